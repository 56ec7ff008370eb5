"""``nerfexp-view``: the viewer's cameras against nerfexp's ``look_at`` and viser's own conversions, the
progressive schedule and its abandoned refinements, and the command in a real headless browser."""

import json
import math
import queue
import re
import shutil
import signal
import subprocess
import threading
import time
from types import SimpleNamespace

import numpy as np
import pytest
import torch
from hydra.utils import instantiate
from PIL import Image
from viser import transforms as viser_transforms

from nerfexp import manifest
from nerfexp.commands import view
from nerfexp.geometry.cameras import camera_rays, focal_from_fov, look_at
from nerfexp.geometry.lenses import Intrinsics
from nerfexp.geometry.viewer_cameras import vertical_fov
from nerfexp.products.camera_files import read_camera_path
from nerfexp.products.trained import load_run
from nerfexp.products.viewer import (
    ProgressiveRenderer,
    Viewer,
    ViewRequest,
    refinement_sizes,
    render_request,
    saved_camera_path,
    target_size,
    viewer_c2w,
    viewer_pose,
)
from nerfexp.rundir.layout import CAMERA_PATH
from nerfexp.rundir.trained import run_config
from tests.browser import close_page, open_page, page_screenshot
from tests.helpers import command

POSES = [  # (eye, target, world up)
    ([4.0, 0.0, 1.0], [0.0, 0.0, 0.0], [0.0, 0.0, 1.0]),
    ([-1.4416, 3.1499, 2.0], [0.0, 0.0, 0.0], [0.0, 0.0, 1.0]),
    ([0.5, -2.0, 0.3], [1.0, 1.0, -1.0], [0.0, 1.0, 0.0]),
    ([0.0, 0.0, 3.0], [0.2, 0.1, 0.0], [0.0, 1.0, 0.0]),  # looking almost straight down the z axis
]


def viser_wxyz(eye, target, up) -> np.ndarray:
    """The orientation of a viser camera at ``eye`` looking at ``target`` with up direction ``up``, worked
    out by hand in viser's convention (``CameraHandle.wxyz``: OpenCV's axes, x right, y down, z forward, the
    rotation's columns) and made a quaternion by viser's own ``transforms.SO3``."""
    eye, target, up = (np.asarray(v, dtype=np.float64) for v in (eye, target, up))
    forward = (target - eye) / np.linalg.norm(target - eye)
    right = np.cross(forward, up)
    right = right / np.linalg.norm(right)
    down = np.cross(forward, right)
    return viser_transforms.SO3.from_matrix(np.stack([right, down, forward], -1)).wxyz


@pytest.mark.parametrize("eye, target, up", POSES)
def test_a_viewer_camera_looking_at_a_point_is_the_camera_look_at_gives(eye, target, up):
    eye, target, up = (torch.tensor(v, dtype=torch.float64) for v in (eye, target, up))
    expected = look_at(eye, target, up)
    c2w = viewer_c2w(torch.from_numpy(viser_wxyz(eye.numpy(), target.numpy(), up.numpy())), eye)
    torch.testing.assert_close(c2w, expected, atol=1e-9, rtol=0)
    # and back: the pose a frustum is drawn at
    back_wxyz, position = viewer_pose(expected)
    torch.testing.assert_close(position, eye)
    torch.testing.assert_close(viewer_c2w(back_wxyz, position), expected, atol=1e-12, rtol=0)


def test_the_viewers_centre_pixel_sees_the_point_looked_at_and_its_top_row_sees_up():
    eye, target, up = torch.tensor([3.0, 1.0, 2.0]), torch.tensor([0.5, -0.5, 0.25]), torch.tensor([0.0, 0.0, 1.0])
    wxyz = torch.from_numpy(viser_wxyz(eye.double().numpy(), target.double().numpy(), up.double().numpy()))
    origins, directions = camera_rays(viewer_c2w(wxyz, eye), 3, 3, Intrinsics.pinhole(2.0, 3, 3))
    torch.testing.assert_close(origins[1, 1], eye.double())
    torch.testing.assert_close(directions[1, 1], ((target - eye) / (target - eye).norm()).double())
    assert directions[0, 1] @ up.double() > directions[1, 1] @ up.double() > directions[2, 1] @ up.double()
    assert (directions[1, 2] - directions[1, 0]) @ torch.linalg.cross(target - eye, up).double() > 0  # right


