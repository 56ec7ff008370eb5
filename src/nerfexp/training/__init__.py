"""Training with Lightning: the LightningModule, its callbacks, the training guards and the run recorders."""
