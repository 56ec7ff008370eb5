"""Published figures the report sets beside measured ones, each with the scenes it is of and the protocol it was
measured under: the NeRF paper's (Mildenhall et al., ECCV 2020; docs/departures.md says where nerfexp differs).

A figure is of scenes named as nerfexp's catalogue names them (``nerfexp.data.catalog``: ``blender/lego`` is the
scene of the archive the catalogue pins), so that it is set beside a run only where the run's scene is that scene
(``nerfexp.report.publication_tables``); a figure of several scenes is the mean over them. Its ablation ``row`` is
the config the run is labelled with (``ablation=ROW``, ``conf/ablation/``), which trains what the paper's row
states (``nerfexp.settings.rows``); the paper's per-scene figures of its NeRF are the ``complete`` row's.
"""

from dataclasses import dataclass

from nerfexp.data.llff import holdout_rule
from nerfexp.report.protocols import OWN_SPLIT, Protocol

NERF = "NeRF (Mildenhall et al., ECCV 2020)"
STEPS = (100_000, 300_000)  # the paper trains each scene for 100k to 300k steps
# The paper's synthetic scenes: 800 x 800 images, the 200 views of each scene's test split
BLENDER = Protocol(resolution=(800, 800), views=(200, 200), split=OWN_SPLIT, steps=STEPS)
# Its real forward-facing scenes: 1008 x 756 images, every 8th held out for testing
LLFF = Protocol(resolution=(1008, 756), views=None, split=holdout_rule(8), steps=STEPS)

# The ablation table's rows: (the paper's name of the row, mean PSNR and SSIM over its 8 Blender scenes)
PAPER_ABLATION = {
    "no_pe_vd_h": ("No PE, VD, H", 26.67, 0.906),
    "no_posenc": ("No Pos. Encoding", 28.77, 0.924),
    "no_view_dependence": ("No View Dependence", 27.66, 0.925),
    "no_hierarchical": ("No Hierarchical", 30.06, 0.938),
    "far_fewer_images": ("Far Fewer Images", 27.78, 0.925),
    "fewer_images": ("Fewer Images", 29.79, 0.940),
    "fewer_frequencies": ("Fewer Frequencies", 30.59, 0.944),
    "more_frequencies": ("More Frequencies", 30.81, 0.946),
    "complete": ("Complete Model", 31.01, 0.947),
}
# Table 1's NeRF PSNR on each scene, by catalogue name
BLENDER_PSNR = {"blender/chair": 33.00, "blender/drums": 25.01, "blender/ficus": 30.13, "blender/hotdog": 36.18,
                "blender/lego": 32.54, "blender/materials": 29.62, "blender/mic": 32.91, "blender/ship": 28.65}
LLFF_PSNR = {"llff/room": 32.70, "llff/fern": 25.17, "llff/leaves": 20.92, "llff/fortress": 31.16,
             "llff/orchids": 20.36, "llff/flower": 27.40, "llff/trex": 26.80, "llff/horns": 27.45}
LLFF_MEAN = (26.50, 0.811)  # Table 1's NeRF on its 8 LLFF scenes: PSNR, SSIM
# The ablation rows on lego alone (PSNR); the complete model's is Table 1's
LEGO_ROWS = {"no_pe_vd_h": 26.38, "no_posenc": 27.75, "no_view_dependence": 29.93, "no_hierarchical": 31.42,
             "far_fewer_images": 27.97, "fewer_images": 31.53, "fewer_frequencies": 30.77, "more_frequencies": 32.50}


@dataclass(frozen=True)
class Figure:
    """A published test score: ``psnr`` (dB) and ``ssim`` (None: not published) of the ablation ``row`` on
    ``scenes`` (catalogue names; several: the mean over them), measured under ``protocol``, printed in ``source``."""

    row: str
    scenes: frozenset[str]
    psnr: float
    ssim: float | None
    protocol: Protocol
    source: str


def paper_figures() -> list[Figure]:
    """Every figure of the NeRF paper that a run can be set beside."""
    table_1, rows = f"{NERF}, Table 1", f"{NERF}, its ablation table"
    figures = [Figure(row, frozenset(BLENDER_PSNR), psnr, ssim, BLENDER, rows)
               for row, (_, psnr, ssim) in PAPER_ABLATION.items()]
    figures += [Figure("complete", frozenset(LLFF_PSNR), *LLFF_MEAN, LLFF, table_1)]
    figures += [Figure("complete", frozenset({scene}), psnr, None, BLENDER, table_1)
                for scene, psnr in BLENDER_PSNR.items()]
    figures += [Figure("complete", frozenset({scene}), psnr, None, LLFF, table_1) for scene, psnr in LLFF_PSNR.items()]
    figures += [Figure(row, frozenset({"blender/lego"}), psnr, None, BLENDER, f"{rows}, on lego alone")
                for row, psnr in LEGO_ROWS.items()]
    return figures


FIGURES = paper_figures()
PUBLISHED_SCENES = frozenset(scene for figure in FIGURES for scene in figure.scenes)


def scene_figure(row: str | None, scene: str) -> Figure | None:
    """The figure of ``row`` on the one scene ``scene`` (a catalogue name), or None where none is published."""
    return next((f for f in FIGURES if f.row == row and f.scenes == {scene}), None)


def mean_figure(row: str | None, scenes: frozenset[str]) -> Figure | None:
    """The published mean of ``row`` over the fewest scenes that include every one of ``scenes`` (catalogue names,
    more than one): the one to set beside a mean over ``scenes``, comparable only where it is over those scenes
    exactly; None where no published mean covers them all."""
    over = [f for f in FIGURES if f.row == row and len(f.scenes) > 1 and scenes <= f.scenes]
    return min(over, key=lambda f: len(f.scenes), default=None)
