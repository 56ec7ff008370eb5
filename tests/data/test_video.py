"""Video input for COLMAP scenes (``data.video``): sharpness against hand-worked values and blurred
copies, the choice of each interval's sharpest frame, the cached frame folder and its errors on small
synthetic videos, the matcher a video implies, and (slow) the whole path video -> frames -> COLMAP ->
posed views on renders of the built-in scene, with blurred frames among them."""

import json
import math
import re
import sys

import imageio.v2 as imageio
import numpy as np
import pycolmap
import pytest
import torch
from hydra import compose, initialize_config_module
from hydra.utils import instantiate
from PIL import Image
from scipy import ndimage

from nerfexp.data import procedural
from nerfexp.data import video as video_module
from nerfexp.data.colmap import ColmapScene
from nerfexp.data.video import (
    FRAMES,
    SOURCE,
    frame_name,
    frame_sharpness,
    interval_of,
    luma,
    n_kept_of,
    sharpest_frames,
    video_frames,
)
from nerfexp.errors import ConfigError, DatasetError
from nerfexp.extras import MissingExtraError
from nerfexp.geometry.cameras import focal_from_fov
from tests.data.photographs import (
    SIZE,
    digest,
    render_photographs,
    rotation_degrees,
    true_cameras,
    umeyama,
    write_images,
)

RATE, FPS = 6, 2  # the test videos' frames per second, and the frames kept per second: intervals of 3 frames
SIDE = 64  # the synthetic videos' frames are SIDE x SIDE (a multiple of 16, as H.264 encoders want)


def checker(cell: int = 4) -> np.ndarray:
    """A black and white checker [SIDE, SIDE, 3] uint8 of ``cell``-pixel squares."""
    i, j = np.indices((SIDE, SIDE)) // cell
    return np.repeat((255 * ((i + j) % 2)).astype(np.uint8)[..., None], 3, -1)


