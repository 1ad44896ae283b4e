"""Micro models: miniature versions of the paper's learned models, trained here on the
synthetic world so that a CPU runs FreeReg's real code path with *learned* weights.

* :mod:`.views` renders the training views (seeded, never the evaluation seeds) and makes
  their ControlNet hints exactly as the pipeline does at inference;
* :mod:`.models` holds the architectures (diffusers / transformers classes, small configs)
  and loads the committed weights from ``weights/``;
* :mod:`.train_diffusion` retrains the VAE, the UNet and the depth ControlNet from scratch.

The model card is ``weights/MODEL_CARD.md``.
"""
