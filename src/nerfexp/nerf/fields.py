"""The radiance field F(x, d) -> (rgb, sigma): the paper's MLP with a swappable view-dependence head (a
``ViewDependence``), answering ``FieldOutputs``."""

import copy
from collections.abc import Callable, Mapping
from typing import ClassVar, NamedTuple

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from nerfexp.domains import (
    COUNT,
    RAW_LIMIT,
    RAW_OFFSET,
    Applies,
    Consistent,
    Memory,
    Rule,
    choice,
    real,
    whole,
    whole_list,
)
from nerfexp.nerf.encodings import Encoding
from nerfexp.sizes import parameter_bytes

TRUNC_EXP_GRADIENT_CLAMP = 15.0  # the gradient of trunc_exp is at most e^15 = 3.3e6 per unit of upstream gradient


class _TruncatedExp(torch.autograd.Function):
    """exp(x) that never overflows, with a bounded gradient (the "truncated exponential" of Instant-NGP).

    Forward: min(exp(x), largest float), so sigma is finite whatever the network outputs (an overflow
    to inf would make d sigma / dx inf and the loss gradient nan). Backward: exp(min(x, 15)), so one
    huge pre-activation cannot send a huge update through the network; below 15 it is the exact gradient.
    """

    @staticmethod
    def forward(ctx, x: Tensor) -> Tensor:
        ctx.save_for_backward(x)
        return torch.exp(x).clamp(max=torch.finfo(x.dtype).max)  # an overflow to inf becomes the largest float

    @staticmethod
    def backward(ctx, grad: Tensor) -> Tensor:
        (x,) = ctx.saved_tensors
        return grad * torch.exp(x.clamp(max=TRUNC_EXP_GRADIENT_CLAMP))


def trunc_exp(x: Tensor) -> Tensor:
    """Density exp(x), finite for any x, with gradients bounded by e^15 (see ``_TruncatedExp``)."""
    return _TruncatedExp.apply(x)


DENSITY_ACTIVATIONS: dict[str, Callable[[Tensor], Tensor]] = {
    "relu": F.relu,  # the paper's; its gradient is zero wherever the field is empty, so it can die
    "softplus": F.softplus,  # never has a zero gradient, so a field that went empty recovers; linear above 20
    "trunc_exp": trunc_exp,  # exp (Instant-NGP, Plenoxels-style): densities span decades at equal step sizes
}


class FieldOutputs(NamedTuple):
    """What a field answers at samples [..., S], by name (nerfstudio's field heads)."""

    rgb: Tensor | None  # [..., S, 3] in [0, 1]; None for a density-only query
    sigma: Tensor  # [..., S] >= 0
    penalties: Tensor | None = None  # [..., S, P]: the colour head's weighted penalties (``penalty_names``), or None


class PositionalOutputs(NamedTuple):
    """What a colour field computes of positions alone, before its colour head (``NeRFField.positional``)."""

    sigma: Tensor  # [...] >= 0, as the field answers it (with training noise in training)
    features: Tensor  # [..., F]: the trunk's output, which the colour head reads
    gradient: Tensor | None = None  # [..., 3]: d raw / dx, where the head predicts normals in training; else None


class ViewDependence(nn.Module):
    """The view-dependence axis's component: the field's trunk features h [..., S, F] and unit view directions
    [..., S or 1, 3] (one per ray broadcasts over its samples) -> rgb [..., S, 3] in [0, 1].

    The field builds it from the trunk width (``in_features``, its first argument). A head with ``uses_normals``
    answers (rgb, predicted normals [..., S, 3]) instead, and the field asks its ``penalties`` of the density's
    gradient, weighted by ``penalty_weights`` [P] and named ``penalty_names`` (Ref-NeRF's,
    ``nerfexp.nerf.reflection``); the others have none. ``DOMAINS`` and ``APPLIES`` declare its constructor's
    settings (``nerfexp.domains``).
    """

    DOMAINS: ClassVar[dict[str, Rule]] = {}
    APPLIES: ClassVar[dict[str, Applies]] = {}
    uses_normals: ClassVar[bool] = False
    penalty_names: ClassVar[tuple[str, ...]] = ()

    def __init__(self):
        super().__init__()
        self.register_buffer("penalty_weights", torch.zeros(len(self.penalty_names)), persistent=False)  # [P]

    def penalties(self, normals: Tensor, gradient: Tensor, directions: Tensor) -> Tensor:
        """The per-sample penalties [..., S, P], unweighted, of the predicted ``normals`` [..., S, 3] given the
        density's ``gradient`` d raw / dx [..., S, 3] and the unit ``directions`` [..., S or 1, 3]; asked only
        of a head with ``uses_normals``."""
        raise NotImplementedError(f"{type(self).__name__} predicts no normals")


