"""A finished (or interrupted) run's files read back as data: ``find_run`` (its directory and checkpoint),
``run_config`` (its config) and ``read_checkpoint`` (the checkpoint's contents); runs made by earlier versions
are read as if made by this one (``MOVED_TARGETS``, ``OLD_SAMPLER_KEYS``, ``MOVED_WEIGHTS``). What is built from them, the model, is a layer above
training (``nerfexp.products.trained``)."""

import contextlib
import io
import pickle
import re
import warnings
import zipfile
from pathlib import Path

import torch
import yaml
from omegaconf import DictConfig, OmegaConf, open_dict
from omegaconf.errors import OmegaConfBaseException

from nerfexp.errors import ConfigError, NerfexpError, failures_refused
from nerfexp.geometry.cameras import poses_problem
from nerfexp.reading import UnreadableFile, read_yaml_text
from nerfexp.rundir.config_shapes import check_own_shapes, with_overrides
from nerfexp.rundir.layout import LAST_CHECKPOINT, REFINED_POSES, RESULTS, RUN_CONFIG, read_json, sha256
from nerfexp.rundir.records import checkpoint_problem
from nerfexp.rundir.saved_configs import as_data, check_resolved
from nerfexp.rundir.state import read_state, unfinished_words

# Where the classes of a run's config lived before the package was split into layers (and the data group
# held the field's density noise), the hash grid before it had a module of its own (nerfexp.nerf.hashgrid), and the
# names the view-dependence axis's classes had while they were called colour heads: a run made by an earlier
# nerfexp is read, and its checkpoint's record compared, as if made by this one. The shims stay until nerfexp 0.2.0
# (SHIMS_UNTIL): the runs made before the layers (commit 591e713, 2026-11-23) are still on researchers' disks,
# under the same version number, 0.1.0; a release may drop them (tests/rundir/test_rundir.py fails once the
# version reaches it with them still here).
SHIMS_UNTIL = (0, 2, 0)
# An entry ending in "." moves every class under it, any other the class it names (``moved_target``); the first
# match of a target wins, so a class moved apart from its module comes before its module's prefix, and a class moved
# twice is followed to where it is now. Callbacks are not read back (saved_configs.TRAINING_ONLY).
MOVED_TARGETS = {
    "nerfexp.nerf.fields.ViewMLPHead": "nerfexp.nerf.fields.MLPViewDependence",
    "nerfexp.nerf.fields.DiffuseHead": "nerfexp.nerf.fields.NoViewDependence",
    "nerfexp.nerf.fields.SphericalHarmonicsHead": "nerfexp.nerf.fields.SphericalHarmonicsViewDependence",
    "nerfexp.nerf.reflection.ReflectionHead": "nerfexp.nerf.reflection.ReflectionViewDependence",
    "nerfexp.nerf.encodings.HashGridEncoding": "nerfexp.nerf.hashgrid.HashGridEncoding",
    "nerfexp.module.": "nerfexp.training.module.",
    "nerfexp.guards.": "nerfexp.training.guards.",
    "nerfexp.renderer.": "nerfexp.nerf.volume_renderer.",
    "nerfexp.fields.": "nerfexp.nerf.fields.",
    "nerfexp.encodings.": "nerfexp.nerf.encodings.",
    "nerfexp.occupancy.": "nerfexp.nerf.occupancy.",
}
TARGET_IN_TEXT = re.compile(r"(_target_: )([\w.]+)")  # a ``_target_`` in a config's YAML text: the key and its class
OLD_NOISE = "density_noise_std: ${oc.select:data.density_noise_std,0.0}"  # the field's line while data held it
# The renderer's arguments that chose and sized its sampler before the sampler was a component of its own (the
# ``sampler`` config group, ``nerfexp.nerf.hierarchy.HierarchyChoice``); a run made then is read with them moved
# there (``moved_sampler``), and its checkpoint's proposal networks under the sampler's name (``current_weights``).
# Runs made before the sampler group are on researchers' disks under the same version number: these shims stay
# until SHIMS_UNTIL too.
OLD_SAMPLER_KEYS = ("hierarchical", "n_coarse", "n_fine", "n_single", "proposal")
HIERARCHY_CHOICE = "nerfexp.nerf.hierarchy.HierarchyChoice"
MOVED_WEIGHTS = {"renderer.proposal.": "renderer.sampler."}  # a checkpoint's state_dict names: old prefix -> new
# The hash grid's sizes while the scale group held them: a checkpoint of then records them beside the encoding's
# own keys (encoding.position.log2_table_size, .finest), which it is compared by (``current_settings``).
OLD_SCALE_KEYS = ("scale.hash_log2_table_size", "scale.hash_finest")


