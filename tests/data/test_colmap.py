"""COLMAP scenes: the whole pycolmap pipeline on renders of the built-in scene against their true
cameras, models written as text (today's and COLMAP 3's layout) and binary, the conventions against
hand-worked poses, the ray bounds, and the errors."""

import logging
import time

import numpy as np
import pycolmap
import pytest
import torch
from hydra import compose, initialize_config_module
from hydra.utils import instantiate
from PIL import Image

from nerfexp.data import colmap_sfm, procedural
from nerfexp.data.colmap import ColmapScene, colmap_to_c2w
from nerfexp.data.colmap_sfm import read_model
from nerfexp.data.datamodule import RayDataModule, fill_ray_bounds
from nerfexp.errors import DatasetError
from nerfexp.geometry.cameras import camera_rays, focal_from_fov, look_at
from nerfexp.geometry.lenses import Intrinsics, pixel_rays
from tests.data.photographs import (
    FOCAL,
    HEIGHT,
    N_VIEWS,
    POINTS,
    RING,
    RING_BOUNDS,
    SIZE,
    UP,
    WIDTH,
    digest,
    hand_made_model,
    render_photographs,
    rotation_degrees,
    true_cameras,
    umeyama,
    write_images,
)


def test_umeyama_recovers_a_known_similarity():
    g = torch.Generator().manual_seed(0)
    src = torch.randn(10, 3, generator=g, dtype=torch.float64)
    R, _ = torch.linalg.qr(torch.randn(3, 3, generator=g, dtype=torch.float64))
    R = R * torch.sign(torch.linalg.det(R))  # a rotation, not a reflection
    t = torch.tensor([1.0, -2.0, 0.5], dtype=torch.float64)
    s, R_found, t_found = umeyama(src, 2.5 * src @ R.T + t)
    assert s == pytest.approx(2.5)
    torch.testing.assert_close(R_found, R)
    torch.testing.assert_close(t_found, t)


# ---------------------------------------------------------------- the whole pipeline, end to end











@pytest.mark.slow
def test_pipeline_recovers_the_true_cameras_up_to_a_similarity(tmp_path, capfd):
    c2w_true = true_cameras()
    focal_true = focal_from_fov(SIZE, procedural.CAMERA_ANGLE_X)
    (tmp_path / "images").mkdir()
    images, distance = render_photographs(c2w_true, focal_true)
    for i, image in enumerate(images):
        Image.fromarray(image).save(tmp_path / "images" / f"{i:03d}.png")
    images_before = digest(tmp_path / "images")

    scene = ColmapScene(root=str(tmp_path))  # threads=-1, the default: every core
    data = scene.load()
    # COLMAP's own log (glog, on the process's stderr) holds no warning per extraction call about using every core
    assert "maximum number of threads" not in capfd.readouterr().err
    assert data.names == [f"{i:03d}.png" for i in range(N_VIEWS)]  # every view registered, in name order
    # SIMPLE_RADIAL (the default) estimated a small distortion: it goes into the rays, and the images are
    # read from where they are, never resampled into an undistorted copy
    assert not (tmp_path / "colmap" / "undistorted").exists() and data.image_dir == tmp_path / "images"
    lenses = data.intrinsics
    assert lenses.shape == (N_VIEWS,) and not lenses.fisheye.any()
    fx, fy, cx, cy = lenses.params.unbind(-1)
    assert torch.equal(fx, fy) and fx.tolist() == pytest.approx([focal_true] * N_VIEWS, rel=0.01)  # one f
    assert cx.tolist() == [SIZE / 2] * N_VIEWS and cy.tolist() == [SIZE / 2] * N_VIEWS  # not refined: centred
    k1 = lenses.distortion[:, 0]  # the photographs are a pinhole's: what COLMAP estimated is small
    assert (k1 == k1[0]).all() and abs(k1[0].item()) < 0.05 and not lenses.distortion[:, 1:].any(), lenses.distortion

    s, R, t = umeyama(data.c2w[:, :3, 3], c2w_true[:, :3, 3])  # recovered world -> true world
    centres = s * data.c2w[:, :3, 3] @ R.T + t
    centre_error = torch.linalg.vector_norm(centres - c2w_true[:, :3, 3], dim=-1)
    rotation_error = rotation_degrees(c2w_true[:, :3, :3].transpose(1, 2) @ R @ data.c2w[:, :3, :3])
    assert centre_error.max() < 0.01 * procedural.SCENE_RADIUS, centre_error
    assert rotation_error.max() < 1.0, rotation_error
    # normalized: camera centres within `bound` of the origin, the farthest on it
    assert torch.linalg.vector_norm(data.c2w[:, :3, 3], dim=-1).max().item() == pytest.approx(scene.bound)
    # near/far, in true units, enclose the true distance of (nearly) every pixel, and are not absurdly wide
    near, far = (bound / s for bound in scene.ray_bounds())
    inside = ((distance >= near) & (distance <= far)).double().mean().item()
    assert inside > 0.99 and near > 0.5 * distance.min() and far < 2 * distance.max(), (near, far, inside)

    test, train = scene.views("test"), scene.views("train")
    assert len(test) == 4 and len(train) == 26 and len(scene.views("val")) == 2  # every 8th image is a test view
    assert test.rgba.shape[1:] == (data.height, data.width, 4)
    assert torch.equal(test.intrinsics.params, data.intrinsics.params[::8])
    assert torch.equal(test.intrinsics.distortion, data.intrinsics.distortion[::8])
    torch.testing.assert_close(test.c2w, data.c2w[::8].float())

    # a second load reads the cache: nothing reconstructed or rewritten, and images/ untouched
    cache_before = digest(tmp_path / "colmap")
    start = time.perf_counter()
    again = ColmapScene(root=str(tmp_path), threads=2).load()
    assert time.perf_counter() - start < 5.0
    torch.testing.assert_close(again.c2w, data.c2w)
    assert digest(tmp_path / "colmap") == cache_before
    assert digest(tmp_path / "images") == images_before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["colmap", "images"]  # no temporary folder left