def skips_within(skips: list[int], depth: int) -> str | None:
    """What is expected of skip connections ``skips`` that name a layer a trunk of ``depth`` layers does not join
    the input to (1..depth-1), else None."""
    return None if all(0 < s < depth for s in skips) else f"layer indices in 1..{depth - 1} for depth {depth}"


class DensityField(nn.Module):
    """sigma from the encoded position alone: a trunk of ReLU layers and one linear density unit.

    Trunk: ``depth`` ReLU layers of ``width``; the encoded position is concatenated again to the
    input of each layer listed in ``skips`` (0-based: the paper's 8 x 256 joins it to the fifth
    layer's output, the sixth layer's input, so ``skips=[5]``). The density is
    ``activation(raw + density_bias)`` of one linear unit on the trunk output. On its own, a proposal
    network (``nerfexp.nerf.proposal``); with a colour head, ``NeRFField``.

    Args:
        position_encoding: maps [..., 3] -> [..., out_dim].
        density_activation: a key of ``DENSITY_ACTIVATIONS``.
    """

    DOMAINS: ClassVar[dict[str, Rule]] = {
        "depth": COUNT,
        "width": COUNT,
        "skips": whole_list(0),
        "density_activation": choice(*DENSITY_ACTIVATIONS),
        "density_bias": RAW_OFFSET,
    }
    APPLIES: ClassVar[dict[str, Applies]] = {}
    CONSISTENT: ClassVar[dict[tuple[str, ...], Consistent]] = {("skips", "depth"): lambda config: skips_within(
        config["skips"], config["depth"])}
    NAME: ClassVar[str] = "a proposal network"  # what it is, in the memory estimate's words: on its own, one

    @classmethod
    def MEMORY(cls, config: Mapping) -> list[Memory]:
        """Its trunk's weights and their optimizer state."""
        return [(("width", "depth"), f"training {cls.NAME} of {config['depth']} layers of {config['width']} units",
                 parameter_bytes(config["width"], config["depth"]))]

    def __init__(self, position_encoding: Encoding, depth: int = 8, width: int = 256, skips: tuple[int, ...] = (5,),
                 density_activation: str = "relu", density_bias: float = 0.0):
        super().__init__()
        if density_activation not in DENSITY_ACTIVATIONS:
            raise ValueError(f"field.density_activation: expected one of {sorted(DENSITY_ACTIVATIONS)}, "
                             f"got {density_activation!r}")
        bad = [s for s in skips if not 0 < s < depth]
        if bad:
            raise ValueError(f"field.skips: layer indices must be in 1..{depth - 1} for depth {depth}, got {bad}")
        # a copy: the renderer builds several fields from one config, and trainable encodings (hash
        # tables) must not be shared between them
        self.position_encoding = copy.deepcopy(position_encoding)
        self.skips = set(skips)
        in_dim = position_encoding.out_dim
        self.trunk = nn.ModuleList(
            nn.Linear((0 if i == 0 else width) + (in_dim if i == 0 or i in self.skips else 0), width)
            for i in range(depth))
        self.sigma = nn.Linear(width, 1)
        self.activation = DENSITY_ACTIVATIONS[density_activation]
        self.density_bias = density_bias

    def _trunk(self, positions: Tensor) -> Tensor:
        """positions [..., 3] -> the trunk's output features [..., width]."""
        encoded = self.position_encoding(positions)
        h = encoded
        for i, layer in enumerate(self.trunk):
            if i in self.skips:
                h = torch.cat([h, encoded], -1)
            h = F.relu(layer(h), inplace=True)  # in place: ReLU backward needs only its output
        return h

    def density(self, positions: Tensor) -> Tensor:
        """sigma [...] >= 0 at positions [..., 3], without training noise (what proposal sampling, the
        occupancy grid and early ray termination look at)."""
        return self.activation(self.sigma(self._trunk(positions)).squeeze(-1) + self.density_bias)


