"""Ref-NeRF's view dependence (Verbin et al., "Ref-NeRF: Structured View-Dependent Appearance for Neural
Radiance Fields", CVPR 2022): colour from the reflected view direction, encoded by how rough the surface is.

Conventions: ``directions`` d are unit ray directions from the camera into the scene [..., 3] (one per ray,
[..., 1, 3], broadcasts over its samples); omega_o = -d points back towards the camera; normals are unit
[..., S, 3]; ``roughness`` rho = 1 / kappa >= 0 is the width of a von Mises-Fisher lobe [..., 1].
"""

import functools
import math
from collections.abc import Sequence

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from nerfexp.domains import COUNT, LOSS_WEIGHT, RAW_OFFSET, whole
from nerfexp.nerf.fields import ViewDependence, hidden_layer, hidden_layer_memory


@functools.cache
def _legendre_recurrence(l_max: int) -> tuple[list[float], dict[tuple[int, int], tuple[float, float]]]:
    """float64 constants for Q_l^m(z) = Y_l^m / Re or Im (x + i y)^m, 0 <= m <= l <= l_max:
    Q_m^m (the sqrt 2 of m > 0 and the Condon-Shortley phase (-1)^m included), and (a, b) of
    Q_l^m = a (z Q_{l-1}^m - b Q_{l-2}^m), the stable recurrence of the normalised associated Legendre functions."""
    diagonal = [math.sqrt(1 / (4 * math.pi))]
    for m in range(1, l_max + 1):  # K_mm P_m^m = (-1)^m sqrt((2m+1) / (4 pi (2m)!)) (2m-1)!! (1 - z^2)^{m/2}
        diagonal.append(-diagonal[-1] * math.sqrt((2 * m + 1) / (2 * m)))
    diagonal[1:] = [math.sqrt(2) * k for k in diagonal[1:]]
    recurrence = {(ell, m): (math.sqrt((4 * ell * ell - 1) / (ell * ell - m * m)),
                             math.sqrt(((ell - 1) ** 2 - m * m) / (4 * (ell - 1) ** 2 - 1)))
                  for m in range(l_max + 1) for ell in range(m + 1, l_max + 1)}
    return diagonal, recurrence


def real_sh_basis(directions: Tensor, degrees: Sequence[int]) -> Tensor:
    """Real orthonormal spherical harmonics Y_l^m at unit ``directions`` [..., 3] -> [..., sum(2l + 1)], for each
    l in ``degrees`` (in the order given), then m = -l..l.

    Y_l^0 = K_l0 P_l(z); Y_l^m = sqrt 2 K_lm P_l^|m|(z) / (1 - z^2)^{|m|/2} times Re (x + i y)^|m| for m > 0,
    Im (x + i y)^|m| for m < 0 (as (1 - z^2)^{|m|/2} e^{i |m| phi} = (x + i y)^|m| on the unit sphere), with
    the Condon-Shortley phase in P_l^m: the convention of ``fields.sh_basis`` (PlenOctrees), Y_1 = c [-y, z, -x].
    The z part comes from the three-term recurrence in l, not from the polynomial's coefficients: those
    alternate in sign and grow like (1 + sqrt 2)^l, so a float32 sum of them loses most of its digits at l = 16.
    """
    degrees = list(degrees)
    l_max = max(degrees)
    diagonal, recurrence = _legendre_recurrence(l_max)
    x, y, z = directions.unbind(-1)
    wanted = set(degrees)
    legendre = {}  # (l, m >= 0) -> Q_l^m(z) [...]
    powers = []  # m -> (Re, Im) of (x + i y)^m [...]
    re, im = torch.ones_like(x), torch.zeros_like(x)
    for m in range(l_max + 1):
        if m > 0:
            re, im = re * x - im * y, re * y + im * x
        powers.append((re, im))
        previous, current = torch.zeros_like(z), torch.full_like(z, diagonal[m])
        for ell in range(m, l_max + 1):
            if ell > m:
                a, b = recurrence[ell, m]
                previous, current = current, a * (z * current - b * previous)
            if ell in wanted:
                legendre[ell, m] = current
    out = []
    for ell in degrees:
        out += [legendre[ell, -m] * powers[-m][1] for m in range(-ell, 0)]
        out += [legendre[ell, m] * powers[m][0] for m in range(ell + 1)]
    return torch.stack(out, -1)