def texture(seed: int) -> np.ndarray:
    """A sharp grey texture [SIDE, SIDE, 3] uint8 of random 4 x 4 pixel cells, different for each seed."""
    cells = np.random.default_rng(seed).integers(0, 256, (SIDE // 4, SIDE // 4), dtype=np.uint8)
    return np.repeat(np.kron(cells, np.ones((4, 4), dtype=np.uint8))[..., None], 3, -1)


def box_blur(rgb: np.ndarray, radius: int) -> np.ndarray:
    """``rgb`` [H, W, 3] uint8 averaged over (2 radius + 1)^2 pixel squares (edges repeated), rounded."""
    size = (2 * radius + 1, 2 * radius + 1, 1)
    return np.round(ndimage.uniform_filter(rgb.astype(np.float64), size, mode="nearest")).astype(np.uint8)


def blurred_video(images: list[np.ndarray]) -> list[np.ndarray]:
    """Three frames per image (one interval at RATE, FPS): image i itself at position i % 3 of its interval,
    box-blurred copies (radius 1, then 2) at the other two, so the sharp frame's place varies."""
    frames = []
    for i, image in enumerate(images):
        blurred = [box_blur(image, 1), box_blur(image, 2)]
        frames += blurred[:i % 3] + [image] + blurred[i % 3:]
    return frames


def write_video(path, frames: list[np.ndarray], rate: float = RATE) -> None:
    """An H.264 MP4 of ``frames`` [H, W, 3] uint8 at ``rate`` per second, at quality 10 (crf 0: lossless
    luma; the colours are subsampled as in any yuv420p video)."""
    imageio.mimwrite(path, frames, format="FFMPEG", fps=rate, codec="libx264", quality=10)


def read_rgb(path) -> np.ndarray:
    return np.asarray(Image.open(path).convert("RGB"))


def grey_difference(a: np.ndarray, b: np.ndarray) -> float:
    """The mean absolute difference of two RGB images [H, W, 3] uint8 in grey (``luma``), which an H.264
    video at crf 0 keeps almost exactly while it subsamples the colours."""
    return float(np.abs(luma(a) - luma(b)).mean())


# ---------------------------------------------------------------- sharpness and the choice of frames

def test_sharpness_of_one_bright_pixel_by_hand():
    # a single 1 in a 5 x 5 image of zeros: over the 3 x 3 interior the Laplacian is -4 at the pixel, 1 at
    # its four neighbours and 0 at the four corners: mean 0, variance (16 + 4) / 9
    grey = np.zeros((5, 5))
    grey[2, 2] = 1.0
    assert frame_sharpness(grey) == pytest.approx(20 / 9, rel=1e-12)


def test_sharpness_is_zero_for_a_flat_image_and_falls_with_blur():
    assert frame_sharpness(luma(np.full((SIDE, SIDE, 3), 200, dtype=np.uint8))) == 0.0
    sharp = checker()
    sharpness = [frame_sharpness(luma(image)) for image in (sharp, box_blur(sharp, 1), box_blur(sharp, 2))]
    assert sharpness[0] > sharpness[1] > sharpness[2] > 0, sharpness


def test_luma_weights():
    rgb = np.array([[[255, 0, 0], [0, 255, 0], [0, 0, 255], [10, 10, 10]]], dtype=np.uint8)  # [1, 4, 3]
    assert luma(rgb)[0].tolist() == pytest.approx([0.299 * 255, 0.587 * 255, 0.114 * 255, 10.0])


def test_intervals_by_hand():
    # rate 30, fps 2: frame k is shown at k / 30 s; interval i spans [i / 2, (i + 1) / 2) s: 15 frames each
    assert [interval_of(k, 30, 2) for k in (0, 14, 15, 29, 30)] == [0, 0, 1, 1, 2]
    assert n_kept_of(90, 30, 2) == 6 and n_kept_of(91, 30, 2) == 7 and n_kept_of(0, 30, 2) == 0  # ceil(D fps)
    # NTSC's 29.97 per second: 3 s are 90 frames (the 90th at 2.97 s), still 6 intervals
    assert n_kept_of(90, 30000 / 1001, 2) == 6
    # fps above the video's rate: every frame is its own interval
    assert [interval_of(k, 10, 25) for k in range(4)] == [0, 2, 5, 7] and n_kept_of(4, 10, 25) == 4


def test_the_sharpest_frame_of_each_interval_is_kept_as_soon_as_its_interval_ends():
    images = [texture(seed) for seed in range(4)]
    frames = blurred_video(images) + [box_blur(texture(4), 2), texture(4)]  # a last, partial interval of 2
    consumed = []

    def stream():
        for k, frame in enumerate(frames):
            consumed.append(k)
            yield frame

    kept = []
    for interval, rgb in sharpest_frames(stream(), RATE, FPS):
        assert len(consumed) <= 3 * (interval + 1) + 1  # yielded once the next interval's first frame is read
        kept.append((interval, rgb))
    assert [interval for interval, _ in kept] == [0, 1, 2, 3, 4]
    for (_, rgb), image in zip(kept, images + [texture(4)]):
        assert np.array_equal(rgb, image)  # never a blurred copy


def test_the_first_of_equally_sharp_frames_is_kept():
    first, second, blurred = texture(0), texture(0).copy(), box_blur(texture(0), 1)
    [(interval, rgb)] = list(sharpest_frames([blurred, first, second], RATE, FPS))
    assert interval == 0 and rgb is first


# ---------------------------------------------------------------- the frame folder

@pytest.fixture
def clip(tmp_path):
    """scene/clip.mp4: 2 s at RATE of four textures, each sharp in one frame of its interval and blurred in
    the other two (``blurred_video``); the textures' list is the fixture's second value."""
    root = tmp_path / "scene"
    root.mkdir()
    images = [texture(seed) for seed in range(4)]
    write_video(root / "clip.mp4", blurred_video(images))
    return root / "clip.mp4", images


def test_frames_are_the_sharp_ones_duration_times_fps_of_them(clip):
    path, images = clip
    folder = video_frames(path.parent, "clip.mp4", FPS)
    assert folder == path.parent / FRAMES
    assert sorted(p.name for p in folder.iterdir()) == [frame_name(i) for i in range(2 * FPS)] + [SOURCE]
    frames = blurred_video(images)
    for i, image in enumerate(images):
        kept = read_rgb(folder / frame_name(i))
        differences = [grey_difference(kept, frame) for frame in frames[3 * i:3 * i + 3]]
        assert np.argmin(differences) == i % 3 and grey_difference(kept, image) < 1.0, differences
    assert json.loads((folder / SOURCE).read_text()) == {"video": "clip.mp4", "fps": FPS}
    assert sorted(p.name for p in path.parent.iterdir()) == ["clip.mp4", FRAMES]  # no temporary folder left


def test_a_second_run_reads_the_cached_frames_without_decoding(clip, monkeypatch):
    path, _ = clip
    folder = video_frames(path.parent, "clip.mp4", FPS)
    before = digest(folder)

    def no_decoding(*args, **kwargs):
        raise AssertionError("the video was decoded again")

    monkeypatch.setattr(imageio, "get_reader", no_decoding)
    assert video_frames(path.parent, "clip.mp4", FPS) == folder
    path.unlink()  # the video is not needed once its frames are cached
    assert video_frames(path.parent, "clip.mp4", FPS) == folder
    assert digest(folder) == before  # nothing rewritten


def test_frames_of_another_fps_or_a_folder_nerfexp_did_not_make_are_refused_and_kept(clip):
    path, _ = clip
    folder = video_frames(path.parent, "clip.mp4", FPS)
    before = digest(path.parent)
    with pytest.raises(DatasetError, match=r"frames holds the frames of clip.mp4 at 2 per second, not of clip.mp4 at "
                                           r"data.fps=3; move frames/ and colmap/ away"):
        video_frames(path.parent, "clip.mp4", 3)
    (folder / SOURCE).unlink()
    with pytest.raises(DatasetError, match=r"frames exists but holds no readable source.json, so nerfexp did not "
                                           r"take it from a video; move it away"):
        video_frames(path.parent, "clip.mp4", FPS)
    del before[f"{FRAMES}/{SOURCE}"]
    assert digest(path.parent) == before


@pytest.mark.parametrize("fps", [0, -2, math.nan, math.inf, 5e-324, 1e-4, 1001, 1e308])
def test_fps_must_be_within_what_videos_hold(tmp_path, fps):
    with pytest.raises(ConfigError, match=r"data.fps must be a number in \[0.001, 1000\] \(frames kept per second "
                                          r"of video\), got "):
        video_frames(tmp_path, "missing.mp4", fps)
    assert list(tmp_path.iterdir()) == []


def test_a_missing_video(tmp_path):
    with pytest.raises(DatasetError, match=r"video .*missing.mp4 does not exist \(data.video, relative to data.root\)"):
        ColmapScene(root=str(tmp_path), video="missing.mp4").load()
    assert list(tmp_path.iterdir()) == []


def test_without_the_video_extra(clip, monkeypatch):
    path, _ = clip
    monkeypatch.setitem(sys.modules, "imageio_ffmpeg", None)  # as if imageio-ffmpeg were not installed
    with pytest.raises(MissingExtraError, match=re.escape('data.video needs imageio_ffmpeg, which is not installed: '
                                                          'pip install "nerfexp[video]"')):
        video_frames(path.parent, "clip.mp4", FPS)
    assert [p.name for p in path.parent.iterdir()] == ["clip.mp4"]


def test_a_file_ffmpeg_cannot_decode(tmp_path):
    (tmp_path / "clip.mp4").write_bytes(b"not a video\n" * 100)
    with pytest.raises(DatasetError, match=r"clip.mp4: not a video ffmpeg can decode \(data.video\): .+"):
        video_frames(tmp_path, "clip.mp4", FPS)
    assert [p.name for p in tmp_path.iterdir()] == ["clip.mp4"]


@pytest.mark.parametrize("duration_known", [True, False])
def test_a_video_too_short_for_three_frames(tmp_path, monkeypatch, duration_known):
    write_video(tmp_path / "clip.mp4", blurred_video([texture(0), texture(1)]))  # 1 s: 2 frames at FPS
    if duration_known:  # refused by its duration, before a frame is decoded
        monkeypatch.setattr(video_module, "decoded_frames", lambda *args: pytest.fail("frames were decoded"))
    else:  # a file that does not say its duration: refused once its frames are counted
        open_video = video_module.open_video
        monkeypatch.setattr(video_module, "open_video", lambda path: (*open_video(path)[:2], 0.0))
    with pytest.raises(DatasetError, match=r"clip.mp4 gives 2 frames at data.fps=2 \(at least 3 needed\): raise "
                                           r"data.fps or use a longer video"):
        video_frames(tmp_path, "clip.mp4", FPS)
    assert [p.name for p in tmp_path.iterdir()] == ["clip.mp4"]  # nothing kept, no temporary folder


def test_the_real_config_builds_a_video_scene(clip):
    path, _ = clip
    with initialize_config_module("nerfexp.conf", version_base=None):
        cfg = compose("config", overrides=["data=colmap", f"data.root={path.parent}", "data.video=clip.mp4"])
    scene = instantiate(cfg.data)
    assert isinstance(scene, ColmapScene) and (scene.video, scene.fps, scene.matcher) == ("clip.mp4", 2, None)


# ---------------------------------------------------------------- the matcher, and features in batches

@pytest.mark.parametrize(("source", "matcher", "called"), [
    ("video", None, "sequential"), ("video", "exhaustive", "exhaustive"),
    ("photographs", None, "exhaustive"), ("photographs", "sequential", "sequential"),
])
def test_a_video_is_matched_sequentially_unless_data_matcher_says_otherwise(clip, monkeypatch, source, matcher,
                                                                            called):
    path, _ = clip
    root = path.parent
    if source == "photographs":
        write_images(root, [frame_name(i) for i in range(4)])
    batches, matched = [], []
    monkeypatch.setattr(pycolmap, "extract_features", lambda database, image_dir, names, **kwargs:
                        batches.append((image_dir.name, list(names))))
    for name in ("exhaustive", "sequential"):
        monkeypatch.setattr(pycolmap, f"match_{name}", lambda *args, name=name, **kwargs: matched.append(name))
    monkeypatch.setattr(pycolmap, "incremental_mapping", lambda *args, **kwargs: {})
    with pytest.raises(DatasetError, match=r"COLMAP registered 0 of 4 images"):
        ColmapScene(root=str(root), video="clip.mp4" if source == "video" else None, matcher=matcher,
                    threads=1).load()
    assert matched == [called]
    # the features of every image, in name order, in batches of two images per thread
    folder = FRAMES if source == "video" else "images"
    assert batches == [(folder, [frame_name(0), frame_name(1)]), (folder, [frame_name(2), frame_name(3)])]


# ---------------------------------------------------------------- the whole path, end to end

N_VIEWS = 16  # the first 16 of test_colmap's cameras: half its wavy ring, 12 degrees apart


@pytest.mark.slow
def test_video_to_frames_to_colmap_to_posed_views(tmp_path, monkeypatch):
    c2w_true = true_cameras()[:N_VIEWS]
    focal_true = focal_from_fov(SIZE, procedural.CAMERA_ANGLE_X)
    renders, _ = render_photographs(c2w_true, focal_true)  # [N, SIZE, SIZE, 3] uint8
    frames = blurred_video(list(renders))  # 8 s at RATE
    write_video(tmp_path / "clip.mp4", frames)
    sequential = []
    match_sequential = pycolmap.match_sequential

    def counted_match_sequential(*args, **kwargs):
        sequential.append(1)
        return match_sequential(*args, **kwargs)

    monkeypatch.setattr(pycolmap, "match_sequential", counted_match_sequential)

    scene = ColmapScene(root=str(tmp_path), video="clip.mp4", threads=2)
    data = scene.load()
    assert data.names == [frame_name(i) for i in range(N_VIEWS)]  # 8 s x 2 per second, every frame registered
    assert sequential == [1]  # a video is matched sequentially
    for i in range(N_VIEWS):  # each kept frame is its interval's sharp render, never a blurred copy
        kept = read_rgb(tmp_path / FRAMES / frame_name(i))
        differences = [grey_difference(kept, frame) for frame in frames[3 * i:3 * i + 3]]
        assert np.argmin(differences) == i % 3, (i, differences)
    with pycolmap.Database.open(tmp_path / "colmap" / "database.db") as database:
        assert database.num_cameras() == 1 and database.num_images() == N_VIEWS  # one shared camera

    # the cameras up to a similarity, twice test_colmap's tolerances on centres and focal length: half its
    # ring of views, through a video's subsampled colours (one run here: 0.9% of the radius, 0.4 degrees)
    s, R, t = umeyama(data.c2w[:, :3, 3], c2w_true[:, :3, 3])  # recovered world -> true world
    centre_error = torch.linalg.vector_norm(s * data.c2w[:, :3, 3] @ R.T + t - c2w_true[:, :3, 3], dim=-1)
    rotation_error = rotation_degrees(c2w_true[:, :3, :3].transpose(1, 2) @ R @ data.c2w[:, :3, :3])
    assert centre_error.max() < 0.02 * procedural.SCENE_RADIUS, centre_error
    assert rotation_error.max() < 1.0, rotation_error
    fx, fy, cx, cy = data.intrinsics.params.unbind(-1)  # SIMPLE_RADIAL: one f, the principal point not refined
    assert torch.equal(fx, fy) and fx.tolist() == pytest.approx([focal_true] * N_VIEWS, rel=0.02)
    assert cx.tolist() == cy.tolist() == [SIZE / 2] * N_VIEWS
    assert abs(data.intrinsics.distortion[0, 0].item()) < 0.05 and not data.intrinsics.distortion[:, 1:].any()
    assert data.image_dir == tmp_path / FRAMES and not (tmp_path / "colmap" / "undistorted").exists()  # as they are
    train = scene.views("train")  # holdout 8: frames 0 and 8 are test views
    assert len(train) == N_VIEWS - 2 and train.rgba.shape[1:] == (data.height, data.width, 4)

    # a second load reads both caches: no decoding, nothing rewritten, no temporary folder left
    before = digest(tmp_path)
    monkeypatch.setattr(imageio, "get_reader", lambda *args, **kwargs: pytest.fail("the video was decoded again"))
    again = ColmapScene(root=str(tmp_path), video="clip.mp4", threads=2).load()
    torch.testing.assert_close(again.c2w, data.c2w)
    assert digest(tmp_path) == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["clip.mp4", "colmap", FRAMES]
