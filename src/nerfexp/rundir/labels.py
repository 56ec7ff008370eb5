"""A run's labels: free-form ``tags`` (short texts) and ``notes`` (one text) that a researcher attaches to a run
or to a sweep's jobs (``nerfexp tags=[baseline,lego] notes="first try"``), as W&B's tags and notes. A run
records them in ``status.json`` and ``results.json``, its loggers receive them (``nerfexp.training.loggers``),
and ``nerfexp-report`` shows each variant's. They say what a run is for, never what it is: a variant is its
overrides without them (``nerfexp.report.variants``), and a resumed run may change them
(``nerfexp.training.resume.MAY_DIFFER``).

Their domains (``TAGS``, ``NOTES``) keep them whole in every logger (W&B refuses a tag longer than 64
characters; Lightning cuts MLflow's parameters at 250, so MLflow gets them as run tags too) and on one line: no
control character (a newline, an escape sequence) reaches a table, a log line or a terminal.
"""

import unicodedata

from omegaconf import DictConfig, ListConfig, OmegaConf
from omegaconf.errors import OmegaConfBaseException

from nerfexp.domains import Rule

LABELS = ("tags", "notes")  # the config's keys, and the records' (status.json, results.json)
MAX_TAGS = 32
TAG_LENGTH = 64  # W&B's limit
NOTES_LENGTH = 1000
CONTROL = ("Cc", "Zl", "Zp")  # Unicode's control characters, line and paragraph separators


def is_label_text(value, length: int) -> bool:
    """Whether ``value`` is a text of 1 to ``length`` characters, not all blank, without a character of
    ``CONTROL``."""
    return (isinstance(value, str) and 0 < len(value) <= length and not value.isspace()
            and not any(unicodedata.category(c) in CONTROL for c in value))


def is_tags(value) -> bool:
    return (isinstance(value, list) and len(value) <= MAX_TAGS
            and all(is_label_text(tag, TAG_LENGTH) for tag in value))


def is_notes(value) -> bool:
    return value is None or is_label_text(value, NOTES_LENGTH)


TAGS: Rule = (f"a list of at most {MAX_TAGS} tags, each a text of 1 to {TAG_LENGTH} characters without control "
              "characters (tags=[baseline,lego]; a number quoted: tags=['2024'])", is_tags)
NOTES: Rule = (f"a text of 1 to {NOTES_LENGTH} characters without control characters, or null (none)", is_notes)
NO_LABELS = {"tags": [], "notes": None}


def run_labels(cfg: DictConfig) -> dict:
    """The labels of a run's config as plain data, ``{"tags": [...], "notes": text or None}``; one outside its
    domain, or that cannot be resolved, as ``NO_LABELS`` has it (a sweep's job writes its status before its
    settings are checked, and the check then stops it)."""
    labels = dict(NO_LABELS)
    for key, (_, valid) in zip(LABELS, (TAGS, NOTES)):
        try:
            value = OmegaConf.select(cfg, key, default=None)
            value = OmegaConf.to_container(value, resolve=True) if isinstance(value, ListConfig) else value
        except OmegaConfBaseException:
            continue
        if valid(value) and value is not None:
            labels[key] = value
    return labels
