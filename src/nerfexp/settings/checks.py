"""The settings check: ``check_settings`` on the resolved values before anything is built, a bad value
being one line naming the key the user sets (``scale.lr``, not the ``model.optimizer.lr`` it flows into)
and what was expected. Each job is checked once: a single run by the Hydra callback ``SettingsCheck``,
before its directory is made; a sweep's job by ``nerfexp.commands.train`` (Hydra calls no run-start
callback there). Sizes that would not fit in memory are refused with their estimate (``nerfexp.memory``).

The checks name no component's key: they walk the components the config builds
(``nerfexp.settings.components``) and ask each through the attributes it declares beside its class (its domains,
the rules its arguments keep together, what it holds in memory, ...: the list is ``nerfexp.domains``'
docstring), so that a new component brings its own rules.
"""

from collections.abc import Iterator

from hydra.experimental.callback import Callback
from omegaconf import MISSING, DictConfig, OmegaConf

from nerfexp.config_keys import entries, leaves, reference, source_key
from nerfexp.domains import breaks, one_line
from nerfexp.errors import ConfigError, callback_refusals, failures_refused
from nerfexp.extras import SETTINGS_NEEDING, TARGETS_NEEDING, require
from nerfexp.kernels import enabled
from nerfexp.memory import network_bytes, require_memory
from nerfexp.rundir.labels import check_plain_labels
from nerfexp.scoring.perceptual import check_weights_file
from nerfexp.settings.components import argument_keys, argument_problem, asked, components, walked_once
from nerfexp.settings.groups import check_group_values
from nerfexp.settings.overrides import override_values, task_overrides
from nerfexp.settings.rows import check_row
from nerfexp.settings.schema import PASSED_ON, REFERENCES, matching, rule_of
from nerfexp.settings.unused import check_used


def is_reference(key: str, written: object) -> bool:
    """Whether ``key`` is one of ``REFERENCES`` standing for its section (``written``, its value as the config
    writes it, is a plain interpolation, ``nerfexp.config_keys.reference``): not checked there."""
    return key in REFERENCES and reference(written) is not None


def checked_settings(cfg: DictConfig) -> Iterator[tuple[str, object]]:
    """Each setting of ``cfg`` as the checks see it: (dotted key, resolved value), ``hydra`` and each
    ``REFERENCES`` section aside, which is checked where it is set (``nerfexp.config_keys.leaves``)."""
    return leaves(cfg, skip=is_reference)


def named(cfg: DictConfig, key: str, value) -> str:
    """``KEY=VALUE`` as the user sets it: where ``key``'s value comes from another key through plain
    interpolations (``${scale.lr}``, ``nerfexp.config_keys.source_key``), that key, and which key it
    sets; else ``key`` itself. A text with a character that does not print (a newline) is quoted, escaped."""
    source = source_key(cfg, key)
    value = one_line(value)
    return f"{key}={value}" if source == key else f"{source}={value} (which sets {key})"


def check_rules(cfg: DictConfig, strict: bool = True) -> None:
    """A ConfigError for the first leaf whose value breaks its rule (its component's ``DOMAINS``, else
    ``SCHEMA``'s: ``nerfexp.settings.schema.rule_of``), or, where ``strict``, that no rule covers. Keys outside
    ``scale`` come first, so that a scale value is named with the key it sets."""
    found = sorted((item for item in checked_settings(cfg) if item[1] is not MISSING),
                   key=lambda item: item[0].startswith("scale."))
    for key, value in found:
        rule = rule_of(cfg, key)
        if rule is None:
            if strict and matching(PASSED_ON, key) is None:
                raise ConfigError(f"{key}={value}: not a setting nerfexp reads "
                                  "(`nerfexp --cfg job` shows those it reads)")
            continue
        if (wanted := breaks(rule, value)) is not None:
            raise ConfigError(f"{named(cfg, key, value)}: expected {wanted}")


def check_arguments(cfg: DictConfig) -> None:
    """A ConfigError where a component's config does not fit its class (``nerfexp.settings.components.
    argument_problem``: an argument it needs that nothing gives it, or one it does not take), naming the key."""
    for component in components(cfg):
        if (problem := argument_problem(component)) is not None:
            raise ConfigError(problem)