# ---------------------------------------------------------------- reading existing models

@pytest.mark.parametrize("form", ["text", "binary"])
def test_reads_a_model_written_as_text_or_binary(tmp_path, form):
    model = tmp_path / "sparse" / "0"
    model.mkdir(parents=True)
    getattr(hand_made_model(), f"write_{form}")(model)
    assert {p.suffix for p in model.iterdir()} == {".bin" if form == "binary" else ".txt"}
    write_images(tmp_path, [f"view_{i}.png" for i in range(1, 5)])

    scene = ColmapScene(root=str(tmp_path), holdout=2, n_val=1)
    data = scene.load()
    assert data.names == [f"view_{i}.png" for i in range(1, 5)]
    assert data.intrinsics.params.tolist() == [[FOCAL, FOCAL, WIDTH / 2, HEIGHT / 2]] * 4
    assert not data.intrinsics.is_distorted().any()
    # the mean camera centre is the origin and the cameras are 4 from it: with bound 4 the scale is 1
    assert data.scale == pytest.approx(1.0) and torch.allclose(data.centre, torch.zeros(3, dtype=torch.float64))
    expected = look_at(torch.tensor(RING, dtype=torch.float64), torch.zeros(3, dtype=torch.float64), UP)
    torch.testing.assert_close(data.c2w, expected)
    assert scene.ray_bounds() == pytest.approx(RING_BOUNDS)
    assert ColmapScene(root=str(tmp_path), near=2.0, far=6.0).ray_bounds() == (2.0, 6.0)  # configured values win

    views = scene.views("test")  # views 1 and 3 (indices 0 and 2)
    torch.testing.assert_close(views.c2w, expected[[0, 2]].float())
    assert views.rgba.shape == (2, HEIGHT, WIDTH, 4) and (views.rgba[1, ..., :3] == 20 / 255).all()
    assert (views.rgba[..., 3] == 1).all()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["images", "sparse"]  # a pinhole model: nothing written