class NeRFField(DensityField):
    """sigma from the encoded position alone; rgb from a feature of it and the view direction.

    The trunk and density of ``DensityField``; in training mode (``self.training``) with
    ``density_noise_std`` > 0, noise ~ N(0, density_noise_std^2) is added to the raw density before the
    activation, a regulariser against floaters (the paper: std 1 on real scenes, none on synthetic ones).
    Evaluation is deterministic.

    With ``appearance_dim`` > 0 (per-image appearance, ``nerfexp.nerf.appearance``) the colour head takes an
    appearance code beside the trunk's features: it is built for width + appearance_dim features and given
    [h, code] (NeRF-W's colour branch); the density never sees the code. The renderer sets it, from its
    appearance embedding's size.

    Args:
        position_encoding: maps [..., 3] -> [..., out_dim].
        view_head: builds the colour head from the trunk width (see ``ViewDependence``).
        density_activation: a key of ``DENSITY_ACTIVATIONS``.
    """

    DOMAINS = {**DensityField.DOMAINS, "density_noise_std": real(0, RAW_LIMIT)}
    NAME = "a field"

    @staticmethod
    def LAYERS(config: Mapping) -> tuple[int, int, tuple[str, ...], tuple[str, ...]]:
        """Every sample passes through its trunk: ``depth`` layers of ``width`` units."""
        return config["width"], config["depth"], ("width",), ("depth",)

    def __init__(self, position_encoding: Encoding, view_head: Callable[[int], ViewDependence], depth: int = 8,
                 width: int = 256, skips: tuple[int, ...] = (5,), density_activation: str = "relu",
                 density_bias: float = 0.0, density_noise_std: float = 0.0, appearance_dim: int = 0):
        super().__init__(position_encoding, depth, width, skips, density_activation, density_bias)
        if not density_noise_std >= 0:
            raise ValueError(f"field.density_noise_std: expected a standard deviation >= 0, got {density_noise_std}")
        self.density_noise_std = density_noise_std
        self.appearance_dim = appearance_dim
        self.view_head = view_head(width + appearance_dim)

    @property
    def uses_normals(self) -> bool:
        return self.view_head.uses_normals

    def forward(self, positions: Tensor, directions: Tensor, appearance: Tensor | None = None) -> FieldOutputs:
        """positions [..., S, 3] and unit directions [..., S or 1, 3] (one per ray broadcasts over
        its samples) -> ``rgb`` [..., S, 3] in [0, 1], ``sigma`` [..., S] >= 0. ``appearance``: codes
        [..., S or 1, appearance_dim] where the field takes them (``appearance_dim`` > 0), else None.

        A head that predicts normals (``ViewDependence.uses_normals``: Ref-NeRF's, ``nerfexp.nerf.reflection``) also
        gets, while gradients are enabled (training), the density's gradient d raw / dx, and the field answers
        ``penalties`` too: the head's weighted penalties per sample [..., S, P] (``penalty_names``), which the
        renderer composites. The gradient is taken with ``create_graph`` so the penalties train the density
        too; it costs a second pass back through the trunk for every sample (docs/components.md).

        In two stages, which a renderer may call apart to colour only some of the samples whose density it
        asked (``acceleration.grid.alpha_threshold``): ``positional`` then ``coloured``."""
        return self.coloured(self.positional(positions), directions, appearance)

    def positional(self, positions: Tensor) -> "PositionalOutputs":
        """What the field computes of positions [..., 3] alone (``PositionalOutputs``): the density, with training
        noise as ``forward`` has it, the trunk's features, and where the colour head predicts normals in training
        the density's gradient. Rows of its tensors may be selected before ``coloured``."""
        with_normals = self.uses_normals and torch.is_grad_enabled()
        if with_normals:  # positions from rays never carry a gradient of their own: a leaf to differentiate
            positions = positions.detach().requires_grad_()
        h = self._trunk(positions)
        raw = self.sigma(h).squeeze(-1) + self.density_bias
        gradient = None
        if with_normals:
            (gradient,) = torch.autograd.grad(raw.sum(), positions, create_graph=True)  # [..., S, 3]
        if self.training and self.density_noise_std > 0:
            raw = raw + self.density_noise_std * torch.randn_like(raw)
        return PositionalOutputs(sigma=self.activation(raw), features=h, gradient=gradient)

    def coloured(self, positional: "PositionalOutputs", directions: Tensor,
                 appearance: Tensor | None = None) -> FieldOutputs:
        """The field's outputs (see ``forward``) from its ``positional`` outputs at samples [..., S] and their unit
        ``directions`` [..., S or 1, 3] (and ``appearance`` codes, as ``forward`` takes them)."""
        h = self._with_appearance(positional.features, appearance)
        sigma = positional.sigma
        if not self.uses_normals:
            return FieldOutputs(rgb=self.view_head(h, directions), sigma=sigma)
        rgb, normals = self.view_head(h, directions)
        if positional.gradient is None:
            return FieldOutputs(rgb=rgb, sigma=sigma)
        head = self.view_head
        penalties = head.penalties(normals, positional.gradient, directions) * head.penalty_weights.to(rgb.dtype)
        return FieldOutputs(rgb=rgb, sigma=sigma, penalties=penalties)

    @property
    def penalty_names(self) -> tuple[str, ...]:
        """The names of the penalties ``forward`` answers per sample (none for the paper's heads)."""
        return self.view_head.penalty_names

    def _with_appearance(self, h: Tensor, appearance: Tensor | None) -> Tensor:
        """The colour head's input: the trunk's features h [..., S, F], joined by the codes [..., S or 1, D]
        where the field takes them -> [..., S, F + D]; h itself where it does not."""
        if (appearance is None) != (self.appearance_dim == 0):
            raise ValueError(f"NeRFField with appearance_dim={self.appearance_dim}: "
                             f"{'no appearance codes given' if appearance is None else 'given appearance codes'}")
        if appearance is None:
            return h
        return torch.cat([h, appearance.to(h.dtype).expand(*h.shape[:-1], self.appearance_dim)], -1)