def check_consistent(cfg: DictConfig) -> None:
    """A ConfigError where a component's arguments do not fit together: the first of its ``CONSISTENT`` rules
    (``nerfexp.domains``: a tuple of its argument names -> what is expected, or None) that says what is expected,
    naming those of the arguments its config sets as the user sets them."""
    for component, rules in asked(cfg, "CONSISTENT"):
        for arguments, rule in rules.items():
            if (wanted := rule(component.config)) is not None:
                keys = argument_keys(cfg, component, [a for a in arguments if a in component.config])
                raise ConfigError(f"{settings_named(cfg, keys)}: expected {wanted}")


def settings_named(cfg: DictConfig, keys: list[str]) -> str:
    """``KEY=VALUE, ...``: each of ``keys`` as the user sets it (``named``)."""
    return ", ".join(named(cfg, key, OmegaConf.select(cfg, key)) for key in keys)


# Batches of rays a command renders with every layer's output kept for a backward pass (key, what, training only):
# a training batch, and an evaluation chunk (one layer's outputs at a time); the components that render batches of
# their own (a test-time fit's step) declare theirs (``RAYS``)
BATCHES = (("datamodule.batch_rays", "a training batch", True),  # (key, what, trained: outputs kept; not read back)
           ("model.chunk", "an evaluation chunk", False))


def samples_per_ray(cfg: DictConfig) -> tuple[int, list[str]] | None:
    """The network evaluations per ray and the keys that set them, as the sampler says (``SAMPLES_PER_RAY``);
    None where no component says."""
    for component, samples in asked(cfg, "SAMPLES_PER_RAY"):
        count, arguments = samples(component.config)
        return count, argument_keys(cfg, component, arguments)
    return None


def widest(cfg: DictConfig) -> tuple[tuple[int, list[str]], tuple[int, list[str]]] | None:
    """The most units of a layer and the most layers of the networks every sample passes through (each component
    that declares ``LAYERS``), each with the keys that set it (the first component's where several tie); None
    where no component declares them."""
    layers = [(units, argument_keys(cfg, component, unit_arguments), depth, argument_keys(cfg, component, depth_args))
              for component, declared in asked(cfg, "LAYERS")
              for units, depth, unit_arguments, depth_args in [declared(component.config)]]
    if not layers:
        return None
    units = max(layers, key=lambda layer: layer[0])
    depth = max(layers, key=lambda layer: layer[2])
    return (units[0], units[1]), (depth[2], depth[3])


def check_activations(cfg: DictConfig, training: bool) -> None:
    """A ConfigError naming every setting the estimate multiplies where a batch of rays (``BATCHES``, and each
    component's ``RAYS``: a test-time fit's step) through the networks would need more than the machine's
    memory: rays x samples per ray (the sampler's ``SAMPLES_PER_RAY``) x the widest layer x the most layers
    (``LAYERS``), every layer's outputs kept where the batch is trained (``nerfexp.memory.network_bytes``)."""
    samples, layers = samples_per_ray(cfg), widest(cfg)
    if samples is None or layers is None:
        return
    (count, sample_keys), ((width, width_keys), (depth, depth_keys)) = samples, layers
    batches = [(OmegaConf.select(cfg, key), [key], what, trained) for key, what, trained in BATCHES
               if training or not trained]
    batches += [(rays, argument_keys(cfg, component, arguments), what, True)
                for component, declared in asked(cfg, "RAYS")
                for rays, arguments, what in [declared(component.config)]]
    for rays, keys, what, kept in batches:
        require_memory(settings_named(cfg, [*keys, *sample_keys, *width_keys, *depth_keys]),
                       f"{what} of {rays} rays x {count} samples through {depth} layers of {width} units",
                       network_bytes(rays, count, width, depth, kept))


def training_views(cfg: DictConfig) -> tuple[int, list[str]]:
    """The scene's training views (at least one) and the keys that set them (``TRAINING_VIEWS``)."""
    for component, views in asked(cfg, "TRAINING_VIEWS"):
        count, arguments = views(component.config)
        return count, argument_keys(cfg, component, arguments)
    return 1, []