def test_a_test_image_linked_to_a_training_image_is_refused_before_training(tmp_path):
    model = tmp_path / "sparse" / "0"
    model.mkdir(parents=True)
    hand_made_model().write_text(model)
    write_images(tmp_path, [f"view_{i}.png" for i in range(1, 5)])
    # holdout 2: views 1 and 3 test, 2 and 4 train; view 3 made a link to view 2 (other pose, COLMAP's name)
    (tmp_path / "images" / "view_3.png").unlink()
    (tmp_path / "images" / "view_3.png").symlink_to("view_2.png")
    data = RayDataModule(ColmapScene(root=str(tmp_path), holdout=2, n_val=1), batch_rays=64)
    with pytest.raises(DatasetError) as caught:
        data.setup("fit")
    images = tmp_path / "images"
    assert str(caught.value) == (f"the test view {images / 'view_3.png'} and the training view {images / 'view_2.png'} "
                                 f"are one view (they name one file ({images / 'view_3.png'})): a score on views "
                                 "training saw is no test score; keep it in one split")


def test_one_image_twice_in_a_split_is_refused_before_it_is_read(tmp_path):
    model = tmp_path / "sparse" / "0"
    model.mkdir(parents=True)
    hand_made_model().write_text(model)
    write_images(tmp_path, [f"view_{i}.png" for i in range(1, 4)])
    (tmp_path / "images" / "view_4.png").symlink_to("view_2.png")  # views 2 and 4: both training views
    with pytest.raises(DatasetError, match=r"view_2.png and .*view_4.png name one file .*: one view counted twice"):
        ColmapScene(root=str(tmp_path), holdout=2, n_val=1).views("train")


def test_the_conventions_by_hand_on_a_colmap_3_text_model(tmp_path):
    # A camera at (4, 0, 0) looking at the origin, z up. COLMAP's R has rows x = (0, 1, 0) (right),
    # y = (0, 0, -1) (down), z = (-1, 0, 0) (forward); t = -R eye = (0, 0, 4). Its quaternion
    # (w, x, y, z): w = sqrt(1 + tr R) / 2 = 0.5, x = (R21 - R12) / 4w = 0.5, y = (R02 - R20) / 4w = 0.5,
    # z = (R10 - R01) / 4w = -0.5. nerfexp's c2w: right (0, 1, 0), up (0, 0, 1), back (1, 0, 0), centre (4, 0, 0).
    (tmp_path / "cameras.txt").write_text("1 SIMPLE_PINHOLE 8 6 10 4 3\n")
    (tmp_path / "images.txt").write_text("1 0.5 0.5 0.5 -0.5 0 0 4 1 a.png\n4 3 1\n")
    (tmp_path / "points3D.txt").write_text("1 0 0 0 255 255 255 0 1 0\n")
    reconstruction = read_model(tmp_path)
    image = reconstruction.images[1]
    c2w = colmap_to_c2w(torch.tensor(image.cam_from_world().matrix())[None])[0]
    expected = torch.tensor([[0.0, 0, 1, 4], [1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 0, 1]], dtype=torch.float64)
    torch.testing.assert_close(c2w, expected)
    # the origin is in front of the camera, on its axis: pycolmap projects it to the image centre
    assert image.project_point(np.zeros(3)) == pytest.approx([4.0, 3.0])
    # the ray through the centre is the mean of the four
    origin, direction = camera_rays(c2w, 2, 2, Intrinsics.pinhole(10.0, 2, 2))
    assert torch.nn.functional.normalize(direction.sum((0, 1)), dim=-1).tolist() == pytest.approx([-1.0, 0, 0])


def test_colmap_to_c2w_of_the_identity_rotation():
    # R = I, t = (0, 0, 4): the camera sits at -t = (0, 0, -4) and looks down COLMAP's +z, which is
    # OpenGL's -z axis, so c2w[:3, 2] = (0, 0, -1); COLMAP's y (down) is OpenGL's -y.
    c2w = colmap_to_c2w(torch.tensor([[[1.0, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 4]]], dtype=torch.float64))[0]
    expected = torch.tensor([[1.0, 0, 0, 0], [0, -1, 0, 0], [0, 0, -1, -4], [0, 0, 0, 1]], dtype=torch.float64)
    torch.testing.assert_close(c2w, expected)


