"""A nerfstudio capture's ray bounds (``NerfstudioScene.ray_bounds``): from its sparse points (a PLY), else its
Instant-NGP box, else the cameras' bound; checked by hand, against a brute force over every pixel ray, and a bad
PLY refused in one line naming it."""

import json

import numpy as np
import pytest
import torch

from nerfexp.data.nerfstudio import NerfstudioScene
from nerfexp.data.procedural import load_procedural
from nerfexp.data.sparse_points import read_ply_points
from nerfexp.data.transforms_file import TRANSFORMS, write_nerfstudio
from nerfexp.errors import DatasetError
from nerfexp.geometry.cameras import camera_rays
from nerfexp.products.ply import ply_bytes

SIZE = 12
BOX_KEYS = {"aabb_scale": 1, "scale": 1 / 3, "offset": [0.5, 0.5, 0.5]}  # the cube [-1.5, 1.5]^3 (ngp_box)


@pytest.fixture(scope="module")
def scene_root(tmp_path_factory):
    root = tmp_path_factory.mktemp("capture")
    write_nerfstudio(root, ((split, load_procedural(split, n, SIZE, SIZE, supersample=1))
                            for split, n in (("train", 5), ("val", 1), ("test", 2))))
    return root


def scene_with(root, tmp_path, **keys) -> NerfstudioScene:
    """The scene ``root`` copied to ``tmp_path`` (its images linked) with ``keys`` added to its transforms file."""
    for image in (root / "images").iterdir():
        (tmp_path / "images").mkdir(exist_ok=True)
        (tmp_path / "images" / image.name).symlink_to(image)
    content = json.loads((root / TRANSFORMS).read_text())
    content.update(keys)
    (tmp_path / TRANSFORMS).write_text(json.dumps(content))
    return NerfstudioScene(root=str(tmp_path))


def write_points(path, points) -> None:
    rows = np.zeros(len(points), dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("red", "u1")])
    for k, axis in enumerate("xyz"):
        rows[axis] = np.asarray(points)[:, k]
    path.write_bytes(ply_bytes({"vertex": rows}))


def test_without_points_or_box_the_old_rule(scene_root, tmp_path):
    scene = scene_with(scene_root, tmp_path)
    assert scene.ray_bounds() == (0.2, 8.0)  # 0.05 and 2 x data.bound 4
    assert scene.bounds_rule().startswith("the cameras' bound")
    assert NerfstudioScene(root=str(tmp_path), near=1.0, far=3.0).bounds_rule() is None


def test_the_box_bounds_every_pixel_ray_of_every_frame(scene_root, tmp_path):
    scene = scene_with(scene_root, tmp_path, **BOX_KEYS)
    near, far = scene.ray_bounds()
    assert scene.bounds_rule().startswith("Instant-NGP's scene box")
    # brute force: every pixel ray of every frame (all splits) against the normalized box, slab test in float64
    box = scene.bounding_box().double()
    entries, exits = [], []
    for split in ("train", "val", "test"):
        views = scene.views(split)
        for c2w, lens in zip(views.c2w.double(), views.intrinsics.to(torch.float64)):
            o, d = camera_rays(c2w, views.height, views.width, lens)
            o, d = o.reshape(-1, 3).double(), d.reshape(-1, 3).double()
            t0, t1 = (box[0] - o) / d, (box[1] - o) / d
            entry, exit_ = torch.minimum(t0, t1).amax(-1).clamp(min=0), torch.maximum(t0, t1).amin(-1)
            hit = exit_ > entry
            entries.append(entry[hit])
            exits.append(exit_[hit])
    entry, exit_ = torch.cat(entries), torch.cat(exits)
    # exact for the pixel rays' pyramids: the bounds hold every ray and lie within a pixel's spread of them
    assert near <= entry.min().item() + 1e-6 and far >= exit_.max().item() - 1e-6
    assert near == pytest.approx(entry.min().item(), rel=0.05) and far == pytest.approx(exit_.max().item(), rel=0.05)
    assert near > 0.2 and far < 8.0  # tighter than the old rule


def test_points_at_a_known_place_give_their_distances_and_win_over_the_box(scene_root, tmp_path):
    write_points(tmp_path / "sparse_pc.ply", [[0.0, 0.0, 0.0]])  # the still life's centre: every camera sees it
    scene = scene_with(scene_root, tmp_path, ply_file_path="sparse_pc.ply", **BOX_KEYS)
    near, far = scene.ray_bounds()
    posed = scene.posed()
    c2w, centre, scale = posed.c2w, posed.centre, posed.scale
    # one point: each camera's percentiles are its distance; 0.9 x the nearest, 1.1 x the farthest
    distances = torch.linalg.vector_norm((torch.zeros(3, dtype=torch.float64) - centre) * scale - c2w[:, :3, 3], dim=-1)
    assert (near, far) == pytest.approx((0.9 * distances.min().item(), 1.1 * distances.max().item()))
    assert "sparse_pc.ply" in scene.bounds_rule()


