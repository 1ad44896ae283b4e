"""Micro models, the inference side: miniature versions of the paper's learned models, trained
on the synthetic world so that a CPU runs FreeReg's real code path with *learned* weights.

* :mod:`.models` holds the diffusion architectures (diffusers / transformers classes, small
  configs) and loads the committed weights from ``weights/``;
* :mod:`.depth` the micro ZoeDepth, :mod:`.fcgf` the micro FCGF (architecture, save, load).

This package sits in the models layer beside :mod:`freereg_lib.backends` and never imports
training: rendering the training views, training, evaluation, diagnosis and the model cards are
:mod:`freereg_lib.training`. The model card is ``weights/MODEL_CARD.md``.
"""