def ide_degrees(n_levels: int) -> list[int]:
    """Ref-NeRF's bands for the integrated directional encoding: l = 1, 2, 4, ..., 2^(n_levels - 1)."""
    return [2**i for i in range(n_levels)]


def integrated_directional_encoding(directions: Tensor, roughness: Tensor, degrees: Sequence[int]) -> Tensor:
    """IDE(omega, rho) = [exp(-l (l + 1) rho / 2) Y_l^m(omega)] (Ref-NeRF eq. 8, kappa = 1 / rho).

    The expected value of each spherical harmonic under a von Mises-Fisher lobe vMF(omega, kappa) is
    A_l(kappa) Y_l^m(omega) (Funk-Hecke), A_l = I_{l+1/2}(kappa) / I_{1/2}(kappa) ~ exp(-l (l + 1) / (2 kappa))
    for large kappa: rough surfaces blur away the high bands, and roughness 0 gives the plain SH.
    unit ``directions`` [..., 3], ``roughness`` [..., 1] >= 0 -> [..., sum(2l + 1)] (``real_sh_basis``'s order).
    """
    bands = torch.tensor([ell * (ell + 1) / 2 for ell in degrees for _ in range(2 * ell + 1)], dtype=roughness.dtype,
                         device=roughness.device)  # [K]
    return real_sh_basis(directions, degrees) * torch.exp(-bands * roughness)


def reflect(directions: Tensor, normals: Tensor) -> Tensor:
    """omega_r = 2 (omega_o . n) n - omega_o, omega_o = -d: the direction towards the camera mirrored about the
    normal. ``directions`` d [..., 3] (into the scene), ``normals`` n [..., 3] unit -> [..., 3] (broadcast)."""
    outgoing = -directions
    return 2 * (outgoing * normals).sum(-1, keepdim=True) * normals - outgoing


def linear_to_srgb(linear: Tensor) -> Tensor:
    """The sRGB transfer function: 12.92 x for x <= 0.0031308, 1.055 x^(1/2.4) - 0.055 above. [...] -> [...].

    The power is taken of x clamped to the knee, so its infinite slope at 0 never enters the gradient."""
    knee = 0.0031308
    return torch.where(linear <= knee, 12.92 * linear, 1.055 * linear.clamp(min=knee) ** (1 / 2.4) - 0.055)


def _unit(x: Tensor) -> Tensor:
    """x / |x| along the last axis; the norm is clamped to sqrt(tiny), the smallest whose square (in the
    division's backward) is a normal float, so values and gradients stay finite even at x = 0."""
    return F.normalize(x, dim=-1, eps=math.sqrt(torch.finfo(x.dtype).tiny))


