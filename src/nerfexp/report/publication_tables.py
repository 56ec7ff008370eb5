"""Published figures beside the measured ones (``nerfexp.report.publications``), only where they apply: report.md's
"Published numbers" and report.csv's ``published_*`` columns.

A figure is set beside a variant only where the variant's scenes are the figure's: scenes of nerfexp's catalogue
by name whose archive had the SHA-256 the catalogue pins (``catalogue_scene``: the run's results.json records the
archive it trained on, ``scene``). A folder given (``data.root``) is never known to be one: the catalogue pins
archives, not the camera files inside them. Each side says the protocol it was measured under (resolution, test
views, steps: ``nerfexp.report.protocols.Protocol``); the difference is given only where the published protocol
covers the measured one and the scenes are the same (``Beside.comparable``).

A variant over several scenes (``--over seed data.scene``) is measured as the paper's means are: each scene's mean
over its runs, then the mean over the scenes (``measured``); beside it the published mean over the fewest scenes
that include them (``nerfexp.report.publications.mean_figure``), and beside each of its scenes that scene's figure.
"""

import math
import statistics
from dataclasses import dataclass

from nerfexp.data.catalog import shipped
from nerfexp.report.protocols import Protocol, merged_protocol, run_protocol
from nerfexp.report.publications import Figure, mean_figure, scene_figure
from nerfexp.report.runs import Run
from nerfexp.report.variants import Variant

PUBLISHED_COLUMNS = ("published_psnr", "published_ssim", "published_source", "published_protocol",
                     "measured_protocol", "psnr_minus_published")  # report.csv's, after the variant's own


def catalogue_scene(results: dict) -> str | None:
    """The catalogue name of a finished run's scene where it is the scene nerfexp's catalogue names (its results.json
    ``scene``: a scene by name, of nerfexp's catalogue, whose archive had the SHA-256 the entry pins); None for any
    other: a folder given, a user's catalogue's scene, an archive with no pinned digest or another one."""
    scene = results.get("scene")
    if not scene:
        return None
    entry = next((e for e in shipped() if e.name == scene.get("name")), None)
    if entry is None or entry.sha256 is None:
        return None
    return entry.name if (scene.get("sha256"), scene.get("catalog")) == (entry.sha256, entry.catalog) else None


@dataclass(frozen=True)
class Measured:
    """A variant's test scores on ``scenes`` (catalogue names): ``psnr`` and ``ssim``, each scene's mean over its
    runs, then the mean over the scenes; the ``protocol`` its runs share (None: they differ)."""

    scenes: tuple[str, ...]
    psnr: float
    ssim: float
    protocol: Protocol | None


def measured(by_scene: dict[str, list[Run]]) -> Measured:
    """The ``Measured`` of finished runs by their scene (each scene at least one run)."""
    def mean_over_scenes(key: str) -> float:
        return statistics.fmean(statistics.fmean(run.results[key] for run in runs) for runs in by_scene.values())

    runs = [run for runs in by_scene.values() for run in runs]
    return Measured(tuple(sorted(by_scene)), mean_over_scenes("test_psnr"), mean_over_scenes("test_ssim"),
                    merged_protocol([run_protocol(run.results) for run in runs]))


@dataclass(frozen=True)
class Beside:
    """A published ``figure`` beside what the variant ``label`` measured on its scenes."""

    label: str
    measured: Measured
    figure: Figure

    @property
    def comparable(self) -> bool:
        """Whether the two were measured alike: over the same scenes, and under a protocol the figure's covers."""
        protocol = self.measured.protocol
        return (set(self.measured.scenes) == self.figure.scenes and protocol is not None
                and self.figure.protocol.covers(protocol))

    @property
    def difference(self) -> float:
        """Measured - published PSNR where ``comparable``, else NaN."""
        return self.measured.psnr - self.figure.psnr if self.comparable else math.nan


def scenes_of(variant: Variant) -> dict[str | None, list[Run]]:
    """The variant's finished runs by ``catalogue_scene`` (None: runs whose scene is no catalogue scene known)."""
    by_scene: dict[str | None, list[Run]] = {}
    for run in variant.finished:
        by_scene.setdefault(catalogue_scene(run.results), []).append(run)
    return by_scene


def beside_published(variant: Variant) -> list[Beside]:
    """The published figures of the variant's ablation row beside its scores: each of its scenes' own figure, then
    the published mean beside its mean over its scenes where every one of them is a catalogue scene (and it has
    several, or its one scene has no figure of its own); none for a variant without an ablation row or on scenes
    no figure is of."""
    row, by_scene = variant.choice("ablation"), scenes_of(variant)
    known = {scene: runs for scene, runs in by_scene.items() if scene is not None}
    rows = [Beside(variant.label, measured({scene: runs}), figure) for scene, runs in sorted(known.items())
            if (figure := scene_figure(row, scene)) is not None]
    if known and None not in by_scene and (len(known) > 1 or not rows):
        if (figure := mean_figure(row, frozenset(known))) is not None:
            rows.append(Beside(variant.label, measured(known), figure))
    return rows


