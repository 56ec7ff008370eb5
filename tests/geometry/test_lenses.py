"""Lenses against independent truth: COLMAP's own projection (pycolmap's ``img_from_cam`` and
``cam_from_img``), float64 round trips, hand-worked pinhole rays, autograd's Jacobian, and lenses that
fold the image over itself."""

import math

import numpy as np
import pycolmap
import pytest
import torch

from nerfexp.geometry.lens_records import LensRecordError, lens_record, read_lens_record
from nerfexp.geometry.lenses import (
    FISHEYE_MODELS,
    PARAMETERS,
    Intrinsics,
    border_pixels,
    distort,
    distortion_vector,
    inversion_problem,
    pixel_grid,
    pixel_rays,
    undistort_perspective,
)

F64 = torch.float64
H, W = 960, 540  # a phone's portrait image
CAMERAS = [  # COLMAP models nerfexp reads, with the parameters of real lenses (or stronger)
    ("SIMPLE_PINHOLE", [600.0, 270.0, 480.0]),
    ("PINHOLE", [687.8, 687.2, 277.3, 482.6]),
    ("SIMPLE_RADIAL", [600.0, 265.0, 490.0, 0.1]),
    ("RADIAL", [520.0, 275.0, 470.0, -0.2, 0.05]),
    ("OPENCV", [687.8, 687.2, 277.3, 482.6, 0.058, -0.081, 0.001, -0.002]),
    ("FULL_OPENCV", [600.0, 610.0, 270.0, 480.0, 0.1, -0.05, 0.001, 0.002, 0.01, 0.02, 0.01, 0.001]),
    ("SIMPLE_RADIAL_FISHEYE", [400.0, 270.0, 480.0, 0.05]),
    ("RADIAL_FISHEYE", [400.0, 270.0, 480.0, 0.05, -0.01]),
    ("OPENCV_FISHEYE", [420.0, 410.0, 270.0, 480.0, 0.05, -0.01, 0.002, -0.001]),
]


def as_lens(model: str, params: list[float]) -> Intrinsics:
    """The lens of a COLMAP camera, mapped here independently of nerfexp's COLMAP reader."""
    names = PARAMETERS[model]
    lead = params[:len(params) - len(names)]
    fx, fy, cx, cy = (lead[0], *lead) if len(lead) == 3 else lead
    distortion = distortion_vector(dict(zip(names, params[len(lead):])))
    return Intrinsics(torch.tensor([fx, fy, cx, cy], dtype=F64), distortion, torch.tensor(model in FISHEYE_MODELS))


@pytest.mark.parametrize(("model", "params"), CAMERAS, ids=[model for model, _ in CAMERAS])
def test_rays_project_back_to_their_pixels_through_colmap_across_the_image(model, params):
    # every pixel of a 33 x 33 grid over the whole image, its four corners included: nerfexp's ray, projected by
    # COLMAP's own camera model, lands on the pixel it was made for, to a millionth of a pixel
    camera = pycolmap.Camera(model=model, width=W, height=H, params=params)
    lens = as_lens(model, params)
    assert inversion_problem(lens, H, W) is None
    pixels = border_pixels(H, W, 33)
    rays = pixel_rays(pixels, lens)  # [K, 3], nerfexp's camera frame: y up, looking down -z
    colmap_rays = (rays * torch.tensor([1.0, -1.0, -1.0], dtype=F64)).numpy()  # COLMAP's: y down, down +z
    assert np.all(colmap_rays[:, 2] > 0)
    back = camera.img_from_cam(colmap_rays)
    assert np.abs(back - pixels.numpy()).max() < 1e-6
    # and COLMAP's inverse (its own iterative undistortion) gives the same directions
    theirs = camera.cam_from_img(pixels.numpy())
    ours = colmap_rays[:, :2] / colmap_rays[:, 2:]
    assert np.abs(theirs - ours).max() * min(params[0], params[1]) < 1e-3  # pixels


