"""Settings that do nothing with the rest of the config: ``APPLIES`` lists the keys that do something only
with certain other settings (``scale.n_fine`` only with ``hierarchical=true``). A user's override of one
that does not apply stops a single run (``check_used``); in a sweep, whose jobs combine values, the job
runs and its record holds null for it (``without_unused``).
"""

from collections.abc import Callable

from omegaconf import DictConfig, OmegaConf

from nerfexp.config_keys import entries, reference
from nerfexp.errors import ConfigError
from nerfexp.settings.schema import matching

HIERARCHY_SAMPLES = {  # what each choice of the sampling axis reads, as said when another key is set
    True: "hierarchical=true (a coarse network of model.renderer.n_coarse samples and a fine one of n_coarse + "
          "n_fine; set scale.n_coarse and scale.n_fine)",
    False: "hierarchical=false (one network of model.renderer.n_single samples; set scale.n_single)",
    "proposal": "hierarchical=proposal (proposal networks choose the samples; set proposal.n_samples and "
                "proposal.n_final)",
}


def hierarchy_reads(choice: bool | str) -> Callable[[DictConfig], str | None]:
    """The reason a key is unused unless ``hierarchical`` is ``choice``."""
    def reason(cfg: DictConfig) -> str | None:
        return None if cfg.hierarchical == choice else HIERARCHY_SAMPLES[cfg.hierarchical]
    return reason


hierarchical_only, single_only, proposal_only = (hierarchy_reads(c) for c in (True, False, "proposal"))


def needs(section: str, key: str, group: str) -> Callable[[DictConfig], str | None]:
    """The reason a key is unused unless ``section`` has ``key``: the choice of ``group`` made it absent."""
    def reason(cfg: DictConfig) -> str | None:
        node = OmegaConf.select(cfg, section)
        return None if isinstance(node, DictConfig) and key in node else f"this {group} (it has no {section}.{key})"
    return reason


def video_only(cfg: DictConfig) -> str | None:
    return None if OmegaConf.select(cfg, "data.video") is not None else "data.video=null (photographs, not a video)"


def lpips_scored(cfg: DictConfig) -> str | None:
    return None if cfg.model.lpips is not False else "model.lpips=false (LPIPS is not scored)"


def boxed(cfg: DictConfig) -> str | None:
    uses = OmegaConf.select(cfg, "acceleration.grid") is not None or "log2_table_size" in cfg.encoding.position
    return None if uses else "acceleration=none and encoding other than hashgrid (nothing reads the box)"


# Keys that do something only with certain other settings: key pattern -> why it is unused (None: it is used).
APPLIES: dict[str, Callable[[DictConfig], str | None]] = {
    "scale.n_coarse": hierarchical_only,
    "scale.n_fine": hierarchical_only,
    "model.renderer.n_coarse": hierarchical_only,
    "model.renderer.n_fine": hierarchical_only,
    "scale.n_single": single_only,
    "model.renderer.n_single": single_only,
    "proposal.*": proposal_only,
    "scale.view_hidden": needs("view_dependence", "hidden", "view_dependence"),
    "scale.position_input_scale": needs("encoding.position", "input_scale", "encoding"),
    "scale.hash_*": needs("encoding.position", "log2_table_size", "encoding"),
    "scale.image_size": needs("data", "image_size", "data"),
    "scale.max_side": needs("data", "max_side", "data"),
    "scale.test_stride": needs("data", "test_stride", "data"),
    "data.fps": video_only,
    "data.aabb": boxed,
    "model.lpips_weights": lpips_scored,
}


def overridden_key(override: str) -> str:
    """The key of a Hydra override (``+scale.n_fine=64`` -> ``scale.n_fine``)."""
    return override.split("=", 1)[0].lstrip("+~")


def unused_settings(cfg: DictConfig, overrides: list[str]) -> list[tuple[str, str]]:
    """The ``overrides`` a user gave whose key does nothing with the rest of ``cfg`` (``APPLIES``), each
    with the reason: [(override, reason)]. Defaults the user did not set are never listed."""
    unused = []
    for override in overrides:
        pattern = matching(APPLIES, overridden_key(override))
        reason = APPLIES[pattern](cfg) if pattern else None
        if reason:
            unused.append((override, reason))
    return unused


def without_unused(cfg: DictConfig, resolved: dict, overrides: list[str]) -> dict:
    """``resolved`` (``cfg`` resolved, as a run records it) with null for each key of ``overrides`` (unused
    settings of a sweep's job, ``unused_settings``) and for each key that is a plain interpolation of one
    (``model.renderer.n_fine: ${scale.n_fine}``): the record says what the run used, not what was asked."""
    keys = {overridden_key(o) for o in overrides}
    keys |= {key for key, raw in entries(OmegaConf.to_container(cfg, resolve=False)) if reference(raw) in keys}
    recorded = OmegaConf.create(resolved)
    for key in keys:
        OmegaConf.update(recorded, key, None, force_add=False)
    return OmegaConf.to_container(recorded)


def check_used(cfg: DictConfig, overrides: list[str]) -> None:
    """A ConfigError for the first of ``overrides`` that does nothing (``unused_settings``)."""
    for override, reason in unused_settings(cfg, overrides)[:1]:
        raise ConfigError(f"{override}: not used with {reason}")