def variant_beside(variant: Variant) -> Beside | None:
    """The figure beside the variant as a whole: the one of ``beside_published`` over all of its scenes."""
    by_scene = scenes_of(variant)
    return next((b for b in beside_published(variant) if None not in by_scene
                 and set(b.measured.scenes) == set(by_scene)), None)


def published_columns(beside: Beside | None) -> dict:
    """report.csv's ``PUBLISHED_COLUMNS`` of a variant (``variant_beside``): NaN and empty where no figure applies."""
    if beside is None:
        return {"published_psnr": math.nan, "published_ssim": math.nan, "published_source": "",
                "published_protocol": "", "measured_protocol": "", "psnr_minus_published": math.nan}
    figure = beside.figure
    return {"published_psnr": figure.psnr, "published_ssim": math.nan if figure.ssim is None else figure.ssim,
            "published_source": figure.source, "published_protocol": figure_text(figure),
            "measured_protocol": protocol_text(beside.measured), "psnr_minus_published": beside.difference}


def scenes_text(scenes) -> str:
    """"blender/lego"; several: "mean over 3 scenes (blender/chair, blender/drums, blender/lego)"."""
    scenes = sorted(scenes)
    return scenes[0] if len(scenes) == 1 else f"mean over {len(scenes)} scenes ({', '.join(scenes)})"


def protocol_text(measured: Measured) -> str:
    protocol = measured.protocol
    return "its runs' protocols differ" if protocol is None else protocol.text()


def figure_text(figure: Figure) -> str:
    """Where a figure was measured: its scenes where several, and its protocol."""
    protocol = figure.protocol.text(published=True)
    return protocol if len(figure.scenes) == 1 else f"{over_text(figure)}; {protocol}"


def over_text(figure: Figure) -> str:
    """"the scene"; several: "mean over 8 scenes"."""
    return "the scene" if len(figure.scenes) == 1 else f"mean over {len(figure.scenes)} scenes"


def fmt(value: float | None, digits: int) -> str:
    return "–" if value is None or not math.isfinite(value) else f"{value:.{digits}f}"


def published_method(variants: list[Variant]) -> list[str]:
    """report.md's note on how a published figure's measured side was computed, where a figure is beside a variant over
    several scenes (which figures apply, and their protocols, "Published numbers" says itself); else none."""
    if not any(len(beside.measured.scenes) > 1 for variant in variants for beside in beside_published(variant)):
        return []
    return ["Published numbers: over several scenes a variant's score there is each scene's mean over its runs, then "
            "the mean over the scenes, as the paper's means are (the table's is the mean over all of its runs)."]


def published_text(variants: list[Variant]) -> list[str]:
    """report.md's "Published numbers": a line per figure beside a variant (``beside_published``), each side with its
    protocol (said once above the table where every line's is the same), the difference only where ``comparable``
    (no column where none is); nothing where no figure applies."""
    besides = [beside for variant in variants for beside in beside_published(variant)]
    if not besides:
        return []
    compared = any(beside.comparable for beside in besides)
    ours = {protocol_text(beside.measured) for beside in besides}
    theirs = {beside.figure.protocol.text(published=True) for beside in besides}
    header = ["variant", "scenes", "test PSNR (dB)", "test SSIM", *(["measured under"] if len(ours) > 1 else []),
              "published PSNR", "published SSIM", "published over", *(["published under"] if len(theirs) > 1 else []),
              "source", *(["PSNR - published"] if compared else [])]
    said = [f"Ours were measured under: {next(iter(ours))}." if len(ours) == 1 else "",
            f"The published, under: {next(iter(theirs))}." if len(theirs) == 1 else ""]
    lines = ["## Published numbers", "",
             "The published figures of each variant's ablation row on its scenes, beside its own: only on scenes "
             "known to be the publication's (a scene of nerfexp's catalogue by name, whose archive had the SHA-256 "
             "the catalogue pins). " + " ".join(filter(None, said)) + " "
             + ("The difference where both were measured over the same scenes under the same protocol; – where "
                "not, and the two are not compared." if compared else
                "None was measured over the same scenes under the same protocol: the two are not compared."), "",
             "| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    for beside in besides:
        measured, figure = beside.measured, beside.figure
        cells = [beside.label, scenes_text(measured.scenes), fmt(measured.psnr, 2), fmt(measured.ssim, 3),
                 *([protocol_text(measured)] if len(ours) > 1 else []), fmt(figure.psnr, 2), fmt(figure.ssim, 3),
                 over_text(figure), *([figure.protocol.text(published=True)] if len(theirs) > 1 else []),
                 figure.source]
        cells += [f"{beside.difference:+.2f}" if beside.comparable else "–"] if compared else []
        lines.append("| " + " | ".join(cells) + " |")
    return lines