def check_memory(cfg: DictConfig, training: bool = True) -> None:
    """A ConfigError naming every setting an estimate multiplies (the one a user set among them) where a batch of
    rays through the networks (``check_activations``), or what a component holds once built (its ``MEMORY``:
    a scene's images, a network's weights, the hash tables, the occupancy grid; ``MEMORY_PER_VIEW``: per
    training view, the appearance codes) would need more than the machine's memory (``nerfexp.memory``).
    ``training``: False for a run read back, whose training batch is not estimated."""
    check_activations(cfg, training)
    views, view_keys = training_views(cfg)
    for component in components(cfg):
        items = [(argument_keys(cfg, component, arguments), what, needed)
                 for arguments, what, needed in getattr(component.cls, "MEMORY", lambda config: [])(component.config)]
        per_view = getattr(component.cls, "MEMORY_PER_VIEW", None)
        if per_view is not None:
            items += [([*argument_keys(cfg, component, arguments), *view_keys], what, needed)
                      for arguments, what, needed in per_view(component.config, views)]
        for keys, what, needed in items:
            require_memory(settings_named(cfg, keys), what, needed)


SPARSE_OPTIMIZERS = ("nerfexp.training.optimizers.LazyAdam",)  # take the hash table's sparse gradients


def check_sparse_gradients(cfg: DictConfig) -> None:
    """A ConfigError where a component's gradients are sparse (its ``SPARSE_GRADIENTS``: the boolean arguments
    that, true, make them so) and the optimizer is not one of ``SPARSE_OPTIMIZERS`` (torch.optim.Adam stops at
    the first step on a sparse gradient)."""
    target = OmegaConf.select(cfg, "model.optimizer._target_")
    if target in SPARSE_OPTIMIZERS:
        return
    for component, sparse in asked(cfg, "SPARSE_GRADIENTS"):
        for key in argument_keys(cfg, component, sparse(component.config)):
            raise ConfigError(f"{named(cfg, key, 'true')} and {named(cfg, 'model.optimizer._target_', target)}: "
                              f"expected an optimizer that takes sparse gradients ({', '.join(SPARSE_OPTIMIZERS)}), "
                              f"or set {source_key(cfg, key)}=false")


def check_world_rays(cfg: DictConfig) -> None:
    """A ConfigError where a component that works on world rays (its ``WORLD_RAYS``: the refusal, in words, given
    the setting that makes the scene's rays NDC and the way back to world rays) meets a scene whose rays are NDC
    rays (its ``NDC``: the boolean arguments that, true, make them so, and the ones to set instead)."""
    ndc = [(argument_keys(cfg, scene, arguments), argument_keys(cfg, scene, instead))
           for scene, declared in asked(cfg, "NDC") for arguments, instead in [declared(scene.config)] if arguments]
    if not ndc:
        return
    keys, instead = ndc[0]
    setting = ", ".join(named(cfg, key, "true") for key in keys)
    back = (f"{', '.join(f'{source_key(cfg, key)}=false' for key in keys)} "
            f"(with {' and '.join(source_key(cfg, key) for key in instead)})")
    for _, refusal in asked(cfg, "WORLD_RAYS"):
        raise ConfigError(refusal(setting, back))


def check_extras(cfg: DictConfig) -> None:
    """A MissingExtraError (a ConfigError) where the config asks for a part of nerfexp whose optional
    package is not installed (``nerfexp.extras``: ``TARGETS_NEEDING``, ``SETTINGS_NEEDING``)."""
    for key, target in entries(OmegaConf.to_container(cfg, resolve=False)):
        if key.endswith("._target_") and isinstance(target, str):
            for prefix, (module, needed_for) in TARGETS_NEEDING.items():
                if target.startswith(prefix):
                    require(module, needed_for)
    for key, module in SETTINGS_NEEDING.items():
        if OmegaConf.select(cfg, key, default=None, throw_on_missing=False) is not None:
            require(module, key)


def check_lpips(cfg: DictConfig) -> None:
    """A ConfigError where LPIPS must be scored from a weights file that is not there, or not torchvision's
    published one without ``model.lpips_custom`` saying it is the user's own: the one ``model.lpips_weights``
    names, or the torch hub cache's (``nerfexp.scoring.perceptual.check_weights_file``); the file is read, and
    its SHA-256 taken again, when the model is set up."""
    check_weights_file(OmegaConf.select(cfg, "model.lpips", default=False),
                       OmegaConf.select(cfg, "model.lpips_weights", default=None),
                       OmegaConf.select(cfg, "model.lpips_custom", default=False))