def test_a_quarter_turn_and_back():
    # viser's quaternion of a quarter turn about z maps x to y; the pose read back is the same camera
    quarter_turn_about_z = torch.tensor([math.cos(math.pi / 4), 0, 0, math.sin(math.pi / 4)], dtype=torch.float64)
    c2w = viewer_c2w(quarter_turn_about_z, torch.tensor([1.0, 2.0, 3.0]))
    opencv_rotation = torch.tensor([[0.0, -1, 0], [1, 0, 0], [0, 0, 1]], dtype=torch.float64)
    flip_y_and_z = torch.diag(torch.tensor([1.0, -1, -1], dtype=torch.float64))
    torch.testing.assert_close(c2w[:3, :3], opencv_rotation @ flip_y_and_z)
    torch.testing.assert_close(c2w[:3, 3], torch.tensor([1.0, 2.0, 3.0], dtype=torch.float64))
    wxyz, position = viewer_pose(c2w)
    torch.testing.assert_close(viewer_c2w(wxyz, position), c2w, atol=1e-12, rtol=0)


def test_vertical_field_of_view_and_focal_length_are_inverses():
    assert vertical_fov(100, 50.0) == pytest.approx(math.pi / 2)  # 2 atan(50 / 50)
    assert focal_from_fov(100, math.pi / 2) == pytest.approx(50.0)
    assert focal_from_fov(37, vertical_fov(37, 81.5)) == pytest.approx(81.5)


def test_the_progressive_schedule_goes_from_an_eighth_of_the_width_to_all_of_it():
    assert refinement_sizes(48, 64) == [(6, 8), (12, 16), (24, 32), (48, 64)]
    assert refinement_sizes(18, 24) == [(2, 3), (4, 6), (9, 12), (18, 24)]
    assert refinement_sizes(6, 8) == [(1, 1), (2, 2), (3, 4), (6, 8)]
    assert refinement_sizes(2, 3) == [(1, 1), (1, 2), (2, 3)]  # 1/8 and 1/4 are both one pixel
    assert refinement_sizes(1, 1) == [(1, 1)]
    assert target_size(4 / 3, 640, 24) == (18, 24)  # the canvas is wider than --max-width
    assert target_size(2.0, 100, 800) == (50, 100)  # narrower: its own width
    assert target_size(640 / 337, 640, 24) == (13, 24)


def request(x: float, kind: str = "rgb") -> ViewRequest:
    c2w = torch.eye(4, dtype=torch.float64)
    c2w[0, 3] = x
    return ViewRequest(c2w, 1.0, 16, 32, kind)


def test_a_camera_that_moves_abandons_the_refinement_and_the_new_camera_is_rendered_coarse_to_fine():
    """A fake render that moves the camera once, while rendering camera 0 at 1/4 of the width, and then
    renders in bands, as the viewer does, checking stale() between them."""
    renders, shown, finished = [], [], threading.Event()
    moved = threading.Event()

    def render(req, height, width, stale):
        renders.append((float(req.c2w[0, 3]), height, width))
        if (float(req.c2w[0, 3]), width) == (0.0, 8) and not moved.is_set():
            moved.set()
            progressive.request(request(1.0))  # the camera moves while this size is rendered
        for _ in range(height):  # bands of rows
            if stale():
                return None
        return np.zeros((height, width, 3), np.uint8)

    def show(req, pixels):
        shown.append((float(req.c2w[0, 3]), pixels.shape[:2]))
        if pixels.shape[:2] == (req.height, req.width) and float(req.c2w[0, 3]) == 1.0:
            finished.set()

    progressive = ProgressiveRenderer(render, show, report=pytest.fail)
    progressive.request(request(0.0))
    assert finished.wait(10)
    progressive.close()
    assert renders == [(0.0, 2, 4), (0.0, 4, 8), (1.0, 2, 4), (1.0, 4, 8), (1.0, 8, 16), (1.0, 16, 32)]
    assert shown == [(0.0, (2, 4)), (1.0, (2, 4)), (1.0, (4, 8)), (1.0, (8, 16)), (1.0, (16, 32))]
    assert not progressive._thread.is_alive()


def test_a_failed_render_is_reported_and_the_next_camera_still_rendered():
    reports, shown, done = [], [], threading.Event()

    def render(req, height, width, stale):
        if float(req.c2w[0, 3]) == 0.0:
            raise RuntimeError("out of memory")
        return np.zeros((height, width, 3), np.uint8)

    def show(req, pixels):
        shown.append(pixels.shape[:2])
        if pixels.shape[:2] == (16, 32):
            done.set()

    progressive = ProgressiveRenderer(render, show, reports.append)
    progressive.request(request(0.0))
    time.sleep(0.2)
    progressive.request(request(1.0))
    assert done.wait(10)
    progressive.close()
    assert reports == ["rendering failed: RuntimeError: out of memory"] and shown[-1] == (16, 32)


