"""The viewer: a trained run in the browser, live: move the camera and the field is rendered
from there (viser serves the page on localhost; ``docs/viewer.md``).

Progressive rendering: when a client's camera moves, its worker thread renders a coarse image at once
(1/8 of the target width), then, while the camera rests, 1/4, 1/2 and the full target width
(``refinement_sizes``); a refinement is abandoned between bands of rays (``frame_bands``) as soon as the
camera moves again, so the newest camera is always the one being rendered. The target width is the
browser's canvas width, at most ``--max-width`` (default: the test views' width); the height follows the
canvas's aspect ratio. One worker thread per client, the model used by one band at a time.

Each image sent is announced on standard output: ``frame N (W x H, KIND, camera at (x, y, z) looking along
(dx, dy, dz)) sent to client C``. The run's
training and test cameras are drawn as frustums; "record camera" keeps the current camera as a keyframe
and "save camera path" writes the keyframes to ``RUN_DIR/view/camera_path.json`` in the format of
``nerfexp-render``'s ``cameras.json`` (``nerfexp.products.camera_files.CameraPath``), which ``nerfexp-render --cameras``
renders, and records it in the run directory's manifest; a ``camera_path.json`` there that the manifest does
not show to be nerfexp-view's (``nerfexp.manifest``) is kept and the save refused, saying so. Cameras:
``nerfexp.geometry.viewer_cameras``.
"""

from __future__ import annotations

import functools
import json
import threading
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import torch
from torch import Tensor

from nerfexp import manifest
from nerfexp.data.base import Scene
from nerfexp.errors import NerfexpError
from nerfexp.extras import require
from nerfexp.geometry.camera_paths import mean_up
from nerfexp.geometry.cameras import focal_from_fov
from nerfexp.geometry.lenses import Intrinsics
from nerfexp.geometry.viewer_cameras import flip_camera_axes, vertical_fov
from nerfexp.products.camera_files import CameraPath
from nerfexp.products.frames import KINDS, frame_bands, frame_images, rgb_pixels, scene_depth_range
from nerfexp.rundir.layout import CAMERA_PATH

if TYPE_CHECKING:  # annotations only: it imports Lightning, which a command stopping at bad input need not wait for
    from nerfexp.training.module import NeRFModule

DIVISORS = (8, 4, 2, 1)  # the progressive schedule: the target width divided by each, in turn
FPS = 30.0  # of a saved camera path
TRAIN_COLOUR = (40, 110, 240)  # the training cameras' frustums
TEST_COLOUR = (240, 120, 20)  # the test cameras'
SAVE_ADVICE = f"move {{it}} elsewhere: nerfexp-view saves camera paths to {CAMERA_PATH.as_posix()}"


def refinement_sizes(height: int, width: int, divisors: tuple[int, ...] = DIVISORS) -> list[tuple[int, int]]:
    """The ``(height, width)`` of the successive renders of a ``height`` x ``width`` target: the target
    divided by each of ``divisors`` (rounded, at least 1 pixel), sizes already in the list left out.

    Example: 48 x 64 gives [(6, 8), (12, 16), (24, 32), (48, 64)]; 6 x 8 gives [(1, 1), (2, 2), (3, 4), (6, 8)].
    """
    sizes = []
    for divisor in divisors:
        size = (max(1, round(height / divisor)), max(1, round(width / divisor)))
        if size not in sizes:
            sizes.append(size)
    return sizes


def viewer_c2w(wxyz: Tensor, position: Tensor) -> Tensor:
    """nerfexp's camera-to-world matrix [..., 4, 4] (OpenGL, float64) of a viewer's camera (OpenCV): its
    orientation ``wxyz`` [..., 4] (a unit quaternion w + xi + yj + zk, the rotation R in p_world = R p_camera +
    t, as viser's ``SO3`` reads it) and ``position`` t [..., 3]."""
    so3 = require("viser", "nerfexp-view").transforms.SO3
    opencv = torch.zeros(*position.shape[:-1], 4, 4, dtype=torch.float64)
    opencv[..., :3, :3] = torch.from_numpy(so3(wxyz.double().numpy()).as_matrix())
    opencv[..., :3, 3] = position.double()
    opencv[..., 3, 3] = 1
    return flip_camera_axes(opencv)


