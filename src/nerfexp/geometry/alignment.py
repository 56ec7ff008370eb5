"""Comparing estimated cameras with true ones: the similarity that best aligns their centres (Umeyama), and the
rotation and centre errors left after it. Everything in float64: the errors measured are fractions of a degree.

Cameras are c2w [N, 4, 4] (``nerfexp.geometry.cameras``); a similarity (s, R, t) maps x to s R x + t.
"""

import torch
from torch import Tensor


def umeyama(source: Tensor, target: Tensor) -> tuple[float, Tensor, Tensor]:
    """The similarity (s, R [3, 3], t [3]) minimizing sum_i |s R x_i + t - y_i|^2 over points x = ``source``
    and y = ``target`` [N, 3] (Umeyama 1991): with the centred covariance Sigma = (y - mu_y)^T (x - mu_x) / N =
    U D V^T, R = U S V^T, S = diag(1, 1, det(U V^T)) (a rotation, never a reflection), s = tr(D S) / var(x),
    t = mu_y - s R mu_x. A ValueError where the source points all coincide (nothing to scale)."""
    x, y = source.double(), target.double()
    mu_x, mu_y = x.mean(0), y.mean(0)
    xc, yc = x - mu_x, y - mu_y
    var_x = (xc * xc).sum(-1).mean()
    if not var_x > 0:
        raise ValueError("umeyama: the source points all coincide")
    U, D, Vt = torch.linalg.svd(yc.T @ xc / len(x))
    S = torch.ones(3, dtype=x.dtype)
    S[2] = torch.sign(torch.linalg.det(U @ Vt))
    R = U @ torch.diag(S) @ Vt
    s = float((D * S).sum() / var_x)
    return s, R, mu_y - s * R @ mu_x


def rotation_angle(R: Tensor) -> Tensor:
    """The angle [...] (radians, in [0, pi]) of rotations R [..., 3, 3]: atan2(|vee(R - R^T)| / 2,
    (tr R - 1) / 2), accurate at small angles, where the arccos of the trace loses half the digits."""
    skew = R - R.transpose(-1, -2)
    vee = torch.stack([skew[..., 2, 1], skew[..., 0, 2], skew[..., 1, 0]], -1)
    trace = R.diagonal(dim1=-2, dim2=-1).sum(-1)
    return torch.atan2(torch.linalg.vector_norm(vee, dim=-1) / 2, (trace - 1) / 2)


def camera_radius(c2w: Tensor) -> float:
    """The cameras' radius: the largest distance of a camera centre (c2w [N, 4, 4]) from their centroid."""
    centres = c2w[:, :3, 3].double()
    return float(torch.linalg.vector_norm(centres - centres.mean(0), dim=-1).max())


def pose_errors(estimated: Tensor, true: Tensor) -> dict[str, float]:
    """How far cameras ``estimated`` are from ``true`` (c2w [N, 4, 4] each, N >= 3 not all at one place) after
    the similarity that best aligns their centres (``umeyama``), the gauge of a reconstruction being arbitrary:
    ``rotation_deg`` (mean over cameras of the angle between the aligned and the true orientation, degrees),
    ``rotation_max_deg``, ``centre`` (mean distance between aligned and true centres, scene units),
    ``centre_max``, ``centre_fraction`` (``centre`` over the true cameras' ``camera_radius``) and the
    similarity's ``scale``."""
    estimated, true = estimated.double(), true.double()
    s, R, t = umeyama(estimated[:, :3, 3], true[:, :3, 3])
    centres = s * estimated[:, :3, 3] @ R.T + t
    orientations = R @ estimated[:, :3, :3]
    angles = torch.rad2deg(rotation_angle(true[:, :3, :3].transpose(-1, -2) @ orientations))
    distances = torch.linalg.vector_norm(centres - true[:, :3, 3], dim=-1)
    return {"rotation_deg": float(angles.mean()), "rotation_max_deg": float(angles.max()),
            "centre": float(distances.mean()), "centre_max": float(distances.max()),
            "centre_fraction": float(distances.mean()) / camera_radius(true), "scale": s}