def test_the_real_config_builds_the_scene(tmp_path):
    (tmp_path / "sparse" / "0").mkdir(parents=True)
    hand_made_model().write_binary(tmp_path / "sparse" / "0")
    write_images(tmp_path, [f"view_{i}.png" for i in range(1, 5)])
    with initialize_config_module("nerfexp.conf", version_base=None):
        cfg = compose("config", overrides=["data=colmap", f"data.root={tmp_path}", "data.holdout=2"])
    scene = instantiate(cfg.data)
    assert isinstance(scene, ColmapScene) and scene.max_side == cfg.scale.max_side and scene.near is None
    assert len(scene.views("train")) == 2 and scene.ray_bounds() == pytest.approx(RING_BOUNDS)
    # the renderer is built from data.near/far: a run fills them in from the sparse points first
    fill_ray_bounds(cfg)
    assert (cfg.data.near, cfg.data.far) == pytest.approx(RING_BOUNDS)
    renderer = instantiate(cfg.model.renderer)
    assert (renderer.near, renderer.far) == pytest.approx(RING_BOUNDS)


# ---------------------------------------------------------------- errors

def test_no_images_folder(tmp_path):
    with pytest.raises(DatasetError, match=r"images does not exist: data.root must be a folder holding images/"):
        ColmapScene(root=str(tmp_path)).load()


def test_blank_images_register_nothing_and_leave_the_folder_as_it_was(tmp_path):
    (tmp_path / "images").mkdir()
    for i in range(3):
        Image.fromarray(np.full((64, 64, 3), 128, dtype=np.uint8)).save(tmp_path / "images" / f"{i}.png")
    before = digest(tmp_path)
    with pytest.raises(DatasetError, match=r"COLMAP registered 0 of 3 images of .*images .*try more overlap"):
        ColmapScene(root=str(tmp_path), threads=2).load()
    assert digest(tmp_path) == before  # nothing added (no cache, no temporary folder), nothing changed


def test_too_few_registered_images(tmp_path, monkeypatch):
    write_images(tmp_path, [f"{i:02d}.png" for i in range(30)])

    def two_registered(database_path, image_path, output_path, options):
        return {0: hand_made_model(ring=RING[:2])}

    monkeypatch.setattr(pycolmap, "extract_features", lambda *args, **kwargs: None)
    monkeypatch.setattr(pycolmap, "match_exhaustive", lambda *args, **kwargs: None)
    monkeypatch.setattr(pycolmap, "incremental_mapping", two_registered)
    message = (r"COLMAP registered 2 of 30 images of .*images \(at least 24 needed, data.min_registered=0.8\); "
               r"try more overlap between neighbouring views")
    with pytest.raises(DatasetError, match=message):
        ColmapScene(root=str(tmp_path)).load()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["images"]


@pytest.mark.parametrize(("threads", "expected", "capped"), [(64, 2, True), (-1, 2, False), (1, 1, False)])
def test_colmap_runs_at_most_the_cpus_this_process_may_use_and_says_where_it_caps(tmp_path, monkeypatch, caplog,
                                                                                 threads, expected, capped):
    # each of COLMAP's stages is asked for its thread count (one per CPU this process may use for -1, where COLMAP's
    # own -1 takes every core of the machine); what they did is beside the point: two images are registered
    write_images(tmp_path, [f"{i:02d}.png" for i in range(2)])
    asked = []
    monkeypatch.setattr(colmap_sfm, "available_cpus", lambda: 2)
    monkeypatch.setattr(pycolmap, "extract_features", lambda *args, extraction_options, **kwargs: asked.append(
        extraction_options.num_threads))
    monkeypatch.setattr(pycolmap, "match_exhaustive", lambda *args, matching_options, **kwargs: asked.append(
        matching_options.num_threads))

    def mapping(database_path, image_path, output_path, options):
        asked.append(options.num_threads)
        return {0: hand_made_model(ring=RING[:2])}

    monkeypatch.setattr(pycolmap, "incremental_mapping", mapping)
    with caplog.at_level(logging.WARNING, logger=colmap_sfm.__name__), pytest.raises(DatasetError):
        ColmapScene(root=str(tmp_path), threads=threads).load()  # no model written: refused after the stages ran
    assert asked == [expected] * 3
    lines = [record.getMessage() for record in caplog.records]
    assert lines == ([f"data.threads={threads}: more threads than the 2 CPUs this process may use; 2 run (threads "
                      "beyond the CPUs only wait on each other)"] if capped else [])