def find_run(path: str | Path) -> tuple[Path, Path]:
    """``(run directory, checkpoint)`` of ``path``: a run directory (the checkpoint its final test scored,
    as ``results.json`` records it, checked against its SHA-256; else ``checkpoints/last.ckpt``) or a
    checkpoint file in one (``RUN_DIR/checkpoints/NAME.ckpt``: the run directory two levels up). A run that saved
    no checkpoint is a NerfexpError saying so, and where its status says it did not finish, how
    (``nerfexp.rundir.state.unfinished_words``: killed, failed, still running); a reader of a checkpoint of such a
    run says so too (``nerfexp.rundir.state.unfinished_line``)."""
    path = Path(path)
    if not path.exists():
        raise NerfexpError(f"{path} does not exist: expected a run directory or a checkpoint file in one")
    run_dir, checkpoint = (path, path / LAST_CHECKPOINT) if path.is_dir() else (path.parent.parent, path)
    if not (run_dir / RUN_CONFIG).is_file():
        raise NerfexpError(f"{run_dir} is not a run directory: it has no {RUN_CONFIG}")
    results = read_json(run_dir / RESULTS) if path.is_dir() else None
    if results is not None and (problem := checkpoint_problem(results)) is not None:
        raise NerfexpError(f"{run_dir / RESULTS}: {problem}: name a checkpoint file to use one")
    tested = None if results is None else results.get("checkpoint")
    if tested is not None:
        checkpoint = run_dir / tested["path"]
        if checkpoint.is_file() and sha256(checkpoint) != tested["sha256"]:
            raise NerfexpError(f"{checkpoint} is not the checkpoint the run's test scored (its SHA-256 differs "
                               f"from {run_dir / RESULTS}'s): name a checkpoint file to use it anyway")
    if not checkpoint.is_file():
        ended = unfinished_words(read_state(run_dir))  # why, where its status says (nerfexp.rundir.state)
        raise NerfexpError(f"{checkpoint} does not exist: the run in {run_dir} has saved no checkpoint"
                           + ("" if ended is None else f"; it {ended}"))
    return run_dir, checkpoint


def _current(text: str, source: Path) -> DictConfig:
    """A run config's text (read from ``source``) as this version's config, read as data
    (``nerfexp.rundir.saved_configs.as_data``, before anything in it is resolved) in the shapes nerfexp's own configs
    give its keys (``nerfexp.rundir.config_shapes.check_own_shapes``): ``MOVED_TARGETS`` paths made
    current, and ``data.density_noise_std`` moved to ``model.renderer.field`` (``OLD_NOISE``: the field
    once read it with a resolver, whose default was 0.0), and the renderer's sampler settings moved to the ``sampler``
    section (``moved_sampler``)."""
    text = TARGET_IN_TEXT.sub(lambda found: found[1] + moved_target(found[2]), text)
    cfg = OmegaConf.create(text.replace(OLD_NOISE, "density_noise_std: 0.0"))
    if not isinstance(cfg, DictConfig):
        raise ConfigError(f"{source}: not a config nerfexp can read (a mapping of keys was expected)")
    cfg = as_data(moved_sampler(cfg), source)
    # a section that a reference lands at another's key is named by its class first, where the file resolves (a
    # reference that leads nowhere is named once the overrides are applied: one of them may mend it)
    with contextlib.suppress(OmegaConfBaseException):
        check_resolved(OmegaConf.to_container(cfg, resolve=True), source)
    check_own_shapes(cfg, source)
    if "density_noise_std" in cfg.get("data", {}):
        with open_dict(cfg):
            cfg.model.renderer.field.density_noise_std = cfg.data.pop("density_noise_std")
    return cfg


