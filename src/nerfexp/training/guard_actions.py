"""What the training guards (``nerfexp.training.guards``) may do on a non-finite step or a collapse: apart,
so that the settings are checked against them without importing Lightning."""

NONFINITE_ACTIONS = ("stop", "skip")
COLLAPSE_ACTIONS = ("stop", "warn")