def test_unsupported_camera_model(tmp_path):
    write_images(tmp_path, ["a.png"])
    with pytest.raises(DatasetError, match=r"unsupported camera model 'EQUIRECTANGULAR' \(data.camera_model\)"):
        ColmapScene(root=str(tmp_path), camera_model="EQUIRECTANGULAR").load()


def assert_rays_through_the_keypoints_hit_the_points(tmp_path, data) -> None:
    """The ray of each image through the image coordinates where COLMAP observed each of POINTS (its
    keypoints, projected by COLMAP's own lens model) passes through that point: nerfexp's lens inverts
    COLMAP's (principal point, distortion) exactly. The scene is not rescaled (RING at bound 4: scale 1)."""
    reconstruction = read_model(tmp_path / "sparse")
    for k, image_id in enumerate(sorted(reconstruction.images)):
        image = reconstruction.images[image_id]
        keypoints = torch.tensor(np.array([point.xy for point in image.points2D]), dtype=torch.float64)
        d = pixel_rays(keypoints, data.intrinsics[k]) @ data.c2w[k, :3, :3].T  # [2, 3] world directions
        to_points = torch.tensor(POINTS, dtype=torch.float64) - data.c2w[k, :3, 3]
        miss = torch.linalg.vector_norm(torch.linalg.cross(to_points, d, dim=-1), dim=-1)
        assert miss.max() < 1e-9, (image.name, miss)


def test_an_off_centre_principal_point_is_read_into_the_rays(tmp_path):
    (tmp_path / "sparse").mkdir()
    hand_made_model(principal_point=(5.0, 3.5)).write_binary(tmp_path / "sparse")
    write_images(tmp_path, [f"view_{i}.png" for i in range(1, 5)])
    data = ColmapScene(root=str(tmp_path)).load()
    assert data.intrinsics.params.tolist() == [[FOCAL, FOCAL, 5.0, 3.5]] * 4
    assert_rays_through_the_keypoints_hit_the_points(tmp_path, data)


def test_a_distorted_model_is_read_with_its_distortion_and_its_images_as_they_are(tmp_path):
    (tmp_path / "sparse").mkdir()
    hand_made_model(model="SIMPLE_RADIAL", distortion=(0.1,)).write_binary(tmp_path / "sparse")
    write_images(tmp_path, [f"view_{i}.png" for i in range(1, 5)])
    scene = ColmapScene(root=str(tmp_path), holdout=2)
    data = scene.load()
    assert data.image_dir == tmp_path / "images"
    assert data.intrinsics.params.tolist() == [[FOCAL, FOCAL, WIDTH / 2, HEIGHT / 2]] * 4
    assert data.intrinsics.distortion[:, 0].tolist() == [0.1] * 4 and not data.intrinsics.distortion[:, 1:].any()
    assert not data.intrinsics.fisheye.any()
    assert_rays_through_the_keypoints_hit_the_points(tmp_path, data)
    views = scene.views("train")  # views 2 and 4: their images read as they are, their lenses kept
    assert views.rgba.shape == (2, HEIGHT, WIDTH, 4) and (views.rgba[0, ..., :3] == 10 / 255).all()
    assert views.intrinsics.distortion[:, 0].tolist() == [0.1] * 2
    assert sorted(p.name for p in tmp_path.iterdir()) == ["images", "sparse"]  # no undistorted copy written


def test_a_cache_folder_without_a_model_is_left_alone(tmp_path):
    write_images(tmp_path, ["a.png"])
    (tmp_path / "colmap").mkdir()
    (tmp_path / "colmap" / "notes.txt").write_text("mine")
    with pytest.raises(DatasetError, match=r"colmap exists but holds no sparse model in sparse/0; move it away"):
        ColmapScene(root=str(tmp_path)).load()
    assert (tmp_path / "colmap" / "notes.txt").read_text() == "mine"