def moved_target(target: str) -> str:
    """The class path ``target`` where this version has the class: made current by the first entry of
    ``MOVED_TARGETS`` that names it (the class itself, or a prefix ending in "." of its module), and so again where
    that entry's path moved later, else unchanged.

    >>> moved_target("nerfexp.encodings.PositionalEncoding")
    'nerfexp.nerf.encodings.PositionalEncoding'
    >>> moved_target("nerfexp.nerf.encodings.HashGridEncoding")
    'nerfexp.nerf.hashgrid.HashGridEncoding'
    >>> moved_target("nerfexp.fields.ViewMLPHead")  # to nerfexp.nerf.fields, then renamed
    'nerfexp.nerf.fields.MLPViewDependence'
    """
    seen = set()
    while target not in seen:  # each move once: an entry that leads back to a path already taken ends the chain
        seen.add(target)
        old = next((old for old in MOVED_TARGETS
                    if target == old or (old.endswith(".") and target.startswith(old))), None)
        if old is None:
            break
        target = MOVED_TARGETS[old] + target.removeprefix(old)
    return target


def moved_sampler(cfg: DictConfig) -> DictConfig:
    """A run config (nothing resolved) whose renderer held its sampler's settings (``OLD_SAMPLER_KEYS``) as this
    version's: those keys, as written, in a top-level ``sampler`` section that builds the sampler they name
    (``HIERARCHY_CHOICE``, what ``conf/sampler/paper.yaml`` writes), and the renderer's ``sampler`` a reference to
    it; any other config unchanged."""
    plain = OmegaConf.to_container(cfg, resolve=False)
    renderer = plain.get("model", {}).get("renderer") if isinstance(plain.get("model"), dict) else None
    if not isinstance(renderer, dict) or "hierarchical" not in renderer or "sampler" in renderer \
            or "sampler" in plain:
        return cfg
    plain["sampler"] = {"_target_": HIERARCHY_CHOICE,
                        **{key: renderer.pop(key) for key in OLD_SAMPLER_KEYS if key in renderer}}
    renderer["sampler"] = "${sampler}"
    return OmegaConf.create(plain)


def current_settings(settings: dict[str, object]) -> dict[str, object]:
    """A checkpoint's recorded settings ({dotted key: resolved value}, ``nerfexp.training.resume.flat_settings``) as
    this version names them: a renderer's sampler keys (``OLD_SAMPLER_KEYS``, ``model.renderer.n_fine``) under the
    sampler, where this version records them twice (``model.renderer.sampler.n_fine``, and ``sampler.n_fine`` where
    the section is set: ``moved_sampler``), ``OLD_SCALE_KEYS`` left out, and every ``_target_`` where its class is
    now (``moved_target``); any other record unchanged."""
    renderer = "model.renderer."
    moved = {}
    for key, value in settings.items():
        argument = key.removeprefix(renderer)
        if key in OLD_SCALE_KEYS:
            continue
        if key.startswith(renderer) and argument.split(".")[0] in OLD_SAMPLER_KEYS \
                and f"{renderer}hierarchical" in settings:
            moved[f"{renderer}sampler.{argument}"] = moved[f"sampler.{argument}"] = value
        elif key.split(".")[-1] == "_target_" and isinstance(value, str):
            moved[key] = moved_target(value)
        else:
            moved[key] = value
    return moved


def current_weights(state_dict: dict) -> None:
    """A checkpoint's ``state_dict`` made this version's, in place: the names ``MOVED_WEIGHTS`` moved."""
    for name in [name for name in state_dict if name.startswith(tuple(MOVED_WEIGHTS))]:
        old = next(prefix for prefix in MOVED_WEIGHTS if name.startswith(prefix))
        state_dict[MOVED_WEIGHTS[old] + name.removeprefix(old)] = state_dict.pop(name)


def run_config(run_dir: Path, overrides: list[str] = ()) -> DictConfig:
    """The config a run used (its ``RUN_CONFIG``), with ``KEY=VALUE`` ``overrides`` of existing keys
    (e.g. ``data.root=...`` for a scene that moved). The file is read as data: a ``_target_`` in it that
    is not one of the classes nerfexp builds, or an interpolation that is not a plain reference to another
    of its keys, is a ConfigError (``nerfexp.rundir.saved_configs``), and the keys only training builds are left
    out; so is a key whose shape nerfexp's own configs do not give it (``_current``: a value where they have a
    section, a section without its class, another ``_partial_``), and an override that changes a shape of the run's
    config (``nerfexp.rundir.config_shapes.with_overrides``). A reference that the config cannot follow, or a value
    that resolves to text holding ``${`` (``check_resolved``), is a ConfigError naming the key, before anything is
    built. The file is read bounded (``nerfexp.reading.read_yaml_text``: its size, no YAML aliases)."""
    source = Path(run_dir) / RUN_CONFIG
    with failures_refused(f"the check of {source}"):  # whatever the checks below raise, a refusal
        try:
            cfg = _current(read_yaml_text(source), source)
        except UnreadableFile as error:
            raise ConfigError(f"{source}: not a config nerfexp can read ({error.reason})") from None
        except (OmegaConfBaseException, yaml.YAMLError) as error:
            raise ConfigError(f"{source}: not a config nerfexp can read ({str(error).splitlines()[0]})") from None
        OmegaConf.set_struct(cfg, True)  # an override of a key the run does not have is a typo, not a new key
        cfg = with_overrides(cfg, list(overrides), source)
        try:
            resolved = OmegaConf.to_container(cfg, resolve=True)  # plain references (and the overrides'): nothing runs
        except OmegaConfBaseException as error:
            where = f" at {error.full_key}" if error.full_key else ""
            raise ConfigError(f"{source}: cannot resolve the config{where}: {str(error).splitlines()[0]}") from None
        check_resolved(resolved, source)
    return cfg


