"""``nerfexp-render RUN_DIR``: a trained run's views along a camera path, as videos and PNG frames.

Conventions: camera-to-world matrices ``c2w`` [..., 4, 4] in the OpenGL convention of
``nerfexp.cameras`` (x right, y up, looking down -z); a camera path is [F, 4, 4], one camera per
frame. A camera's "up" is its y axis, ``c2w[..., :3, 1]``; its "back" its z axis, ``c2w[..., :3, 2]``.

What a render leaves in ``RUN_DIR/render/`` (the folder is replaced as a whole once every frame is
written, so a reader sees the previous render or the new one, never a part):
``rgb.mp4``, ``depth.mp4``, ``opacity.mp4``; the same frames as 8-bit PNGs ``rgb/0000.png``, ...,
``depth/0000.png``, ..., ``opacity/0000.png``, ...; and ``cameras.json``: the path's name, ``fps``,
``height``, ``width``, ``focal`` (pixels) and ``c2w`` per frame.
"""

import argparse
import contextlib
import json
import math
import os
import shutil
import sys
import tempfile
from collections.abc import Iterator
from pathlib import Path

import imageio.v2 as imageio
import imageio.v3 as iio
import numpy as np
import torch
import torch.nn.functional as F
from hydra.utils import instantiate
from omegaconf import DictConfig
from torch import Tensor
from tqdm import tqdm

from nerfexp.cameras import camera_rays, look_at
from nerfexp.data.datamodule import Scene, model_batch
from nerfexp.errors import NerfexpError
from nerfexp.module import NeRFModule
from nerfexp.outputs import depth_image, find_run, load_module, pixels, run_config

PATHS = ("orbit", "spiral")
KINDS = ("rgb", "depth", "opacity")  # what is rendered of each frame, each a video and a folder of PNGs
RENDER_DIR = "render"


def mean_up(c2w: Tensor) -> Tensor:
    """The cameras' mean up direction [3] (unit): the normalized sum of their y axes (LLFF's convention)."""
    return F.normalize(c2w[:, :3, 1].sum(0), dim=-1)


def orbit_path(c2w: Tensor, n_frames: int) -> Tensor:
    """``n_frames`` cameras evenly spaced on a circle around the origin, each looking at it: [F, 4, 4].

    For 360-degree captures (cameras ``c2w`` [N, 4, 4] around an object at the origin). The circle lies
    at the cameras' mean distance r from the origin and their mean elevation e above the plane through
    the origin perpendicular to their mean up u (``mean_up``); with a unit basis (a, b) of that plane,
    frame k sits at r (cos e (cos phi_k a + sin phi_k b) + sin e u), phi_k = 2 pi k / F.
    ``a`` points to the camera farthest from the up axis, so the first frame is near that training view.

    Example: cameras at distances 3 and 5, elevations 30 and 50 degrees, z up: a circle of radius
    4 cos 40deg at height 4 sin 40deg.
    """
    up = mean_up(c2w)
    centres = c2w[:, :3, 3]  # [N, 3]
    distances = torch.linalg.vector_norm(centres, dim=-1)  # [N]
    heights = centres @ up  # [N]
    elevation = torch.asin((heights / distances).clamp(-1, 1)).mean()
    across = centres - heights[:, None] * up  # [N, 3]: the centres projected onto the plane
    a = F.normalize(across[torch.linalg.vector_norm(across, dim=-1).argmax()], dim=-1)
    b = torch.linalg.cross(up, a, dim=-1)
    phi = 2 * math.pi * torch.arange(n_frames, dtype=c2w.dtype) / n_frames  # [F]
    ring = torch.cos(phi)[:, None] * a + torch.sin(phi)[:, None] * b  # [F, 3]
    eyes = distances.mean() * (torch.cos(elevation) * ring + torch.sin(elevation) * up)
    return look_at(eyes, torch.zeros(3, dtype=c2w.dtype), up)


def llff_focus_depth(near: float, far: float) -> float:
    """The depth a forward-facing spiral looks at (LLFF's ``render_path_spiral``): the weighted harmonic
    mean 1 / (0.25 / (0.9 near) + 0.75 / (5 far)) of a depth just before the nearest content and one
    well beyond the farthest. Example: near 2, far 6 gives 1 / (0.25 / 1.8 + 0.75 / 30) = 6.08."""
    if not 0 < near < far:
        raise NerfexpError(f"a spiral's focus depth needs depth bounds 0 < near < far, got near={near}, far={far}; "
                           "give it with --focus DEPTH")
    return 1 / (0.25 / (0.9 * near) + 0.75 / (5 * far))


