"""The vocabulary of settings' domains: a ``Rule`` is what a setting's value must be, in words for the error,
and the test. Components declare the domains of their own arguments next to their class with it
(``DOMAINS``: argument name -> Rule, e.g. ``PositionalEncoding.DOMAINS``), and the settings check
(``nerfexp.settings``) reads them from the class a config's ``_target_`` names; the keys no component owns
have theirs in ``nerfexp.settings.schema.SCHEMA``. Pure Python: every layer may use it, ``nerf/`` included.

A component may also declare when its arguments do nothing (``APPLIES``: argument name -> a function of the
component's own config, resolved as plain data, giving the reason it is unused, or None where it is used),
which the unused-settings check (``nerfexp.settings.unused``) reads the same way.

The settings package names no component's key: it walks the components a composed config builds
(``nerfexp.settings.components``: each once, under the key where it is set, never one its parent's ``APPLIES``
leaves unused) and asks each class for what it declares, all optional; ``config`` is the component's own
arguments, resolved, as plain data, and argument names may be dotted to reach into its own sections:

- ``DOMAINS`` (argument -> ``Rule``) and ``APPLIES`` (argument -> ``Applies``): above.
- ``CONSISTENT`` (a tuple of its arguments -> ``Consistent``): what is expected where those arguments do not fit
  together, or None; refused as ``KEY=VALUE, ...: expected TEXT``, each key as the user sets it
  (``PositionalEncoding``'s frequency limit, ``HashGridEncoding``'s coarsest <= finest, a field's skips).
- ``MEMORY`` (config -> [``Memory``]): what building it holds (a scene's images, a network's weights, a hash table,
  an occupancy grid), each item refused alone where it exceeds the machine's memory (``nerfexp.sizes`` has the
  arithmetic); ``MEMORY_PER_VIEW`` ((config, training views) -> [``Memory``]): the same per training view (the
  appearance codes), the scene's ``TRAINING_VIEWS`` (config -> (views >= 1, arguments)) giving the views.
- The activation memory of a batch of rays spans components: the sampler's ``SAMPLES_PER_RAY`` (config ->
  (network evaluations per ray, arguments)) x the widest and deepest ``LAYERS`` (config -> (units, layers, unit
  arguments, layer arguments): a network every sample passes through) x the rays of the training batch, the
  evaluation chunk and each component's ``RAYS`` (config -> (rays, arguments, what a step renders): a test-time fit).
- The scene's box: a scene's ``SERVES`` (its arguments only other components read: ``aabb``) does nothing unless a
  component built lists it in ``SCENE_FIELDS``; a component's ``REPLACES_SCENE`` (scene argument -> why it does
  nothing) takes a scene setting's place (a contraction's box and far).
- ``SPARSE_GRADIENTS`` (config -> its boolean arguments that, true, make its gradients sparse): the optimizer must
  take them.
- ``NDC`` (a scene's: config -> (arguments that, true, make its rays NDC, arguments to set instead)) and
  ``WORLD_RAYS`` (a component's: (the NDC setting, the way back to world rays) -> its refusal in words).

When each is asked: docs/developing.md.
"""

import math
from collections.abc import Callable, Mapping

# (what is expected, the test); what is expected may be a function that says it, where saying it is dear
Rule = tuple[str | Callable[[], str], Callable[[object], bool]]
# a component's config (its arguments, resolved, as plain data) -> why an argument does nothing, or None
Applies = Callable[[Mapping], str | None]
# a component's config -> what is expected, in words, where some of its arguments do not fit together, or None
Consistent = Callable[[Mapping], str | None]
# what building a component holds: (the arguments that size it, what it is in words, its bytes)
Memory = tuple[tuple[str, ...], str, int]

# Counts (steps, rays, samples, units, views, ...) at most 2^63 - 1: torch and numpy hold whole numbers, and the
# loggers their steps, in 64-bit integers. Counts that size arrays are bounded by the memory estimates too
# (nerfexp.settings.checks.check_memory).
INTEGER_LIMIT = 2 ** 63 - 1


def is_whole(value) -> bool:
    return isinstance(value, int) and not isinstance(value, bool)


def is_real(value) -> bool:
    """A finite number (a whole number of any size is one: it is never converted to a float to be tested)."""
    return isinstance(value, int | float) and not isinstance(value, bool) and (isinstance(value, int)
                                                                             or math.isfinite(value))


def is_power_of_two(value: float) -> bool:
    return value > 0 and float(value).is_integer() and int(value) & (int(value) - 1) == 0


def bound_text(value: float) -> str:
    """A bound as a rule says it: a power of two from 2^20 on as ``2^24``, one less than a power of two
    past 2^32 as ``2^63 - 1``, a whole number in full, another number as ``{:g}`` does."""
    if abs(value) >= 2 ** 20 and is_power_of_two(abs(value)):
        return f"{'-' if value < 0 else ''}2^{int(abs(value)).bit_length() - 1}"
    if value > 2 ** 32 and is_power_of_two(value + 1):
        return f"2^{int(value + 1).bit_length() - 1} - 1"
    return str(value) if isinstance(value, int) else f"{value:g}"


def whole(low: int, high: int | None = None) -> Rule:
    """A whole number in [low, high] (high: None for no upper bound)."""
    expected = f"a whole number >= {low}" if high is None else f"a whole number in [{low}, {bound_text(high)}]"
    return expected, lambda v: is_whole(v) and v >= low and (high is None or v <= high)


