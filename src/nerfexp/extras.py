"""The optional parts of nerfexp and the pip extra that installs each (``pyproject.toml``): the default
run needs none of them, and a run that does stops before any work with one line naming the extra."""

import importlib
from types import ModuleType

from nerfexp.errors import ConfigError

EXTRAS = {  # module -> the extra that installs it
    "pycolmap": "colmap",
    "imageio_ffmpeg": "video",
    "hydra_plugins.hydra_submitit_launcher": "slurm",
    "viser": "view",
}

# What in a config needs an optional package, here and not beside the component: a component whose module
# imports the package cannot be asked (its class cannot be imported) without it. A class's module (the prefix of
# a ``_target_``) -> (module, what the user chose, in words); a setting -> (module) where it is not null.
TARGETS_NEEDING = {"nerfexp.data.colmap.": ("pycolmap", "data=colmap")}
SETTINGS_NEEDING = {"data.video": "imageio_ffmpeg"}


class MissingExtraError(ConfigError):
    """A feature was asked for whose optional package is not installed; the message names the extra."""


def require(module: str, needed_for: str) -> ModuleType:
    """``module`` imported, or a MissingExtraError saying that ``needed_for`` (what the user asked for,
    e.g. ``data=colmap``) needs the extra that installs it."""
    try:
        return importlib.import_module(module)
    except ModuleNotFoundError as error:
        if error.name is None or not (module == error.name or module.startswith(f"{error.name}.")):
            raise  # the module is there but something it imports is not: not a missing extra
        raise MissingExtraError(f"{needed_for} needs {module}, which is not installed: "
                                f"pip install \"nerfexp[{EXTRAS[module]}]\"") from None