def spiral_path(c2w: Tensor, n_frames: int, focus_depth: float, rotations: float = 2,
                z_rate: float = 0.5) -> Tensor:
    """``n_frames`` cameras on a spiral around the mean camera, all looking at one point: [F, 4, 4].

    For forward-facing captures (LLFF's ``render_path_spiral``). The mean camera sits at the mean centre
    c of ``c2w`` [N, 4, 4], with the mean back axis z and the mean up u made orthonormal (x = u cross z,
    y = z cross x). Radii (r_x, r_y, r_z) are the 90th percentiles of the cameras' |offsets| from c
    along x, y, z. Frame k, at angle theta_k = 2 pi rotations k / F, sits at
    c + r_x cos(theta) x - r_y sin(theta) y - r_z sin(z_rate theta) z and looks at the focus point
    c - focus_depth z (in front of the mean camera), with up u.
    """
    centre = c2w[:, :3, 3].mean(0)
    up = mean_up(c2w)
    back = F.normalize(c2w[:, :3, 2].sum(0), dim=-1)
    right = F.normalize(torch.linalg.cross(up, back, dim=-1), dim=-1)
    basis = torch.stack([right, torch.linalg.cross(back, right, dim=-1), back])  # [3, 3]: rows x, y, z
    radii = torch.quantile((c2w[:, :3, 3] - centre).abs() @ basis.T, 0.9, dim=0)  # [3]
    theta = 2 * math.pi * rotations * torch.arange(n_frames, dtype=c2w.dtype) / n_frames  # [F]
    local = torch.stack([torch.cos(theta), -torch.sin(theta), -torch.sin(z_rate * theta)], -1) * radii  # [F, 3]
    return look_at(centre + local @ basis, centre - focus_depth * back, up)


def default_path(data: DictConfig) -> str:
    """``spiral`` for forward-facing scenes (the data config has ``ndc: true``, or builds an LLFF scene),
    else ``orbit``. Reads the keys defensively: a data config may have neither."""
    forward_facing = bool(data.get("ndc", False)) or "llff" in str(data.get("_target_", "")).lower()
    return "spiral" if forward_facing else "orbit"


def scene_focus_depth(scene: Scene, data: DictConfig) -> float:
    """The spiral's focus depth from the scene's depth bounds: its ``bounds`` (per-view near and far,
    as LLFF stores them; ``bounds()``, a method, for COLMAP scenes) where it has them, else the data
    config's ``near`` and ``far``."""
    bounds = getattr(scene, "bounds", None)
    if callable(bounds):
        bounds = bounds()
    if bounds is not None:
        bounds = torch.as_tensor(bounds, dtype=torch.float64)
        return llff_focus_depth(bounds.min().item(), bounds.max().item())
    return llff_focus_depth(float(data.get("near", 0)), float(data.get("far", 0)))


def frame_size(height: int, width: int, focal: float, size: int | None) -> tuple[int, int, float]:
    """``(height, width, focal)`` of frames ``size`` pixels wide (None: the views' own width, made even),
    the height scaled by the same factor and rounded to an even number (video encoders need even sizes),
    the focal length (pixels) scaled with the width so the field of view stays the same."""
    size = size or max(2, width - width % 2)
    scaled_height = max(2, 2 * round(height * size / width / 2))
    return scaled_height, size, focal * size / width


def render_frame(module: NeRFModule, scene: Scene, c2w: Tensor, height: int, width: int,
                 focal: float) -> dict[str, Tensor]:
    """The module's render of camera ``c2w`` [4, 4]: ``rgb`` [H, W, 3], ``depth``, ``opacity`` [H, W].

    The camera's world rays become the model's rays as in training (``model_batch``); the module renders
    them ``module.chunk`` rays at a time, so memory is bounded at any resolution."""
    origins, directions = camera_rays(c2w.to(module.device, torch.float32), height, width, focal)
    batch = model_batch(scene, {"origins": origins, "directions": directions})
    return module.render_image(batch["origins"], batch["directions"], batch.get("viewdirs"))


def frame_images(frame: dict[str, Tensor], near: float, far: float) -> dict[str, Tensor]:
    """The images of a rendered frame, values in [0, 1]: ``rgb`` [H, W, 3]; ``depth`` (near white,
    far black, faded by opacity: ``outputs.depth_image``) and ``opacity`` [H, W]."""
    return {"rgb": frame["rgb"], "depth": depth_image(frame["depth"], frame["opacity"], near, far),
            "opacity": frame["opacity"]}


