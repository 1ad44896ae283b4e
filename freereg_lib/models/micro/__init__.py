"""Micro models, the inference side: miniature versions of the paper's learned models, trained
on the synthetic world so that a CPU runs FreeReg's real code path with *learned* weights.

* :mod:`.diffusion` holds the diffusion architectures (diffusers / transformers classes, small
  configs) and loads the committed weights from ``weights/``;
* :mod:`.depth` the micro ZoeDepth, :mod:`.fcgf` the micro FCGF (architecture, save, load).

It builds on :mod:`freereg_lib.models`' pieces (``base``, ``diffusion``, ``zoedepth``, ``fcgf``,
``weightcheck``); only :mod:`freereg_lib.models.torch_backends` imports it. It never imports
training: rendering the training views, training, evaluation, diagnosis and the model cards are
:mod:`freereg_lib.training`. The model card is ``weights/MODEL_CARD.md``.
"""