def test_an_ideal_pinhole_ray_is_the_hand_worked_one():
    # fx = 100, fy = 50, principal point (30, 20): the pixel centre (50.0, 45.0) has
    # x = (50 - 30) / 100 = 0.2, y = (45 - 20) / 50 = 0.5 (down), so the ray is (0.2, -0.5, -1) / |.|
    lens = Intrinsics(torch.tensor([100.0, 50.0, 30.0, 20.0], dtype=F64), torch.zeros(8, dtype=F64),
                      torch.tensor(False))
    ray = pixel_rays(torch.tensor([[50.0, 45.0]], dtype=F64), lens)[0]
    expected = torch.tensor([0.2, -0.5, -1.0], dtype=F64)
    assert torch.allclose(ray, expected / expected.norm(), atol=1e-15)


def test_the_pinhole_rays_are_the_blender_cameras_bit_for_bit():
    # the rays of a centred pinhole in float32 are those nerfexp made before lenses, (j + 0.5 - W/2) / f,
    # -(i + 0.5 - H/2) / f, -1, normalized: the complete model's rays are unchanged
    height, width, focal = 7, 10, 11.3
    rows = torch.arange(height, dtype=torch.float32) + 0.5
    cols = torch.arange(width, dtype=torch.float32) + 0.5
    i, j = torch.meshgrid(rows, cols, indexing="ij")
    d = torch.stack([(j - 0.5 * width) / focal, -(i - 0.5 * height) / focal, -torch.ones_like(i)], -1)
    before = d / torch.linalg.vector_norm(d, dim=-1, keepdim=True)
    lens = Intrinsics.pinhole(focal, height, width).to(torch.float32)
    assert torch.equal(pixel_rays(pixel_grid(height, width), lens), before)


@pytest.mark.parametrize("dtype", [torch.float32, F64])
def test_a_batch_mixing_lens_types_gives_each_cameras_own_rays_bit_for_bit_and_solves_only_where_needed(
        dtype, monkeypatch):
    # every model above, each twice, shuffled: each camera's rays in the batch are those of the camera alone (a
    # pinhole's the hand-worked formula's, with no solve), and each Newton solve is given the pixels of the
    # lenses that need it, no others: the distorted perspective lenses' in p, the fisheyes' in theta
    import nerfexp.geometry.lenses as lenses

    h, w = 8, 6
    single = [as_lens(model, params).resized((H, W), (h, w)).to(dtype) for model, params in CAMERAS]
    order = torch.randperm(2 * len(single), generator=torch.Generator().manual_seed(0)) % len(single)
    grid = pixel_grid(h, w, dtype=dtype)
    alone = torch.stack([pixel_rays(grid, single[i]) for i in order])  # [N, h, w, 3]
    calls = []

    def counting(solve):
        def counted(values, distortion):
            calls.append((solve.__name__, tuple(values.shape)))
            return solve(values, distortion)
        return counted
    for name in ("undistort_perspective", "undistort_angle"):
        monkeypatch.setattr(lenses, name, counting(getattr(lenses, name)))
    together = pixel_rays(grid, Intrinsics.stack([single[i] for i in order]).unsqueeze(2))  # [N, h, w, 3]
    assert together.dtype == dtype and torch.equal(together, alone)
    fisheye = sum(model in FISHEYE_MODELS for model, _ in CAMERAS)  # 3
    perspective = sum(model not in FISHEYE_MODELS and len(PARAMETERS[model]) > 0 for model, _ in CAMERAS)  # 4
    assert calls == [("undistort_perspective", (2 * perspective * h * w, 2)),
                     ("undistort_angle", (2 * fisheye * h * w,))]