class ReflectionViewDependence(ViewDependence):
    """Ref-NeRF's colour: rgb = clamp(linear_to_srgb(c_d + s * c_s), 0, 1).

    From the trunk features h: the diffuse colour c_d = sigmoid(raw - ln 3), the specular tint s, the roughness
    rho = softplus(raw + ``roughness_bias``), a predicted normal n' = -raw / |raw| and a bottleneck feature b.
    The specular colour c_s = sigmoid(MLP([b, IDE(omega_r, rho), n' . omega_o])) sees the view only through the
    reflection omega_r of omega_o about n'. Departures from the paper: the directional MLP has one ReLU layer of
    ``hidden`` (not 8 x 256), so that it costs like the paper's NeRF view head; the normals' losses
    (``penalties``, weighted by ``normal_weight`` and ``orientation_weight``) are asked by the field, which has
    the density's gradient, and composited by the renderer. ``uses_normals``: forward returns (rgb, predicted
    normals), not rgb alone.
    """

    DOMAINS = {
        "hidden": COUNT,
        "n_levels": whole(1, 6),  # bands up to l = 32, where the float32 basis is still accurate
        "roughness_bias": RAW_OFFSET,
        "normal_weight": LOSS_WEIGHT,
        "orientation_weight": LOSS_WEIGHT,
    }
    LAYERS = staticmethod(hidden_layer)
    MEMORY = staticmethod(hidden_layer_memory)
    uses_normals = True
    penalty_names = ("normals", "orientation")  # the columns of ``normal_penalties``

    def __init__(self, in_features: int, hidden: int = 128, n_levels: int = 5, roughness_bias: float = -1.0,
                 normal_weight: float = 3e-4, orientation_weight: float = 0.1):
        super().__init__()
        self.degrees = ide_degrees(n_levels)
        self.roughness_bias = roughness_bias
        # the weights of R_p and R_o (Ref-NeRF's 3e-4 and 0.1), applied per sample by the field
        self.register_buffer("penalty_weights", torch.tensor([normal_weight, orientation_weight]), persistent=False)
        self.diffuse = nn.Linear(in_features, 3)
        self.tint = nn.Linear(in_features, 3)
        self.roughness = nn.Linear(in_features, 1)
        self.normal = nn.Linear(in_features, 3)
        self.bottleneck = nn.Linear(in_features, in_features)
        self.hidden = nn.Linear(in_features + sum(2 * ell + 1 for ell in self.degrees) + 1, hidden)
        self.specular = nn.Linear(hidden, 3)

    def forward(self, h: Tensor, directions: Tensor) -> tuple[Tensor, Tensor]:
        """h [..., S, F], unit directions [..., S or 1, 3] -> (rgb [..., S, 3] in [0, 1], normals [..., S, 3])."""
        diffuse = torch.sigmoid(self.diffuse(h) - math.log(3))  # [..., S, 3]
        tint = torch.sigmoid(self.tint(h))  # [..., S, 3]
        roughness = F.softplus(self.roughness(h) + self.roughness_bias)  # [..., S, 1]
        normals = -_unit(self.normal(h))  # [..., S, 3]
        reflected = reflect(directions, normals)  # [..., S, 3]
        cosine = -(normals * directions).sum(-1, keepdim=True)  # n' . omega_o [..., S, 1]
        x = torch.cat([self.bottleneck(h), integrated_directional_encoding(reflected, roughness, self.degrees),
                       cosine], -1)
        specular = torch.sigmoid(self.specular(F.relu(self.hidden(x), inplace=True)))  # [..., S, 3]
        return linear_to_srgb(diffuse + tint * specular).clamp(0, 1), normals

    def penalties(self, normals: Tensor, gradient: Tensor, directions: Tensor) -> Tensor:
        """``normal_penalties``: [..., S, 2]."""
        return normal_penalties(normals, gradient, directions)


def normal_penalties(predicted: Tensor, gradient: Tensor, directions: Tensor) -> Tensor:
    """Ref-NeRF's normal regularisers per sample, to be weighted by the rendering weights: [..., S, 2].

    Column 0, R_p = 1 - n' . n: the predicted normals n' [..., S, 3] (unit) follow the density's normals
    n = -gradient / |gradient| (``gradient`` = d sigma / dx [..., S, 3]). Column 1, R_o = max(0, n' . d)^2:
    a predicted normal facing away from the camera (d [..., S or 1, 3], the ray direction into the scene).
    """
    normals = -_unit(gradient)
    predicted_loss = 1 - (predicted * normals).sum(-1)
    orientation_loss = F.relu((predicted * directions).sum(-1)) ** 2
    return torch.stack([predicted_loss, orientation_loss], -1)