def viewer_pose(c2w: Tensor) -> tuple[Tensor, Tensor]:
    """A viewer's ``(wxyz [..., 4], position [..., 3])`` (OpenCV, float64) of nerfexp's cameras ``c2w``
    [..., 4, 4] (OpenGL): the inverse of ``viewer_c2w``, the quaternion by viser's ``SO3.from_matrix``."""
    so3 = require("viser", "nerfexp-view").transforms.SO3
    opencv = flip_camera_axes(c2w)
    return torch.from_numpy(so3.from_matrix(opencv[..., :3, :3].numpy()).wxyz), opencv[..., :3, 3]


def target_size(aspect: float, canvas_width: int, max_width: int) -> tuple[int, int]:
    """``(height, width)`` of the finest render for a canvas ``canvas_width`` pixels wide whose width is
    ``aspect`` times its height: the canvas's width, at most ``max_width``, and the height that keeps the aspect."""
    width = max(1, min(canvas_width, max_width))
    return max(1, round(width / aspect)), width


def even(value: float) -> int:
    """``value`` rounded to an even number, at least 2 (video encoders need even sizes)."""
    return max(2, 2 * round(value / 2))


def frustum_scale(c2w: Tensor) -> float:
    """The size of the cameras' frustums in the scene: a tenth of the cameras' mean distance from their
    centroid (``c2w`` [N, 4, 4]), or 0.1 where they all stand at one place."""
    centres = c2w[:, :3, 3].double()
    spread = torch.linalg.vector_norm(centres - centres.mean(0), dim=-1).mean().item()
    return 0.1 * spread if spread > 0 else 0.1


@dataclass(frozen=True)
class ViewRequest:
    """What a client asks to see: camera ``c2w`` [4, 4] (float64, OpenGL), its vertical field of view
    ``fov`` (radians), the finest render's ``height`` x ``width`` and which image (``KINDS``)."""

    c2w: Tensor
    fov: float
    height: int
    width: int
    kind: str


# (request, height, width, stale) -> 8-bit pixels [height, width, 3], or None where stale() turned true
RenderFn = Callable[[ViewRequest, int, int, Callable[[], bool]], np.ndarray | None]


class ProgressiveRenderer:
    """Renders a client's latest request on a thread of its own, ever finer (``refinement_sizes``), passing
    each image to ``show(request, pixels)``. A new request abandons the render under way: ``render`` is
    given ``stale()``, true once a newer request came (or ``close``), and returns None when it sees it."""

    def __init__(self, render: RenderFn, show: Callable[[ViewRequest, np.ndarray], None],
                 report: Callable[[str], None], divisors: tuple[int, ...] = DIVISORS):
        self._render = render
        self._show = show
        self._report = report
        self._divisors = divisors
        self._changed = threading.Condition()
        self._request: ViewRequest | None = None
        self._version = 0  # counts the requests
        self._closed = False
        self._thread = threading.Thread(target=self._work, name="nerfexp-view-render", daemon=True)
        self._thread.start()

    @property
    def latest(self) -> ViewRequest | None:
        """The newest request, or None before the first."""
        return self._request

    def request(self, request: ViewRequest) -> None:
        """Render ``request`` from coarse to fine, abandoning what was being rendered."""
        with self._changed:
            self._request = request
            self._version += 1
            self._changed.notify()

    def close(self, timeout: float = 10) -> None:
        """Abandon the render under way and end the thread (waiting up to ``timeout`` seconds)."""
        with self._changed:
            self._closed = True
            self._changed.notify()
        self._thread.join(timeout)

    def _stale(self, version: int) -> bool:
        return self._closed or self._version != version

    def _next(self, done: int) -> tuple[int, ViewRequest] | None:
        """Wait for a request newer than version ``done``: ``(its version, it)``, or None once closed."""
        with self._changed:
            self._changed.wait_for(lambda: self._closed or self._version != done)
            return None if self._closed else (self._version, self._request)

    def _refine(self, version: int, request: ViewRequest) -> None:
        """Render and show ``request`` (version ``version``) ever finer until done or stale."""
        stale = functools.partial(self._stale, version)
        try:
            for height, width in refinement_sizes(request.height, request.width, self._divisors):
                pixels = self._render(request, height, width, stale)
                if pixels is None or stale():
                    return
                self._show(request, pixels)
        except Exception as error:  # the viewer goes on with the next camera; the user sees why
            self._report(f"rendering failed: {type(error).__name__}: {error}")

    def _work(self) -> None:
        done = 0  # the version last rendered or abandoned
        while (latest := self._next(done)) is not None:
            done, request = latest
            self._refine(done, request)