def hidden_layer(config: Mapping) -> tuple[int, int, tuple[str, ...], tuple[str, ...]]:
    """``LAYERS`` of a colour head of one hidden layer of ``hidden`` units, which every sample passes through."""
    return config["hidden"], 1, ("hidden",), ()


def hidden_layer_memory(config: Mapping) -> list[Memory]:
    """``MEMORY`` of a colour head of one hidden layer of ``hidden`` units: its weights, trained."""
    return [(("hidden",), f"training a view head of 1 layers of {config['hidden']} units",
             parameter_bytes(config["hidden"], 1))]


class MLPViewDependence(ViewDependence):
    """The paper's head: a linear feature of the trunk, joined with gamma(d), one ReLU layer, rgb."""

    DOMAINS = {"hidden": COUNT}
    LAYERS = staticmethod(hidden_layer)
    MEMORY = staticmethod(hidden_layer_memory)

    def __init__(self, in_features: int, direction_encoding: Encoding, hidden: int = 128):
        super().__init__()
        self.direction_encoding = direction_encoding
        self.feature = nn.Linear(in_features, in_features)
        # The hidden layer on [feature, gamma(d)], split in two: with directions [..., 1, 3] the
        # direction's half is computed once per ray and broadcast over the ray's samples. The renderer
        # without a grid passes flat per-sample directions instead (one 2-D batch, fewer copies), so
        # there it is computed per sample: a 27 x hidden product, a few percent of the step.
        self.hidden = nn.Linear(in_features, hidden)
        self.hidden_direction = nn.Linear(direction_encoding.out_dim, hidden, bias=False)
        self.rgb = nn.Linear(hidden, 3)

    def forward(self, h: Tensor, directions: Tensor) -> Tensor:
        """h [..., S, F], directions [..., S or 1, 3] -> rgb [..., S, 3]."""
        x = self.hidden(self.feature(h)) + self.hidden_direction(self.direction_encoding(directions))
        return torch.sigmoid(self.rgb(F.relu(x, inplace=True)))


