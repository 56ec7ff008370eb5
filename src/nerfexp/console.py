"""What nerfexp's commands print: their own lines and progress bars, not their dependencies' notices.

Lightning announces at INFO what nerfexp's own lines already say or what no run needs (the
accelerators found, a tip advertising a package, each checkpoint restored or saved without
``weights_only``); its warnings still show. Dependency warnings are filtered one by one, each by its
message, category and the module it is attributed to, so that a new warning is never hidden."""

import logging
import warnings

LIGHTNING_NOTICES = (  # loggers whose INFO lines are Lightning's notices (their warnings still show)
    "lightning.pytorch.utilities.rank_zero",  # GPU/TPU available, the litlogger tip, "Restoring states ..."
    "lightning.fabric.utilities.rank_zero",
    "lightning.pytorch.trainer.connectors.checkpoint_connector",  # "`weights_only` was not set ..."
)
DEPENDENCY_WARNINGS = (  # (message regex, category, module regex): warnings about a dependency's own code
    # torch deprecated LeafSpec (2.13 warns), which Lightning 2.6 still builds (lightning/pytorch/utilities/_pytree.py)
    (r"`isinstance\(treespec, LeafSpec\)` is deprecated", FutureWarning, r"lightning\.pytorch\.utilities\._pytree"),
)


def quiet_dependencies() -> None:
    """Silence ``LIGHTNING_NOTICES``' INFO lines and ignore ``DEPENDENCY_WARNINGS``, for this process."""
    for name in LIGHTNING_NOTICES:
        logging.getLogger(name).setLevel(logging.WARNING)
    for message, category, module in DEPENDENCY_WARNINGS:
        warnings.filterwarnings("ignore", message=message, category=category, module=module)