def not_a_checkpoint(source: Path | io.BytesIO, error: Exception) -> str:
    """What file ``source`` (a path, or a file's bytes already read), which ``torch.load`` could not read as data
    (``error``), is, in a few words: never torch's own message, whose advice to load it with
    ``weights_only=False`` would run any code it holds."""
    if (source.getbuffer().nbytes if isinstance(source, io.BytesIO) else source.stat().st_size) == 0:
        return "an empty file"
    if not zipfile.is_zipfile(source):
        return "not a whole zip archive as torch.save writes: cut short, or another kind of file"
    if isinstance(error, pickle.UnpicklingError):
        return "it holds objects other than tensors, numbers, strings and containers of them"
    return "a damaged zip archive"


def load_as_data(path: Path, what: str, kind: str = "checkpoints",
                 error_type: type[NerfexpError] = NerfexpError, data: bytes | None = None) -> object:
    """What ``torch.save`` wrote to ``path``, read as data (``weights_only``: tensors and plain containers; a
    pickle that would run code is refused), on the CPU; an ``error_type`` naming the file, ``what`` it
    should be (e.g. "a checkpoint") and what it is, where it cannot be read so (``kind``: such files).
    ``data``: the file's bytes where the caller has read them already (to check their SHA-256), read in place
    of the file, so that what was checked is what is loaded."""
    source = path if data is None else io.BytesIO(data)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # torch's notes on pickle protocols: the error below says what matters
            return torch.load(source, map_location="cpu", weights_only=True)
    except OSError as error:
        raise error_type(f"{path}: cannot read {what} ({error.strerror})") from None
    except Exception as error:  # torch raises any type (IndexError, KeyError, ...) on bytes it cannot parse
        raise error_type(f"{path}: not {what} ({not_a_checkpoint(source, error)}); nerfexp reads {kind} as data "
                         "only, never running code in them") from None


def read_checkpoint(path: Path) -> dict:
    """A Lightning checkpoint's contents read as data (``load_as_data``); a NerfexpError naming the file
    otherwise."""
    path = Path(path)
    if not path.is_file():
        raise NerfexpError(f"{path}: no such checkpoint file")
    state = load_as_data(path, "a checkpoint")
    if not isinstance(state, dict) or not isinstance(state.get("state_dict"), dict) or "global_step" not in state:
        raise NerfexpError(f"{path}: not a Lightning checkpoint (expected a state_dict and a global_step)")
    return state


def read_refined_poses(run_dir: Path) -> torch.Tensor | None:
    """The training cameras c2w [N, 4, 4] (float64) as the run's camera refinement left them (its
    ``REFINED_POSES``, read as data: ``nerfexp.training.pose_records``); None where the run has no such file (it
    did not refine its cameras). A file whose ``c2w`` is not a list of rigid 4 x 4 camera poses within 2^24 scene
    units of the origin (``nerfexp.geometry.cameras.pose_problem``) is a NerfexpError naming it."""
    path = Path(run_dir) / REFINED_POSES
    record = read_json(path)
    if record is None:
        return None
    c2w = record.get("c2w") if isinstance(record, dict) else None
    if (problem := poses_problem(c2w)) is not None:
        raise NerfexpError(f"{path}: not a record of refined cameras (expected c2w, a non-empty list of 4 x 4 rigid "
                           f"camera-to-world matrices): {problem}")
    return torch.tensor(c2w, dtype=torch.float64)
