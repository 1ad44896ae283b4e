"""Training, evaluation, diagnosis and model cards of the micro models (commands layer).

* :mod:`.views` renders the training views (seeded, never the evaluation seeds) and makes
  their ControlNet hints exactly as the pipeline does at inference;
* :mod:`.train_diffusion` retrains the VAE, the UNet and the depth ControlNet from scratch,
  :mod:`.retrain` reruns the committed schedule; :mod:`.train_depth`, :mod:`.train_fcgf` the
  micro ZoeDepth and FCGF;
* :mod:`.evaluate`, :mod:`.evaluate_depth`, :mod:`.evaluate_fcgf`, :mod:`.diagnose` measure them
  on synthetic pairs no training room reaches (the development set and the test split,
  :mod:`.splits`; :mod:`.evaluate_split`, :mod:`.evaluate_layers`, :mod:`.fusion_sweep`);
  :mod:`.card` writes the model cards beside the weights.

Each is a ``python -m freereg_lib.training.<name>`` command. The library (pipeline, models,
:mod:`freereg_lib.models.micro`, which holds the architectures and loads the weights) never imports
this package (``tests/test_layers.py``).
"""
