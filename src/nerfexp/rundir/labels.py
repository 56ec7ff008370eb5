"""A run's labels: free-form ``tags`` (short texts) and ``notes`` (one text) that a researcher attaches to a run
or to a sweep's jobs (``nerfexp tags=[baseline,lego] notes="first try"``), as W&B's tags and notes. A run
records them in ``status.json`` and ``results.json``, its loggers receive them (``nerfexp.training.loggers``),
and ``nerfexp-report`` shows each variant's. They say what a run is for, never what it is: a variant is its
overrides without them (``nerfexp.report.variants``), and a resumed run may change them
(``nerfexp.training.resume.MAY_DIFFER``).

Their domains (``TAGS``, ``NOTES``) keep them whole in every logger (W&B refuses a tag longer than 64
characters; Lightning cuts MLflow's parameters at 250, so MLflow gets them as run tags too) and on one line: no
control character (a newline, an escape sequence) reaches a table, a log line or a terminal.

They are text, recorded as written and never resolved: a label that holds ``${`` (an interpolation, a resolver's
``${oc.env:HOME}`` or ``${now:%Y}``, an escaped ``\\${x}``) is refused in one line before any work
(``check_plain_labels``). Resolved, it would be recorded as one text in ``results.json`` and kept as the
interpolation in the run's saved config, which resolves to another text later, or which the commands that read a
run back refuse (``nerfexp.rundir.saved_configs``); so what the records say and what the saved config says are
the same text.
"""

import unicodedata
from collections.abc import Iterable

from omegaconf import DictConfig, OmegaConf

from nerfexp.domains import Rule, one_line
from nerfexp.errors import ConfigError

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


def written_labels(cfg: DictConfig) -> dict:
    """The labels of a run's config as it writes them, plain data, nothing resolved: ``{"tags": ..., "notes":
    ...}``, a label the config does not have as None."""
    plain = OmegaConf.to_container(cfg, resolve=False)
    return {key: plain.get(key) for key in LABELS}


def texts(value) -> list[str]:
    """Every text in ``value``: itself, or the texts at any depth of its lists and mappings (keys included)."""
    if isinstance(value, str):
        return [value]
    if isinstance(value, dict):
        return [text for pair in value.items() for item in pair for text in texts(item)]
    return [text for item in value for text in texts(item)] if isinstance(value, list | tuple) else []


def is_plain(value) -> bool:
    """Whether no text in ``value`` holds ``${``: nothing OmegaConf would resolve, nor an escaped interpolation
    that it would resolve to the text of one."""
    return not any("${" in text for text in texts(value))


def plain_label_refusal(said: str) -> ConfigError:
    """The one line refusing a label that holds ``${``, ``said`` as ``KEY=VALUE``."""
    return ConfigError(f"{said}: expected plain text: tags and notes are recorded as written, never resolved, so "
                       "they cannot hold '${' (an interpolation); write the text itself")


def check_plain_labels(cfg: DictConfig, overrides: Iterable[tuple[str, str, list]] = ()) -> None:
    """A ConfigError for the first label that, as written, holds ``${`` (``is_plain``): among ``overrides``
    (``(argument, key, values)``: each override's key and every value it sets, a sweep's each job's:
    ``nerfexp.settings.overrides.override_values``), named as given, then in ``cfg``, named by its key (each on one
    line: ``nerfexp.domains.one_line``). Checked before anything resolves a label (a resolver may fail, or read the
    environment)."""
    for argument, key, values in overrides:
        if key in LABELS and not all(is_plain(value) for value in values):
            raise plain_label_refusal(one_line(argument))
    for key, value in written_labels(cfg).items():
        if not is_plain(value):
            raise plain_label_refusal(f"{key}={one_line(value)}")


def run_labels(cfg: DictConfig) -> dict:
    """The labels of a run's config as plain data, as it writes them (never resolved), ``{"tags": [...],
    "notes": text or None}``; one outside its domain, or not plain text (``is_plain``), as ``NO_LABELS`` has it
    (a sweep's job writes its status before its settings are checked, and the check then stops it)."""
    labels = dict(NO_LABELS)
    for (key, value), (_, valid) in zip(written_labels(cfg).items(), (TAGS, NOTES)):
        if is_plain(value) and valid(value) and value is not None:
            labels[key] = value
    return labels
