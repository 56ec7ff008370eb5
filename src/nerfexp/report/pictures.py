"""The page's pictures: a few test views, each variant's render and error heat map beside the ground
truth, decoded from the runs' ``test/`` PNGs and written anew."""


import math
from collections.abc import Callable
from pathlib import Path

import torch
from matplotlib import colormaps
from torch import Tensor

from nerfexp.data.images import read_image
from nerfexp.errors import DatasetError
from nerfexp.pixels import png_bytes
from nerfexp.report.page import Picture, Tile
from nerfexp.report.runs import Run
from nerfexp.report.variants import Variant
from nerfexp.rundir.layout import DIFFERENCE_PLOT, PARETO_PLOT, PSNR_PLOT, REPORT_IMAGES

VIEWS_SHOWN = 3  # test views on the page by default: the first, the middle and the last
PLOTS = [(PSNR_PLOT, "validation PSNR against training seconds"),
         (PARETO_PLOT, "test PSNR against training time, at the end and at each budget"),
         (DIFFERENCE_PLOT, "test PSNR difference to the reference against training time")]


def default_views(n_views: int, count: int = VIEWS_SHOWN) -> list[int]:
    """``count`` of ``n_views`` test views spread evenly from the first to the last (all where there are
    fewer). Example: 8 views, count 3: [0, 4, 7]."""
    if n_views <= 1:
        return list(range(n_views))
    shown = min(count, n_views)
    return sorted({round(k * (n_views - 1) / (shown - 1)) for k in range(shown)})


def run_seed(run: Run) -> int | None:
    seed = (run.results or {}).get("config", {}).get("seed")
    return seed if isinstance(seed, int) else None


def shown_run(variant: Variant) -> Run | None:
    """The variant's finished run whose renders the page shows: the one with the lowest seed, then the first by the
    other keys it is averaged over (``Variant.seed_of``: a scene of a sweep over scenes), so that variants are shown
    with the same seed, on the same scene, where they have them (then the first by path)."""
    return min(variant.finished, key=lambda run: (run_seed(run) is None, run_seed(run) or 0, variant.seed_of(run),
                                                  str(run.path)), default=None)


def shown_as(variant: Variant, run: Run) -> str:
    """Which of the variant's runs ``run`` is, as its picture's caption says: "seed 0", and the other keys the
    variant is averaged over where there are any ("seed 0, data.scene=blender/chair")."""
    others = [o for o in variant.seed_of(run) if not o.startswith("seed=")]
    return ", ".join([f"seed {run_seed(run)}", *others])


ERROR_WHITE = 0.25  # the error heat map's scale: 0 black, this mean absolute error (of 1) and above white


def error_heatmap(rgba: Tensor) -> Tensor:
    """The heat map [H, W, 3] (uint8) of an error image [H, W, 4] (uint8, |render - truth| per channel as
    a run saves it): the mean over the colour channels on matplotlib's ``magma`` map, 0 black and
    ``ERROR_WHITE`` or more white, the same scale for every variant."""
    error = rgba[..., :3].double().mean(-1) / 255 / ERROR_WHITE
    return torch.from_numpy(colormaps["magma"](error.clamp(0, 1).numpy(), bytes=True)[..., :3])


def copy_picture(source: Path, folder: Path, name: str, alt: str,
                 pixels: Callable[[Tensor], Tensor] = lambda rgba: rgba[..., :3]) -> Picture:
    """The image file ``source`` (a run's render, read as data: decoded with its checks, never copied
    byte for byte) written anew as the RGB PNG ``folder/name`` of ``pixels(rgba)`` (uint8 [H, W, 4] ->
    [H, W, 3]); a missing or damaged file is a ``Picture`` saying so. ``name`` is relative to the page's
    folder."""
    try:
        rgba = read_image(source, "the run's test renders")
    except DatasetError as error:
        return Picture(alt, missing="missing" if not source.is_file() else f"unreadable: {error}")
    (folder / name).parent.mkdir(parents=True, exist_ok=True)
    (folder / name).write_bytes(png_bytes(pixels(rgba).numpy()))
    return Picture(alt, f"{REPORT_IMAGES}/{name}", rgba.shape[1])


def view_tiles(variants: list[Variant], views: list[int], folder: Path) -> dict[int, list[Tile]]:
    """For each test view in ``views``: a ground-truth tile, then each variant's render and error image
    (``shown_run``) with that view's PSNR and SSIM, and LPIPS where the run scored it; the pictures written
    into ``folder``."""
    shown = [(variant, shown_run(variant)) for variant in variants]
    tiles = {}
    for index in views:
        truth = next((path for _, run in shown
                      if run is not None and (path := run.path / "test" / f"r_{index}_target.png").is_file()), None)
        row = [Tile("ground truth", (copy_picture(truth, folder, f"view{index}/truth.png", "ground truth")
                                     if truth else Picture("ground truth", missing="missing"),))]
        for k, (variant, run) in enumerate(shown):
            if run is None:
                row.append(Tile(variant.label, (Picture("render", missing="no finished run"),)))
                continue
            test = run.path / "test"
            pictures = (copy_picture(test / f"r_{index}.png", folder, f"view{index}/{k}.png", "render"),
                        copy_picture(test / f"r_{index}_error.png", folder, f"view{index}/{k}_error.png",
                                     "error heat map", error_heatmap))
            caption = shown_as(variant, run)
            if index in (views_run := run.results.get("test_views", [])):
                at = views_run.index(index)
                psnr, ssim = (run.results.get(f"test_{m}_per_view", [math.nan] * len(views_run))[at]
                              for m in ("psnr", "ssim"))
                lpips = run.results.get("test_lpips_per_view")  # absent where the run did not score LPIPS
                lpips_text = f", LPIPS {lpips[at]:.3f}" if lpips else ""
                caption = f"PSNR {psnr:.2f} dB, SSIM {ssim:.3f}{lpips_text}, {caption}"
            row.append(Tile(variant.label, pictures, caption))
        tiles[index] = row
    return tiles


def check_views(variants: list[Variant], views: list[int] | None) -> list[int]:
    """The test views to show: ``views`` where every one is a test view of some shown run, else a
    SystemExit naming the ones that are not; None: ``default_views`` of the runs' test views."""
    available = sorted({i for v in variants if (run := shown_run(v)) for i in run.results.get("test_views", [])})
    if views is None:
        return [available[i] for i in default_views(len(available))]
    if unknown := [i for i in views if i not in available]:
        have = f"views {available[0]} to {available[-1]}" if available else "no test views"
        raise SystemExit(f"nerfexp-report: error: --views {' '.join(map(str, unknown))}: not a test view of "
                         f"the runs shown (they have {have})")
    return list(dict.fromkeys(views))


VIEWS_NOTE = ("Each variant's run with the lowest seed (over scenes, every variant's on the same scene, named below "
              "it): its render of the view (top) and its error (below): the absolute difference to the ground truth "
              f"averaged over the colour channels, black 0, white {ERROR_WHITE:g} and above (magma). The PSNR and "
              "SSIM (and LPIPS, where the run scored it) are that run's on that view. Small images are enlarged with "
              "visible pixels.")
