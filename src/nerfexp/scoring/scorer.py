"""How a test image is scored (``TestScorer``, which ``NeRFModule.test_step`` makes): under both test protocols
of per-image appearance (``nerfexp.nerf.appearance.PROTOCOLS``: the whole image, or NeRF-W's right half with the
image's code fitted on its left half), from its camera as given or refined with the networks frozen first
(``test_cameras=refined``, ``nerfexp.nerf.poses.PoseFit``)."""

import contextlib
import logging
import math
import sys
from collections.abc import Callable, Iterator
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import Tensor, nn
from tqdm import tqdm

from nerfexp.data.views import SPLIT_NAMES, Views
from nerfexp.errors import DatasetError
from nerfexp.nerf.appearance import FULL_IMAGE, NERFW_RIGHT_HALF, CodeFit, left_columns
from nerfexp.nerf.poses import PoseFit, camera_corrected_rays
from nerfexp.nerf.volume_renderer import final_output
from nerfexp.scoring.metrics import psnr, ssim, unscorable

log = logging.getLogger(__name__)


@contextlib.contextmanager
def fit_progress_bar(description: str, steps: int, shown: bool) -> Iterator[Callable[[int], None] | None]:
    """A test-time fit's bar of ``steps`` steps (``description``: what is fitted, for which view), drawn under
    Lightning's test bar on standard output where ``shown`` (the trainer draws bars: ``StepProgressBar``, on a
    terminal) and gone when the fit ends. Yields the callback a fit calls with the steps done
    (``nerfexp.nerf.frozen_fit.fit_frozen``'s ``progress``), or None where not ``shown``: nothing to draw."""
    if not shown:
        yield None
        return
    with tqdm(total=steps, desc=description, unit="step", position=1, leave=False, file=sys.stdout,
              dynamic_ncols=True, disable=None) as bar:
        yield lambda done: bar.update(done - bar.n)


@dataclass(frozen=True)
class TestScorer:
    """What scoring a test image takes, each named: the ``renderer`` (its fields and its appearance codes,
    ``renderer.appearance``, or None), the headline ``protocol`` (``test_protocol``), NeRF-W's fit of a test image's
    code ``appearance_fit`` and the test cameras' fit ``camera_fit`` (None: not fitted), ``render_image`` (rays
    [H, W, 3], viewdirs [H, W, 3] or None, code [D] -> "rgb" [H, W, 3], ...: a whole image rendered in chunks),
    ``lpips`` (image, target [H, W, 3] -> the LPIPS scores by name), whether the test's trainer ``draws_bars``
    (``fit_progress_bar``), and the ``device`` a camera's correction is fitted on."""

    __test__ = False  # a class pytest should not collect

    renderer: nn.Module
    protocol: str
    appearance_fit: CodeFit | None
    camera_fit: PoseFit | None
    render_image: Callable[..., dict[str, Tensor]]
    lpips: Callable[[Tensor, Tensor], dict[str, float]]
    draws_bars: bool
    device: torch.device

    def protocol_scores(self, scored: dict, batch: dict) -> dict:
        """A test image's scores under both protocols (``nerfexp.nerf.appearance.PROTOCOLS``), added to
        ``scored`` (``NeRFModule._evaluate``'s: the whole image, with the test code where there are codes):
        "psnr_full_image", "ssim_full_image" (those of ``scored``) and "psnr_right_half", "ssim_right_half" (the
        right half, ``left_columns``, rendered with the code fitted on the left half, ``fitted_code``; without
        codes, the right half of the same render). Under ``protocol`` nerfw_right_half, "psnr", "ssim",
        "lpips" and "lpips_custom" are the right half's; the render kept ("rgb") is the whole image's either way."""
        H, W, _ = batch["rgb"].shape  # rows, columns, channels
        right = slice(left_columns(W), None)
        mask = batch.get("mask")
        kept = None if mask is None else mask[:, right]  # [H, W - W // 2]
        target = batch["rgb"][:, right]
        if self.renderer.appearance is None:
            rendered = scored["rgb"][:, right]
        else:
            viewdirs = None if batch.get("viewdirs") is None else batch["viewdirs"][:, right]
            rendered = self.render_image(batch["origins"][:, right], batch["directions"][:, right], viewdirs,
                                         self.fitted_code(batch))["rgb"]
        protocols = {"psnr_full_image": scored["psnr"], "ssim_full_image": scored["ssim"],
                     "psnr_right_half": psnr(rendered, target, kept), "ssim_right_half": ssim(rendered, target, kept)}
        if self.protocol == FULL_IMAGE:
            return {**scored, **protocols}
        shown = rendered if kept is None else torch.where(kept[..., None], rendered, target)
        return {**scored, **protocols, "psnr": protocols["psnr_right_half"], "ssim": protocols["ssim_right_half"],
                **self.lpips(shown, target)}

    def fitted_code(self, batch: dict) -> Tensor:
        """NeRF-W's protocol: the test image's code [D] fitted on its left half (the pixels its mask keeps there)
        from the renderer's test code, the networks frozen (``appearance_fit``: only the code is differentiated
        and stepped), each step's pixels drawn with the image's "index" as seed. Gradients are enabled for it
        alone, inside Lightning's inference mode."""
        start = self.renderer.appearance.test_code()
        with torch.inference_mode(False), torch.enable_grad():
            rays = fitting_rays(batch, left_half=True)
            if self.appearance_fit is None or not len(rays["rgb"]):
                return start

            def loss(pixels: Tensor, code: Tensor) -> Tensor:
                return fitting_loss(self.renderer, rays, pixels, code)
            with self.fit_progress("its appearance code", self.appearance_fit, batch) as progress:
                return self.appearance_fit(loss, start.clone(), len(rays["rgb"]), seed=int(batch["index"]),
                                           progress=progress)

    def fit_progress(self, what: str, fit: CodeFit | PoseFit, batch: dict
                     ) -> contextlib.AbstractContextManager[Callable[[int], None] | None]:
        """A test-time ``fit`` of ``what`` for the test view ``batch``, said as it starts: a line in the log with
        its steps and rays (what a long fit takes its time over) and a bar of its steps where the trainer draws
        bars (``fit_progress_bar``). Yields the fit's ``progress`` callback (None: no bar)."""
        index = int(batch["index"])
        log.info("test view %d: fitting %s (%d Adam steps of %d rays)", index, what, fit.steps, fit.rays)
        return fit_progress_bar(f"test view {index}: {what}", fit.steps, self.draws_bars)

    def refined_camera(self, batch: dict) -> tuple[dict, dict[str, float]]:
        """A test image's ``batch`` with its rays ("origins", "directions", "viewdirs" [H, W, 3]) those of its camera
        refined by ``camera_fit`` (a correction (w, t), ``nerfexp.nerf.poses``), the networks frozen, on the
        pixels the headline protocol does not score apart: the left half under NeRF-W's protocol (where the
        appearance code is fitted afterwards, through the refined camera), else the whole image (BARF's); the
        image seen with the renderer's test code. The correction's size: "camera_fit_deg" (the turn, degrees) and
        "camera_fit_shift" (the move, scene units). Unchanged, with no sizes, where cameras are given."""
        if self.camera_fit is None:
            return batch, {}
        appearance = self.renderer.appearance
        code = None if appearance is None else appearance.test_code()
        with torch.inference_mode(False), torch.enable_grad():
            rays = fitting_rays(batch, left_half=self.protocol == NERFW_RIGHT_HALF)
            if not len(rays["rgb"]):
                return batch, {}

            def loss(pixels: Tensor, delta: Tensor) -> Tensor:
                return fitting_loss(self.renderer, rays, pixels, code, delta)
            with self.fit_progress("its camera", self.camera_fit, batch) as progress:
                delta = self.camera_fit(loss, len(rays["rgb"]), seed=int(batch["index"]), device=self.device,
                                        progress=progress)
        origins, directions, viewdirs = camera_corrected_rays(delta, batch["origins"], batch["directions"],
                                                              batch.get("viewdirs"))
        refined = {**batch, "origins": origins.to(batch["origins"].dtype),
                   "directions": directions.to(batch["directions"].dtype)}
        if viewdirs is not None:
            refined["viewdirs"] = viewdirs.to(batch["viewdirs"].dtype)
        return refined, {"camera_fit_deg": math.degrees(float(torch.linalg.vector_norm(delta[:3]))),
                         "camera_fit_shift": float(torch.linalg.vector_norm(delta[3:]))}