@contextlib.contextmanager
def replaced_directory(path: Path) -> Iterator[Path]:
    """A new, empty directory to fill; once the block succeeds it takes the place of ``path`` (a previous
    ``path`` is removed), and if the block fails it is removed instead. Readers see the old directory
    or the new one, never a part of one (and for an instant between two renames, none)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    new = Path(tempfile.mkdtemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp"))
    try:
        os.chmod(new, 0o755)  # mkdtemp's is 0o700
        yield new
    except BaseException:
        shutil.rmtree(new, ignore_errors=True)
        raise
    trash = Path(tempfile.mkdtemp(dir=path.parent, prefix=f".{path.name}.", suffix=".old"))
    if path.exists():
        os.replace(path, trash / path.name)
    os.replace(new, path)
    shutil.rmtree(trash)


def render_path(module: NeRFModule, scene: Scene, cameras: Tensor, height: int, width: int, focal: float,
                out_dir: Path, fps: float) -> None:
    """Render ``cameras`` [F, 4, 4] frame by frame into ``out_dir``: a video per kind (``KINDS``) and
    the PNG frames, streamed to disk as they are rendered; with a progress bar."""
    near, far = module.renderer.near, module.renderer.far
    with contextlib.ExitStack() as videos:
        writers = {kind: videos.enter_context(
            imageio.get_writer(out_dir / f"{kind}.mp4", format="FFMPEG", fps=fps, codec="libx264", quality=8,
                               macro_block_size=2)) for kind in KINDS}
        for index, c2w in enumerate(tqdm(cameras, desc="rendering", unit="frame")):
            images = frame_images(render_frame(module, scene, c2w, height, width, focal), near, far)
            for kind, image in images.items():
                frame = pixels(image)  # [H, W, 3] or [H, W] uint8
                (out_dir / kind).mkdir(exist_ok=True)
                iio.imwrite(out_dir / kind / f"{index:04d}.png", frame)
                writers[kind].append_data(frame if frame.ndim == 3 else np.repeat(frame[..., None], 3, -1))


def render_run(run: Path, overrides: list[str], n_frames: int, fps: float, size: int | None, chunk: int | None,
               path: str | None, focus: float | None) -> Path:
    """Render the run at ``run`` (a run directory, or a checkpoint file in one) along a camera path made
    from its training cameras: ``path`` (None: ``default_path``), into ``RUN_DIR/render``; returns it."""
    run_dir, checkpoint = find_run(run)
    cfg = run_config(run_dir, overrides)
    module, _ = load_module(cfg, checkpoint)
    if chunk is not None:
        module.chunk = chunk
    module.to("cuda" if torch.cuda.is_available() else "cpu").eval()
    scene = instantiate(cfg.data)
    views = scene.views("train")
    path = path or default_path(cfg.data)
    c2w = views.c2w.double()
    if path == "orbit":
        cameras = orbit_path(c2w, n_frames)
    else:
        cameras = spiral_path(c2w, n_frames, focus if focus is not None else scene_focus_depth(scene, cfg.data))
    height, width, focal = frame_size(views.height, views.width, views.focal, size)
    out_dir = run_dir / RENDER_DIR
    with replaced_directory(out_dir) as new:
        render_path(module, scene, cameras, height, width, focal, new, fps)
        record = {"path": path, "fps": fps, "height": height, "width": width, "focal": focal,
                  "c2w": cameras.tolist()}
        (new / "cameras.json").write_text(json.dumps(record, indent=2))
    return out_dir


def _positive(kind: type):
    def parse(text: str):
        value = kind(text)
        if value <= 0:
            raise argparse.ArgumentTypeError(f"expected a positive number, got {text}")
        return value
    return parse


def _even(text: str) -> int:
    value = _positive(int)(text)
    if value % 2:
        raise argparse.ArgumentTypeError(f"expected an even width (video encoders need one), got {text}")
    return value


def main(argv: list[str] | None = None) -> None:
    """``nerfexp-render RUN_DIR`` (or a checkpoint file in it): render the trained model along a camera
    path (an orbit around 360-degree scenes, a spiral for forward-facing ones) into RUN_DIR/render:
    rgb.mp4, depth.mp4, opacity.mp4 and their PNG frames."""
    parser = argparse.ArgumentParser(prog="nerfexp-render", description=main.__doc__)
    parser.add_argument("run", type=Path, help="a run directory (its checkpoints/last.ckpt), or a checkpoint file")
    parser.add_argument("overrides", nargs="*", metavar="KEY=VALUE",
                        help="changes to the run's config, e.g. data.root=/new/place/of/the/scene")
    parser.add_argument("--path", choices=PATHS, help="camera path (default: spiral for forward-facing "
                        "scenes, i.e. data.ndc or an LLFF scene; else orbit)")
    parser.add_argument("--frames", type=_positive(int), default=120, help="number of frames (default 120)")
    parser.add_argument("--fps", type=_positive(float), default=30, help="frames per second of the videos")
    parser.add_argument("--size", type=_even, help="frame width in pixels, even; the height keeps the "
                        "training views' aspect ratio (default: the training views' width)")
    parser.add_argument("--chunk", type=_positive(int), help="rays rendered at once (default: the run's model.chunk)")
    parser.add_argument("--focus", type=_positive(float), help="spiral only: the depth its cameras look at "
                        "(default: from the scene's depth bounds)")
    args = parser.parse_args(argv)
    try:
        out_dir = render_run(args.run, args.overrides, args.frames, args.fps, args.size, args.chunk, args.path,
                             args.focus)
    except NerfexpError as error:
        sys.exit(f"nerfexp-render: error: {error}")
    print(f"{args.frames} frames written to {out_dir}")


if __name__ == "__main__":
    main()