@pytest.mark.parametrize(("model", "params"), CAMERAS[2:6], ids=[model for model, _ in CAMERAS[2:6]])
def test_undistortion_inverts_distortion_in_float64(model, params):
    lens = as_lens(model, params)
    g = torch.Generator().manual_seed(0)
    p = (torch.rand(1000, 2, generator=g, dtype=F64) - 0.5) * torch.tensor([W / params[0], H / params[0]])
    back = undistort_perspective(distort(p, lens.distortion, lens.fisheye), lens.distortion)
    assert (back - p).abs().max() < 1e-12


def test_the_jacobian_is_autograds():
    # Newton's steps use the closed-form Jacobian of the distortion; autograd differentiates the same map
    from nerfexp.geometry.lenses import _perspective  # the private pair (value, Jacobian) under test

    lens = as_lens(*CAMERAS[5])
    p = torch.tensor([[0.3, -0.4], [0.0, 0.0], [-0.7, 0.2]], dtype=F64)
    _, jacobian = _perspective(p, lens.distortion)
    for k in range(len(p)):
        truth = torch.autograd.functional.jacobian(lambda q: _perspective(q, lens.distortion)[0], p[k])
        assert torch.allclose(jacobian[k], truth, atol=1e-12)


def test_a_fisheye_sees_beyond_90_degrees_without_infinities():
    # an equidistant fisheye (all k 0) of f = 100: theta = r / f, so a pixel 200 px right of the centre looks
    # 2 radians (115 degrees) off the axis: direction (sin 2, 0, -cos 2) in nerfexp's frame
    lens = Intrinsics(torch.tensor([100.0, 100.0, 0.0, 0.0], dtype=F64), torch.zeros(8, dtype=F64),
                      torch.tensor(True))
    ray = pixel_rays(torch.tensor([[200.0, 0.0]], dtype=F64), lens)[0]
    assert torch.allclose(ray, torch.tensor([math.sin(2.0), 0.0, -math.cos(2.0)], dtype=F64), atol=1e-12)
    centre = pixel_rays(torch.zeros(1, 2, dtype=F64), lens)[0]
    assert torch.equal(centre, torch.tensor([0.0, 0.0, -1.0], dtype=F64))


@pytest.mark.parametrize(("named", "fisheye", "says"), [
    ({"k1": -0.3}, False, "folds the image over itself"),  # r (1 - 0.3 r^2) peaks at r = 1.05, inside the image
    ({"k1": -2.0}, True, "folds the image over itself"),
    ({}, True, "180 degrees from the axis"),  # an equidistant fisheye of f = 100 on a 960 px image: 4.8 rad at the edge
])
def test_a_lens_that_cannot_be_inverted_over_its_image_is_said_to(named, fisheye, says):
    focal = 100.0 if fisheye else 300.0
    lens = Intrinsics(torch.tensor([focal, focal, 270.0, 480.0], dtype=F64), distortion_vector(named),
                      torch.tensor(fisheye))
    problem = inversion_problem(lens, H, W)
    assert problem is not None and says in problem


def test_a_lens_record_round_trips_and_names_a_bad_key():
    lens = as_lens(*CAMERAS[4])
    record = lens_record(lens)
    assert record["camera_model"] == "OPENCV" and record["cx"] == 277.3
    again = read_lens_record(record)
    assert torch.equal(again.params, lens.params) and torch.equal(again.distortion, lens.distortion)
    fisheye = as_lens(*CAMERAS[8])
    assert lens_record(fisheye)["camera_model"] == "OPENCV_FISHEYE"
    assert bool(read_lens_record(lens_record(fisheye)).fisheye)
    with pytest.raises(LensRecordError, match="'fl_y': expected a number of pixels"):
        read_lens_record({**record, "fl_y": "wide"})
    with pytest.raises(LensRecordError, match="'k4': camera_model OPENCV has no coefficient k4"):
        read_lens_record({**record, "k4": 0.1})
    with pytest.raises(LensRecordError, match="'camera_model': expected one of PINHOLE, OPENCV"):
        read_lens_record({**record, "camera_model": "EQUIRECTANGULAR"})