def test_a_saved_camera_path_is_read_back_by_nerfexp_render(tmp_path):
    keyframes = [request(0.0), request(2.0, "depth")]
    path = saved_camera_path(keyframes, max_width=25)
    # 25 made even (12.5 pairs round to 12); the first keyframe's 32 x 16 aspect and vertical field of view, 1 rad
    assert (path.name, path.width, path.height) == ("viewer", 24, 12)
    focal = 6 / math.tan(0.5)  # a pinhole centred on the 24 x 12 frames
    torch.testing.assert_close(path.intrinsics.params, torch.tensor([focal, focal, 12.0, 6.0], dtype=torch.float64))
    assert not path.intrinsics.is_distorted()
    (tmp_path / CAMERA_PATH.name).write_text(json.dumps(path.record()))
    read = read_camera_path(tmp_path / CAMERA_PATH.name)
    assert (read.name, read.height, read.width, read.fps) == (path.name, path.height, path.width, path.fps)
    assert torch.equal(read.intrinsics.params, path.intrinsics.params) and not read.intrinsics.is_distorted()
    torch.testing.assert_close(read.c2w, torch.stack([k.c2w for k in keyframes]))


def test_a_camera_path_is_saved_over_its_own_file_only(tmp_path, capsys):
    viewer = SimpleNamespace(state_lock=threading.Lock(), keyframes=[request(0.0), request(2.0)], max_width=25,
                             run_dir=tmp_path, status=SimpleNamespace(content=""))
    path = tmp_path / CAMERA_PATH
    Viewer.save(viewer)
    viewer.keyframes.append(request(1.0))
    Viewer.save(viewer)  # its own file: replaced
    assert len(json.loads(path.read_text())["c2w"]) == 3 and viewer.status.content.startswith("3 cameras saved")
    assert manifest.unproven(tmp_path, [CAMERA_PATH.as_posix()]) == []
    path.write_text("a camera path the user copied here")  # while the viewer runs: kept, the save refused
    Viewer.save(viewer)
    message = (f"{path} is not a file nerfexp-view wrote (it is not in {tmp_path / manifest.MANIFEST}, or changed "
               f"since): move it elsewhere: nerfexp-view saves camera paths to {CAMERA_PATH.as_posix()}")
    assert path.read_text() == "a camera path the user copied here" and viewer.status.content == f"Not saved: {message}"
    assert f"nerfexp-view: camera path not saved: {message}" in capsys.readouterr().out


def test_a_run_holding_a_users_camera_path_is_refused_before_it_is_served(tiny_run, tmp_path, monkeypatch):
    run_dir = shutil.copytree(tiny_run, tmp_path / "run", ignore=shutil.ignore_patterns("view"))
    (run_dir / CAMERA_PATH).parent.mkdir()
    (run_dir / CAMERA_PATH).write_text("mine")
    (run_dir / "view" / "notes.txt").write_text("mine too")  # beside the camera path: no reason to refuse

    def served(*args, **kwargs):
        raise AssertionError("the run was served")

    monkeypatch.setattr(view, "run_scene", served)  # the scene is built after the check, before serving
    with pytest.raises(SystemExit) as exit:
        view.main([str(run_dir), "--port", "0"])
    assert exit.value.code == f"nerfexp-view: error: {run_dir / CAMERA_PATH} is not a file nerfexp-view wrote " + (
        f"(it is not in {run_dir / manifest.MANIFEST}, or changed since): move it elsewhere: nerfexp-view saves "
        f"camera paths to {CAMERA_PATH.as_posix()}")
    (run_dir / CAMERA_PATH).unlink()
    with pytest.raises(AssertionError, match="the run was served"):
        view.main([str(run_dir), "--port", "0"])


@pytest.mark.parametrize("host", ["0.0.0.0", "::", "192.168.1.20", "gpu-box.example.org", "", "127.0.0.1", "::1",
                                  "127.1.2.3", "localhost"])
def test_serving_beyond_loopback_is_warned_of_in_one_line_before_the_run_is_served(tiny_run, monkeypatch, capsys,
                                                                                   host):
    # issue 39 section 6: the viewer has no password; anything but this machine's loopback lets others drive it
    def served(*args, **kwargs):
        raise AssertionError("the run was served")

    monkeypatch.setattr(view, "run_scene", served)  # the scene is built after the warning, before serving
    with pytest.raises(AssertionError, match="the run was served"):
        view.main([str(tiny_run), "--port", "0", "--host", host])
    lines = capsys.readouterr().err.splitlines()
    if host in ("127.0.0.1", "::1", "127.1.2.3", "localhost"):
        assert lines == [] and view.remote_warning(host, tiny_run) is None
    else:
        assert lines == [f"nerfexp-view: warning: serving on {host}, not this machine alone: anyone who can reach it "
                         f"can watch the run, record cameras and write a camera path into {tiny_run / CAMERA_PATH}, "
                         "with no password (from elsewhere, forward the port over SSH instead: docs/viewer.md)"]