def render_request(module: NeRFModule, scene: Scene, lock: threading.Lock, request: ViewRequest, height: int,
                   width: int, stale: Callable[[], bool]) -> np.ndarray | None:
    """8-bit pixels [height, width, 3] of the image ``request.kind`` of camera ``request.c2w`` seen with
    its vertical field of view at ``height`` x ``width`` (``frame_bands``, one band at a time under
    ``lock``), or None as soon as ``stale()`` is true between two bands."""
    lens = Intrinsics.pinhole(focal_from_fov(height, request.fov), height, width)  # the browser's camera: a pinhole
    bands, parts = frame_bands(module, scene, request.c2w, height, width, lens), []
    while not stale():
        with lock:
            band = next(bands, None)
        if band is None:
            frame = {key: torch.cat([part[key] for part in parts]) for key in parts[0]}
            images = frame_images(frame, module.renderer.near, module.renderer.ray_far)
            return rgb_pixels(images[request.kind])
        parts.append(band)
    return None


def saved_camera_path(keyframes: list[ViewRequest], max_width: int) -> CameraPath:
    """The keyframes as a camera path: their cameras, seen by frames ``max_width`` pixels wide (even)
    with the first keyframe's aspect ratio and vertical field of view."""
    first = keyframes[0]
    width = even(max_width)
    height = even(width * first.height / first.width)
    c2w = torch.stack([keyframe.c2w for keyframe in keyframes])
    lens = Intrinsics.pinhole(focal_from_fov(height, first.fov), height, width)
    return CameraPath("viewer", c2w, height, width, lens, FPS)


