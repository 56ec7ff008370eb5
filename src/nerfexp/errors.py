"""Errors that nerfexp reports to the user as one clear line instead of a traceback."""


class NerfexpError(Exception):
    """Base class: bad input or a run that cannot continue, with a message that says what and where."""


class ConfigError(NerfexpError):
    """A config value is missing or unusable; the message names the key."""


class DatasetError(NerfexpError):
    """A dataset is missing or malformed; the message names the file or key and what was expected."""


class NonFiniteError(NerfexpError):
    """Training produced a NaN or infinity; the message names the step, the quantity and the component."""


class FieldCollapseError(NerfexpError):
    """A network's density field went to zero everywhere and stayed there; the message names the step,
    the network and what to try."""