def test_points_no_camera_sees_leave_it_to_the_box(scene_root, tmp_path):
    write_points(tmp_path / "sparse_pc.ply", [[0.0, 0.0, 100.0]])  # far above every camera's view
    scene = scene_with(scene_root, tmp_path, ply_file_path="sparse_pc.ply", **BOX_KEYS)
    assert scene.bounds_rule().startswith("Instant-NGP's scene box")


def test_read_ply_points_ascii_and_binary(tmp_path):
    points = [[1.0, 2.0, 3.0], [-4.5, 0.25, 6.0]]
    write_points(tmp_path / "binary.ply", points)
    assert read_ply_points(tmp_path / "binary.ply").tolist() == points
    (tmp_path / "ascii.ply").write_text("ply\nformat ascii 1.0\ncomment made by hand\nelement vertex 2\n"
                                        "property uchar red\nproperty double x\nproperty double y\nproperty double z\n"
                                        "end_header\n7 1 2 3\n8 -4.5 0.25 6\n")
    assert read_ply_points(tmp_path / "ascii.ply").tolist() == points


@pytest.mark.parametrize("content, message", [
    (b"not a ply", "not a PLY file"),
    (b"ply\nformat binary_little_endian 1.0\nelement vertex 3\nproperty float x\nproperty float y\nproperty float z\n"
     b"end_header\n" + bytes(12), "do not match the header's 3 vertices"),
    (b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nproperty float y\nend_header\n1 2\n",
     "must have the properties x, y and z"),
    (b"ply\nformat ascii 1.0\nelement face 1\nproperty list uchar int vertex_indices\nend_header\n",
     "first element to be 'element vertex COUNT'"),
    (b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nproperty float y\nproperty float z\nend_header\n"
     b"nan 0 0\n", "not finite"),
])
def test_a_bad_ply_is_one_line_naming_it(scene_root, tmp_path, content, message):
    (tmp_path / "sparse_pc.ply").write_bytes(content)
    scene = scene_with(scene_root, tmp_path, ply_file_path="sparse_pc.ply")
    with pytest.raises(DatasetError, match=message) as caught:
        scene.ray_bounds()
    assert str(tmp_path / "sparse_pc.ply") in str(caught.value) and "\n" not in str(caught.value)


def test_a_missing_ply_is_named_with_the_key(scene_root, tmp_path):
    scene = scene_with(scene_root, tmp_path, ply_file_path="sparse_pc.ply")
    with pytest.raises(DatasetError, match="sparse_pc.ply does not exist .*'ply_file_path'"):
        scene.ray_bounds()


def test_a_colmap_model_beside_the_frames_gives_its_points_bounds_in_the_frames_units(tmp_path):
    """The hand-made model of tests/data/test_colmap.py (a ring of cameras 4 from two points, whose near and far
    are RING_BOUNDS there) beside frames posed at half its scale: the bounds are RING_BOUNDS halved, and a
    model matching fewer than two frames by file name gives none."""
    from nerfexp.data.nerfstudio import colmap_point_bounds
    from nerfexp.data.transforms_file import Frame
    from tests.data.photographs import RING, RING_BOUNDS, hand_made_model

    model = tmp_path / "sparse" / "0"
    model.mkdir(parents=True)
    hand_made_model().write_binary(model)
    c2w = torch.eye(4, dtype=torch.float64).repeat(len(RING), 1, 1)
    c2w[:, :3, 3] = 0.5 * torch.tensor(RING, dtype=torch.float64) + torch.tensor([1.0, -2.0, 3.0])  # moved too
    frames = [Frame(f"images/view_{i}.png", c2w[i - 1], {}, None, f"frame {i}") for i in range(1, len(RING) + 1)]
    near, far = colmap_point_bounds(model, frames, c2w)
    assert (near, far) == pytest.approx((0.5 * RING_BOUNDS[0], 0.5 * RING_BOUNDS[1]), rel=1e-6)
    others = [Frame(f"images/other_{i}.png", c2w[i - 1], {}, None, f"frame {i}") for i in range(1, len(RING))]
    assert colmap_point_bounds(model, [frames[0], *others], c2w) is None