class Viewer:
    """The viewer of one run on a viser server: the GUI, the cameras' frustums, one
    ``ProgressiveRenderer`` per client and the recorded keyframes."""

    def __init__(self, server, module: NeRFModule, scene: Scene, run_dir: Path, max_width: int,
                 image: str = KINDS[0]):
        self.server = server
        self.module = module
        self.scene = scene
        self.run_dir = run_dir
        self.max_width = max_width
        self.image = image
        self.keyframes: list[ViewRequest] = []
        self.renderers: dict[int, ProgressiveRenderer] = {}
        self.frames: dict[int, int] = {}  # images sent, per client
        self.model_lock = threading.Lock()
        self.state_lock = threading.Lock()
        self.add_cameras()
        self.add_gui()
        server.on_client_connect(self.connect)
        server.on_client_disconnect(self.disconnect)

    def add_cameras(self) -> None:
        """The training and test cameras as frustums (``TRAIN_COLOUR``, ``TEST_COLOUR``), the scene's up
        direction their mean up (``mean_up``), and every client's first camera the first test camera."""
        train, test = self.scene.views("train"), self.scene.views("test")
        scale = frustum_scale(train.c2w)
        for split, views, colour in (("train", train, TRAIN_COLOUR), ("test", test, TEST_COLOUR)):
            wxyz, position = viewer_pose(views.c2w)
            for index in range(len(views)):
                fov = vertical_fov(views.height, views.intrinsics.params[index, 1].item())  # fy
                self.server.scene.add_camera_frustum(
                    f"/cameras/{split}/{index}", fov=fov, aspect=views.width / views.height, scale=scale,
                    color=colour, thickness=1.5, thickness_units="screen", wxyz=wxyz[index].numpy(),
                    position=position[index].numpy())
        self.server.scene.set_up_direction(mean_up(train.c2w.double()).numpy())
        first = test.c2w[0].double()
        near, far = scene_depth_range(self.scene)
        camera = self.server.initial_camera
        camera.fov = vertical_fov(test.height, test.intrinsics.params[0, 1].item())  # fy
        camera.position = first[:3, 3].numpy()
        camera.look_at = (first[:3, 3] - 0.5 * (near + far) * first[:3, 2]).numpy()  # down -z, mid-depth
        camera.up = first[:3, 1].numpy()

    def add_gui(self) -> None:
        gui = self.server.gui
        self.kind = gui.add_dropdown("image", KINDS, initial_value=self.image)
        self.kind.on_update(lambda _: self.rerender())
        record, save, clear = (gui.add_button(label) for label in
                               ("record camera", "save camera path", "clear keyframes"))
        self.status = gui.add_markdown("No keyframes recorded.")
        gui.add_markdown(f"Frustums: training cameras in blue, test cameras in orange. Saved paths go to "
                         f"`{self.run_dir / CAMERA_PATH}`.")
        record.on_click(lambda event: self.record(event.client))
        save.on_click(lambda _: self.save())
        clear.on_click(lambda _: self.clear())

    def request_of(self, camera) -> ViewRequest:
        """What a client's viser camera asks to see (``viewer_c2w``, ``target_size``)."""
        c2w = viewer_c2w(torch.from_numpy(np.asarray(camera.wxyz)), torch.from_numpy(np.asarray(camera.position)))
        height, width = target_size(camera.aspect, camera.image_width, self.max_width)
        return ViewRequest(c2w, float(camera.fov), height, width, self.kind.value)

    def connect(self, client) -> None:
        def show(request: ViewRequest, pixels: np.ndarray) -> None:
            client.scene.set_background_image(pixels, format="jpeg", jpeg_quality=90)
            client.flush()
            with self.state_lock:
                self.frames[client.client_id] += 1
                number = self.frames[client.client_id]
            height, width, _ = pixels.shape
            say(f"frame {number} ({width} x {height}, {request.kind}, {camera_text(request.c2w)}) "
                f"sent to client {client.client_id}")

        renderer = ProgressiveRenderer(
            lambda request, height, width, stale: render_request(self.module, self.scene, self.model_lock,
                                                                 request, height, width, stale),
            show, lambda message: say(f"client {client.client_id}: {message}"))
        with self.state_lock:
            self.renderers[client.client_id] = renderer
            self.frames[client.client_id] = 0
        say(f"client {client.client_id} connected")
        client.camera.on_update(lambda camera: renderer.request(self.request_of(camera)))
        renderer.request(self.request_of(client.camera))

    def disconnect(self, client) -> None:
        with self.state_lock:
            renderer = self.renderers.pop(client.client_id, None)
        if renderer is not None:
            renderer.close()
            say(f"client {client.client_id} disconnected")

    def rerender(self) -> None:
        """Every client's latest camera again, with the image now chosen."""
        with self.state_lock:
            renderers = list(self.renderers.values())
        for renderer in renderers:
            if (latest := renderer.latest) is not None:
                renderer.request(ViewRequest(latest.c2w, latest.fov, latest.height, latest.width, self.kind.value))

    def record(self, client) -> None:
        with self.state_lock:
            self.keyframes.append(self.request_of(client.camera))
            count = len(self.keyframes)
        self.status.content = f"{count} keyframe{'s' * (count != 1)} recorded."

    def clear(self) -> None:
        with self.state_lock:
            self.keyframes.clear()
        self.status.content = "No keyframes recorded."

    def save(self) -> None:
        """The keyframes written to ``RUN_DIR/view/camera_path.json`` (``saved_camera_path``), atomically, and
        recorded in the run directory's manifest; refused, saying so, where the file there is not one
        nerfexp-view wrote (``nerfexp.manifest.check_ours``)."""
        with self.state_lock:
            keyframes = list(self.keyframes)
        if not keyframes:
            self.status.content = "No keyframes to save: record a camera first."
            return
        path = self.run_dir / CAMERA_PATH
        try:
            manifest.check_ours(self.run_dir, [CAMERA_PATH.as_posix()], "nerfexp-view", SAVE_ADVICE)
        except NerfexpError as error:
            self.status.content = f"Not saved: {error}"
            say(f"nerfexp-view: camera path not saved: {error}")
            return
        cameras = saved_camera_path(keyframes, self.max_width).record()
        manifest.write(self.run_dir, CAMERA_PATH.as_posix(), json.dumps(cameras, indent=2).encode())
        self.status.content = f"{len(keyframes)} cameras saved to `{path}`."
        say(f"camera path of {len(keyframes)} cameras saved to {path}")

    def close(self) -> None:
        with self.state_lock:
            renderers = list(self.renderers.values())
            self.renderers.clear()
        for renderer in renderers:
            renderer.close()


def camera_text(c2w: Tensor) -> str:
    """``camera at (x, y, z) looking along (dx, dy, dz)`` of a camera ``c2w`` [4, 4] (OpenGL: along -z), to 4 digits."""
    def vector(v: Tensor) -> str:
        return f"({', '.join(f'{float(x):.4g}' for x in v)})"
    return f"camera at {vector(c2w[:3, 3])} looking along {vector(-c2w[:3, 2])}"


def say(line: str) -> None:
    """A line on standard output, flushed at once (a test or a log reads them as they come)."""
    print(line, flush=True)
