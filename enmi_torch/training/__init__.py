"""Training with Lightning (the ``train`` extra): the mask-fitting module, its figure and the fit-mask command."""