def real(low: float, high: float | None = None, *, above: bool = False) -> Rule:
    """A finite number >= ``low`` (> ``low`` where ``above``), and <= ``high`` where given."""
    expected = (f"a finite number {'>' if above else '>='} {bound_text(low)}"
                + ("" if high is None else f" and <= {bound_text(high)}"))
    return expected, lambda v: (is_real(v) and (v > low if above else v >= low)
                                and (high is None or v <= high))


def yaml_word(value) -> str:
    """``value`` as a config writes it: true and false for booleans, null for None."""
    return "null" if value is None else str(value).lower() if isinstance(value, bool) else str(value)


def one_line(value) -> object:
    """``value`` as an error's one line shows it: a text with a character that does not print (a newline, an escape
    sequence) quoted and escaped, as a list's texts are; anything else as it is."""
    return repr(value) if isinstance(value, str) and not value.isprintable() else value


def choice(*values) -> Rule:
    """One of ``values`` (strings or booleans: 1 and 0, equal to True and False, are neither)."""
    return f"one of {', '.join(map(yaml_word, values))}", lambda v: isinstance(v, str | bool) and v in values


def optional(rule: Rule, meaning: str) -> Rule:
    """``rule``, or null meaning ``meaning``."""
    return f"{rule[0]}, or null ({meaning})", lambda v: v is None or rule[1](v)


def expected(rule: Rule) -> str:
    """What ``rule`` expects, in words."""
    return rule[0]() if callable(rule[0]) else rule[0]


def breaks(rule: Rule, value) -> str | None:
    """What ``rule`` expects, in words, where ``value`` breaks it; None where it keeps it."""
    return None if rule[1](value) else expected(rule)


def all_of(*rules: Rule) -> Rule:
    """Every one of ``rules`` (a value several settings read must keep each's): what they expect, each once, joined
    by "and"."""
    def words() -> str:
        return " and ".join(dict.fromkeys(map(expected, rules)))
    return words, lambda v: all(rule[1](v) for rule in rules)


def list_of(rule: Rule, length: int | None = None) -> Rule:
    """A list (of ``length`` items where given) each of which keeps ``rule``."""
    count = "" if length is None else f"{length} "
    return (f"a list of {count}items, each {expected(rule)}",
            lambda v: isinstance(v, list) and (length is None or len(v) == length) and all(map(rule[1], v)))


def whole_list(low: int) -> Rule:
    return f"a list of whole numbers >= {low}", lambda v: isinstance(v, list) and all(whole(low)[1](x) for x in v)


COUNT = whole(1, INTEGER_LIMIT)
NONNEGATIVE_COUNT = whole(0, INTEGER_LIMIT)
FRACTION = real(0, 1)
BOOLEAN = ("true or false", lambda v: isinstance(v, bool))
TEXT = ("a text", lambda v: isinstance(v, str) and v != "")
PATH = ("a path", lambda v: isinstance(v, str) and v != "")
NULL = ("null", lambda v: v is None)

# Numbers several layers' domains share, here so that none imports upward for one.
# How far from the origin a camera, and how far along a ray a sample, may be, in scene units: rays, samples
# and the networks' inputs are float32, whose neighbouring values 2^24 away from 0 are one whole unit apart, so
# beyond it positions have no sub-unit resolution (a scene is a few units across: docs/numerics.md)
POSITION_LIMIT = 2.0 ** 24
# Offsets of a raw density or roughness (a bias, noise) within +-88: exp and softplus of the raw value stay finite
# float32 numbers (exp overflows float32 past log of its largest value, (2 - 2^-23) 2^127, 88.7...)
RAW_LIMIT = math.floor(math.log((2 - 2.0 ** -23) * 2.0 ** 127))
# A loss term's weight at most 2^24: weighted more, the colour loss (about 1 at most) falls below float32's
# resolution of their sum, and training ignores the images
LOSS_WEIGHT_LIMIT = 2.0 ** 24
FLOAT32_TOP_OCTAVE = 18  # the largest k of sin(2^k pi x) still meaningful for float32 positions
# Threads a setting asks for (torch's, COLMAP's) at most 2^16, more CPUs than any machine has (Linux addresses a few
# thousand at most): a larger count is a mistake, never a machine, and OpenMP, asked for it, tries to allocate for
# every thread and aborts the process without a line (torch takes no count past 2^31 - 1 at all). Within it, a count
# above the CPUs this process may use is capped at them where it is applied, with a line (``nerfexp.cpus``).
THREAD_LIMIT = 2 ** 16

NEAR = real(0, POSITION_LIMIT)  # distances along rays, in scene units
FAR = real(0, POSITION_LIMIT, above=True)
RAW_OFFSET = real(-RAW_LIMIT, RAW_LIMIT)
LOSS_WEIGHT = real(0, LOSS_WEIGHT_LIMIT)
THREADS = whole(1, THREAD_LIMIT)
# Adam moves each weight by about the learning rate per step: above 1 a step outweighs the weights themselves
# (initialised within +-1)
LEARNING_RATE = real(0, 1, above=True)


def is_position(value) -> bool:
    """A coordinate in scene units within ``POSITION_LIMIT`` of 0."""
    return is_real(value) and abs(value) <= POSITION_LIMIT


POSITION = ("a finite number within +-2^24", is_position)


BOX = ("[[x0, y0, z0], [x1, y1, z1]] of numbers within +-2^24 with x0 < x1, y0 < y1, z0 < z1, or null",
       lambda v: v is None or (isinstance(v, list) and len(v) == 2 and all(isinstance(c, list) and len(c) == 3
                                                                         and all(map(is_position, c)) for c in v)
                               and all(a < b for a, b in zip(*v))))