def fitting_loss(renderer: nn.Module, rays: dict[str, Tensor], pixels: Tensor, code: Tensor | None,
                 delta: Tensor | None = None) -> Tensor:
    """The MSE of the fitting pixels ``pixels`` [R] of ``rays`` (``fitting_rays``) rendered by ``renderer`` with
    appearance ``code`` [D] (None: no codes), through their camera corrected by ``delta`` [6] where given: the loss
    both test-time fits minimize, the networks frozen."""
    pixels = pixels.to(rays["rgb"].device)
    origins, directions = rays["origins"][pixels], rays["directions"][pixels]
    viewdirs = rays["viewdirs"][pixels] if "viewdirs" in rays else None
    if delta is not None:
        origins, directions, viewdirs = camera_corrected_rays(delta, origins, directions, viewdirs)
    outputs = renderer(origins, directions, deterministic=True, viewdirs=viewdirs,
                       codes=None if code is None else code.expand(len(pixels), -1))
    return F.mse_loss(final_output(outputs)["rgb"].float(), rays["rgb"][pixels].float())


def fitting_rays(batch: dict[str, Tensor], left_half: bool) -> dict[str, Tensor]:
    """A test image's fitting pixels: its left half (``left_columns``) or the whole image, those its "mask" keeps
    where it has one: "origins", "directions", "viewdirs" (where the batch has them), "rgb", each [M, 3], copies
    autograd may use (called outside inference mode)."""
    H, W, _ = batch["rgb"].shape  # rows, columns, channels
    columns = slice(0, left_columns(W) if left_half else W)
    mask = batch.get("mask")
    kept = (torch.ones(H, columns.stop, dtype=torch.bool, device=batch["rgb"].device) if mask is None
            else mask[:, columns].clone())
    return {key: batch[key][:, columns][kept].clone() for key in ("origins", "directions", "viewdirs", "rgb")
            if key in batch}


def check_scored(views: Views, split: str, protocol: str) -> None:
    """A DatasetError naming the split and the view where a view of ``split`` would have no headline PSNR or SSIM
    (``unscorable``) under the test protocol ``protocol``: a test view's right half under NeRF-W's, else the whole
    image (a validation is always scored on the whole image). Called before any step, so that a split with nothing
    left to score is refused in one line, never scored NaN."""
    start = left_columns(views.width) if split == "test" and protocol == NERFW_RIGHT_HALF else 0
    mask = None if views.mask is None else views.mask[:, :, start:]
    problem = unscorable(views.height, views.width - start, mask)
    if problem is not None:
        i, why = problem
        region = (f"its right half (columns {start} to {views.width - 1}, test_protocol={protocol})" if start
                  else "the image")
        raise DatasetError(f"the {SPLIT_NAMES[split]} view {views.name(i)}: {region} {why}, so it would be scored "
                           "NaN: every view scored must leave pixels to score")