def check_settings(cfg: DictConfig, training: bool = True, scoring: bool = True) -> None:
    """A ConfigError for a ``NERFEXP_KERNELS`` that is not on or off (``nerfexp.kernels.enabled``), a missing
    optional package (first: a component whose package is missing cannot say what its settings are), then the
    first setting that is out of its domain (``check_rules``), a component's config that does not fit its class
    (``check_arguments``: an argument it needs not given), a frequency float32 cannot resolve, a skip
    connection past the field's depth, hash grid levels out of order, ray bounds with near not before far,
    sparse gradients without an optimizer that takes them, a component that needs world rays with NDC rays, a size
    that would not fit in memory, or LPIPS weights
    that must be there and are not (where ``scoring``). ``training``: False for a run read back
    (``check_run_settings``). Any other exception of a check is a ConfigError too (``nerfexp.errors.
    failures_refused``): a check that fails refuses the config."""
    with failures_refused("the settings check"):
        missing = sorted(key for key, value in checked_settings(cfg) if value is MISSING)
        if missing:
            raise ConfigError(f"missing mandatory value: {', '.join(missing)} (set it on the command line, "
                              f"e.g. {missing[0]}=...)")
        enabled()  # the kernels' switch, read now so that a value it does not take stops the run before any work
        check_extras(cfg)  # first: a component whose package is missing cannot say what its settings are
        check_rules(cfg, strict=training)
        with walked_once(cfg):  # the checks below ask the components many times
            check_arguments(cfg)  # first: the rules read the arguments a component is built with
            check_consistent(cfg)
            check_sparse_gradients(cfg)
            check_world_rays(cfg)
            check_memory(cfg, training)
        if scoring:
            check_lpips(cfg)


def check_run_settings(cfg: DictConfig, scoring: bool = False) -> None:
    """``check_settings`` for a run read back (nerfexp-eval, -render, -export, -view): its saved config with the
    user's ``KEY=VALUE`` overrides, checked before anything is built from it, a bad value named as the user set
    it. What only training builds is left out: the keys removed when a run is read back (callbacks, logger,
    ``trainer.default_root_dir``) are not there, and a training batch's memory is not estimated (a run trained
    on a larger machine is read back on a smaller one); a key of a run made by an earlier nerfexp that no rule
    covers is the run's, not a user's mistake, and is passed over. LPIPS's weights are looked for only where
    the command is ``scoring`` the test views (nerfexp-eval): a render needs none."""
    check_settings(cfg, training=False, scoring=scoring)


def check_composition(cfg: DictConfig, hydra: DictConfig) -> None:
    """A ConfigError where what Hydra composed for a run (``cfg``; ``hydra``: its ``hydra`` section, or
    ``HydraConfig.get()``) would not be what the run records: a config group given what is not one of its options
    (``nerfexp.settings.groups.check_group_values``), or a label that is not plain text
    (``nerfexp.rundir.labels.check_plain_labels``), each as a sweep's override sets it for any of its jobs too.
    First of the checks: the others read the groups' choices, and resolve the labels."""
    check_group_values(hydra)
    check_plain_labels(cfg, override_values(task_overrides(hydra)))  # a sweep's: every job's values


class SettingsCheck(Callback):
    """Hydra callback (``hydra.callbacks.settings``): ``check_composition``, ``check_settings`` and ``check_used``
    on a single run's config before Hydra creates its directory, so that a bad value leaves nothing behind; a
    sweep's config (what its jobs share) gets ``check_composition`` before the sweep's directory is made, and each
    job is checked by ``nerfexp.commands.train`` (the sweep's values differ per job). It stops with
    ``SystemExit``, whatever the check raised (``nerfexp.errors.callback_refusals``): Hydra turns a callback's
    exceptions into warnings and goes on."""

    def on_run_start(self, config: DictConfig, **kwargs) -> None:
        with callback_refusals("the settings check"):
            check_composition(config, config.hydra)
            check_settings(config)
            check_row(config, config.hydra.runtime.choices, list(config.hydra.overrides.task))
            check_used(config, list(config.hydra.overrides.task))

    def on_multirun_start(self, config: DictConfig, **kwargs) -> None:
        with callback_refusals("the settings check"):
            check_composition(config, config.hydra)
