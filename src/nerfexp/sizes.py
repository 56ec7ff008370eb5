"""The bytes that what a component builds holds: pure arithmetic on its sizes, so that a component (in any layer,
``nerf/`` included) can say what it costs beside its class (``MEMORY``, ``nerfexp.domains``), and the memory
check (``nerfexp.memory``, ``nerfexp.settings.checks``) compares it with the machine's memory.
"""

FLOAT = 4  # bytes of a float32
PARAMETER_COPIES = 4  # a trained parameter (a weight, a hash table's entry), its gradient and Adam's two moments
VOXEL_BYTES = FLOAT  # a density per grid cell or point


def parameter_bytes(width: int, depth: int) -> int:
    """The trained weights of a network of ``depth`` hidden layers of ``width`` units, each a ``width`` x
    ``width`` matrix (its inputs aside), with their gradients and optimizer state (``PARAMETER_COPIES``)."""
    return depth * width * width * FLOAT * PARAMETER_COPIES


def hash_table_bytes(n_levels: int, log2_table_size: int, features_per_level: int) -> int:
    """A multiresolution hash encoding's tables and their optimizer state, at most ``2^log2_table_size``
    entries of ``features_per_level`` numbers at each of ``n_levels`` levels."""
    return n_levels * 2 ** log2_table_size * features_per_level * FLOAT * PARAMETER_COPIES


def codes_bytes(n_views: int, dim: int) -> int:
    """Per-image appearance codes: ``n_views`` codes of ``dim`` numbers, trained (``PARAMETER_COPIES``)."""
    return n_views * dim * FLOAT * PARAMETER_COPIES


def grid_bytes(resolution: int) -> int:
    """A grid of ``resolution``^3 densities (the occupancy grid's cells, nerfexp-export's points)."""
    return resolution ** 3 * VOXEL_BYTES