FRAME = re.compile(r"frame (\d+) \((\d+) x (\d+), (\w+), camera at \(([^)]*)\) looking along \(([^)]*)\)\) "
                   r"sent to client (\d+)")


def read_lines(stream, lines: queue.Queue) -> None:
    for line in stream:
        lines.put(line.rstrip("\n"))


def wait_for(lines: queue.Queue, seen: list[str], pattern: re.Pattern, timeout: float) -> re.Match | None:
    """The first line (of those seen, then of those to come, within ``timeout`` seconds) matching ``pattern``."""
    deadline = time.monotonic() + timeout
    for line in seen:
        if match := pattern.search(line):
            return match
    while time.monotonic() < deadline:
        try:
            line = lines.get(timeout=max(0.01, deadline - time.monotonic()))
        except queue.Empty:
            return None
        seen.append(line)
        if match := pattern.search(line):
            return match
    return None


@pytest.mark.slow
def test_the_viewer_sends_renders_of_the_first_test_camera_to_a_real_browser(tiny_run, tmp_path):
    argv, env = command("nerfexp-view", str(tiny_run), "--port", "0", "--image", "opacity")
    server = subprocess.Popen(argv, cwd=tmp_path, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                              env=env)
    lines, seen = queue.Queue(), []
    threading.Thread(target=read_lines, args=(server.stdout, lines), daemon=True).start()
    try:
        serving = wait_for(lines, seen, re.compile(r"at (http://127\.0\.0\.1:\d+) \(Ctrl-C to stop\)"), 60)
        assert serving, "\n".join(seen)
        browser = open_page(serving[1], tmp_path / "profile", 1280, 960)
        # the finest render (the test views' 24 pixels wide) of the first test camera reached the browser
        views = instantiate(run_config(tiny_run).data).views("test")
        first = views.c2w[0].double()
        finest = re.compile(FRAME.pattern.replace(r"(\d+) x", f"({views.width}) x"))
        match = None
        while (match := wait_for(lines, seen, finest, 40)) is not None:
            position, direction = (torch.tensor([float(v) for v in match[i].split(", ")]) for i in (5, 6))
            if torch.allclose(position, first[:3, 3].float(), atol=1e-3):
                break
            seen.remove(match.string)  # a frame of the camera before the initial one arrived: look further
        assert match, "\n".join(seen)
        torch.testing.assert_close(direction, -first[:3, 2].float(), atol=1e-3, rtol=0)  # the same rotation
        assert match[4] == "opacity" and match[7] == "0"
        # the page shows that frame: the screenshot, averaged down to the frame's pixels, is the viewer's
        # render of the same camera, apart from where the page's panels lie over it
        width, height = int(match[2]), int(match[3])
        loaded = load_run(tiny_run)
        fy = views.intrinsics.params[0, 1].item()  # the viewer's initial camera: the first test view's
        request = ViewRequest(first, vertical_fov(views.height, fy), height, width, "opacity")
        expected = render_request(loaded.module, instantiate(loaded.cfg.data), threading.Lock(), request, height,
                                  width, lambda: False).astype(int)
        assert np.median(np.abs(255 - expected).max(-1)) > 48  # the frame is far from viser's white page
        # measured: 3/4 of the pixels within 4 levels; the rest under the panels (a notice, the controls). The
        # first screenshot is often 25 to 30 levels lighter all over, frustums included (chromium 156, here and
        # on CI); one half a second later shows the frame: look again until the page shows it
        differences = []
        deadline = time.monotonic() + 15
        while not differences or (differences[-1] >= 10 and time.monotonic() < deadline):
            time.sleep(0.5)
            shot = page_screenshot(tmp_path / "profile")
            shown = np.asarray(Image.fromarray(shot).resize((width, height), Image.Resampling.BOX)).astype(int)
            differences.append(np.percentile(np.abs(shown - expected).max(-1), 75))  # over [H, W]
        close_page(browser)
        assert differences[-1] < 10, differences
        frames = [FRAME.search(line) for line in seen if FRAME.search(line)]
        assert int(frames[0][2]) <= 3  # the first image sent is the coarse one: 24 / 8 pixels wide
    finally:
        server.send_signal(signal.SIGINT)
        try:
            code = server.wait(timeout=30)
        except subprocess.TimeoutExpired:
            server.kill()
            raise
    stopped = wait_for(lines, seen, re.compile(r"nerfexp-view: stopped \(SIGINT\)"), 5)
    assert code == 130 and stopped, "\n".join(seen)  # ended by SIGINT, as shells report it