class NoViewDependence(ViewDependence):
    """rgb from the position alone, the view direction unused: the "No View Dependence" ablation."""

    def __init__(self, in_features: int):
        super().__init__()
        self.rgb = nn.Linear(in_features, 3)

    def forward(self, h: Tensor, directions: Tensor) -> Tensor:
        """h [..., S, F] -> rgb [..., S, 3]; ``directions`` is ignored."""
        return torch.sigmoid(self.rgb(h))


SH_MAX_DEGREE = 3  # the highest band ``sh_basis`` writes out (16 coefficients per colour channel)


def sh_basis(directions: Tensor, degree: int) -> Tensor:
    """Real spherical harmonics up to ``degree`` (0..SH_MAX_DEGREE) at unit ``directions`` [..., 3]:
    [..., (degree+1)^2].

    Ordered by band l, then m = -l..l, with the standard orthonormal constants (as in PlenOctrees).
    """
    if not 0 <= degree <= SH_MAX_DEGREE:
        raise ValueError(f"view_dependence.degree: expected 0..{SH_MAX_DEGREE}, got {degree}")
    x, y, z = directions.unbind(-1)
    out = [torch.full_like(x, 0.28209479177387814)]
    if degree >= 1:
        c1 = 0.4886025119029199
        out += [-c1 * y, c1 * z, -c1 * x]
    if degree >= 2:
        xx, yy, zz, xy, yz, xz = x * x, y * y, z * z, x * y, y * z, x * z
        out += [1.0925484305920792 * xy, -1.0925484305920792 * yz, 0.31539156525252005 * (2 * zz - xx - yy),
                -1.0925484305920792 * xz, 0.5462742152960396 * (xx - yy)]
    if degree >= 3:
        out += [-0.5900435899266435 * y * (3 * xx - yy), 2.890611442640554 * xy * z,
                -0.4570457994644658 * y * (4 * zz - xx - yy), 0.3731763325901154 * z * (2 * zz - 3 * xx - 3 * yy),
                -0.4570457994644658 * x * (4 * zz - xx - yy), 1.445305721320277 * z * (xx - yy),
                -0.5900435899266435 * x * (xx - 3 * yy)]
    return torch.stack(out, -1)


class SphericalHarmonicsViewDependence(ViewDependence):
    """rgb = sigmoid(sum_k c_k Y_k(d)): the field predicts SH coefficients per colour channel."""

    DOMAINS = {"degree": whole(0, SH_MAX_DEGREE)}

    def __init__(self, in_features: int, degree: int = 2):
        super().__init__()
        self.degree = degree
        self.coefficients = nn.Linear(in_features, 3 * (degree + 1) ** 2)

    def forward(self, h: Tensor, directions: Tensor) -> Tensor:
        """h [..., S, F], unit directions [..., S or 1, 3] -> rgb [..., S, 3]."""
        coefficients = self.coefficients(h).unflatten(-1, (3, -1))  # [..., 3, K]
        basis = sh_basis(directions, self.degree)  # [..., K]
        return torch.sigmoid((coefficients * basis[..., None, :]).sum(-1))
