"""Published figures beside measured ones only where they apply: on the publication's scenes (a catalogue scene known
by its name and pinned archive checksum), each side with its protocol, the difference only where the protocols and
the scenes are the same; a variant over several scenes as the mean over them (run directories written by hand with
known numbers, and real runs of a scene by name and of a folder)."""

import csv
import json
import math
import shutil
import statistics
from pathlib import Path

import pytest

from nerfexp.data.catalog import shipped
from nerfexp.data.llff import holdout_rule
from nerfexp.data.scene_cache import SCENE_KEYS, scene_folder, scene_record_path
from nerfexp.report.folder import write_report
from nerfexp.report.protocols import Protocol
from nerfexp.report.publications import BLENDER, BLENDER_PSNR, FIGURES, LEGO_ROWS, LLFF_PSNR, PAPER_ABLATION
from nerfexp.rundir.records import REFINED
from tests.helpers import TINY, make_run, run_nerfexp

ENTRIES = {entry.name: entry for entry in shipped()}
PAPER = {"steps": 200_000, "resolution": [800, 800], "views": 200}  # a run at the paper's Blender protocol


def scene_record(name: str, **changes) -> dict:
    """results.json's ``scene`` of a run on the catalogue scene ``name`` as the cache records it (``changes``: keys
    replaced)."""
    entry = ENTRIES[name]
    record = {"name": name, "catalog": entry.catalog, "url": entry.urls[0], "downloaded_from": entry.urls[0],
              "path": entry.path, "sha256": entry.sha256, "size": 1, "checksum": "pinned",
              "sha256_from": entry.sha256_from, "recorded": "2026-01-01T00:00:00Z",
              "unpacked": "2026-01-01T00:00:00Z", "folder": f"/cache/scenes/{name.replace('/', '+')}"}
    assert set(record) == set(SCENE_KEYS)
    return {**record, **changes}


def measured_run(root: Path, name: str, row: str, scene: dict | None, seed: int = 0, psnr: float = 30.0,
                 ssim: float = 0.9, steps: int = 200_000, resolution=(800, 800), views: int = 200,
                 split: str | None = None, folder: str = "/data/nerf_synthetic/lego", **results) -> Path:
    """A finished run of the ablation ``row`` on the scene ``scene`` records (None: the folder ``folder``, given as
    data.root), with its test scores and protocol; ``results``: more keys of its results.json."""
    where = f"data.scene={scene['name']}" if scene else f"data.root={folder}"
    run = make_run(root, name, [f"ablation={row}", where, f"seed={seed}"], psnr=psnr, ssim=ssim,
                   choices={"ablation": row, "data": "blender"})
    written = json.loads((run / "results.json").read_text())
    written.update(steps=steps, time_per_step_s=written["train_time_s"] / steps, test_views=list(range(views)),
                   **results)
    written.update({"test_resolution": list(resolution)} if resolution else {})  # None: as an earlier nerfexp's run
    written.update({"scene": scene} if scene else {})
    written.update({"split": split} if split else {})
    (run / "results.json").write_text(json.dumps(written))
    return run


def read_csv(path: Path) -> dict[str, dict]:
    with open(path) as file:
        return {row["variant"]: row for row in csv.DictReader(file)}


def section(report: str) -> str:
    """report.md's "Published numbers" ("" where it has no such section)."""
    return report.split("## Published numbers")[1].split("\n## ")[0] if "## Published numbers" in report else ""


def published(report: str) -> list[str]:
    """The lines of report.md's "Published numbers" table (none where it has no such section)."""
    return [line for line in section(report).splitlines() if line.startswith("| ")][1:]


# Whether a run's scene is the paper's lego, by what its results.json records: the catalogue's name and the
# archive's SHA-256 the catalogue pins (nerfexp's own catalogue); a folder is never known to be it
IDENTITIES = {
    "the catalogue's lego, its pinned archive": (scene_record("blender/lego"), True),
    "lego's folder given as data.root": (None, False),
    "a lego of another archive": (scene_record("blender/lego", sha256="0" * 64), False),
    "a lego of a user's catalogue": (scene_record("blender/lego", catalog="lab.yaml"), False),
}


@pytest.mark.parametrize("scene, shown", IDENTITIES.values(), ids=IDENTITIES)
def test_a_published_figure_is_shown_only_beside_the_publications_own_scene(tmp_path, scene, shown):
    for seed, psnr in enumerate((31.0, 32.0)):
        measured_run(tmp_path, f"c{seed}", "complete", scene, seed=seed, psnr=psnr)
    write_report([tmp_path], tmp_path)
    report, (row,) = (tmp_path / "report.md").read_text(), read_csv(tmp_path / "report.csv").values()
    if not shown:
        assert published(report) == [] and "32.54" not in report and "Published numbers" not in report  # nor a word of them
        assert math.isnan(float(row["published_psnr"])) and row["published_source"] == ""
        return
    # Table 1's NeRF on lego: 32.54 dB; ours the mean of 31.0 and 32.0 = 31.5, measured under the paper's protocol
    protocol = "800 x 800 px, 200 test views (the scene's own test split), 200,000 steps"
    assert published(report) == ["| ablation=complete, data.scene=blender/lego | blender/lego | 31.50 | 0.900 | 32.54 "
                                 "| – | the scene | NeRF (Mildenhall et al., ECCV 2020), Table 1 | -1.04 |"]
    assert f"Ours were measured under: {protocol}. The published, under: 800 x 800 px, 200 test views (the scene's " \
           "own test split), 100,000 to 300,000 steps." in section(report)  # one line: each protocol said once
    assert float(row["published_psnr"]) == 32.54 and math.isnan(float(row["published_ssim"]))
    assert float(row["psnr_minus_published"]) == pytest.approx(31.5 - 32.54) and row["measured_protocol"] == protocol


def test_no_published_figure_beside_a_scene_of_a_folder_the_glossy_scene_or_a_row_the_paper_has_none_of(tmp_path):
    measured_run(tmp_path, "glossy", "complete", None, folder="/data/glossy")  # nerfexp-scene --scene glossy
    measured_run(tmp_path, "lego", "complete", None)  # a Blender scene of unknown identity
    make_run(tmp_path, "plain", ["data.scene=blender/lego", "seed=0"], choices={"data": "blender"})  # no row
    write_report([tmp_path], tmp_path)
    assert published((tmp_path / "report.md").read_text()) == []
    assert all(math.isnan(float(row["published_psnr"])) for row in read_csv(tmp_path / "report.csv").values())


# One thing of the protocol changed from the paper's at a time: each is another protocol, so both are shown with what
# they were measured under and no difference; the paper's range of steps includes its ends
PROTOCOLS = {
    "half the resolution": ({"resolution": (400, 400)}, "400 x 400 px, 200 test views", False),
    "every other test view": ({"views": 100}, "800 x 800 px, 100 test views", False),
    "fewer steps": ({"steps": 50_000}, "50,000 steps", False),
    "more steps": ({"steps": 300_001}, "300,001 steps", False),
    "views split by a rule": ({"split": holdout_rule(8)}, "(" + holdout_rule(8) + ")", False),
    "refined test cameras": ({"test_cameras": REFINED}, "steps, test cameras refined", False),
    "NeRF-W's right halves": ({"test_protocol": "nerfw_right_half"}, "steps, NeRF-W's right halves", False),
    "resolution not recorded (an earlier nerfexp's run)": ({"resolution": None}, "resolution not recorded", False),
    "the paper's fewest steps": ({"steps": 100_000}, "100,000 steps", True),
    "the paper's most steps": ({"steps": 300_000}, "300,000 steps", True),
}


@pytest.mark.parametrize("changes, words, comparable", PROTOCOLS.values(), ids=PROTOCOLS)
def test_under_another_protocol_both_are_shown_with_their_protocols_and_no_difference(tmp_path, changes, words,
                                                                                      comparable):
    measured_run(tmp_path, "c0", "complete", scene_record("blender/lego"), psnr=30.0, **{**PAPER, **changes})
    write_report([tmp_path], tmp_path)
    report, (row,) = (tmp_path / "report.md").read_text(), read_csv(tmp_path / "report.csv").values()
    (line,) = published(report)
    ours = section(report).split("Ours were measured under: ")[1].split(". The published")[0]
    assert words in row["measured_protocol"] == ours and words in ours  # ours, said with its protocol
    assert "The published, under: 800 x 800 px, 200 test views (the scene's own test split), 100,000 to 300,000 " \
           "steps." in section(report) and "| 32.54 | – | the scene |" in line
    if comparable:
        assert line.endswith("| -2.54 |") and float(row["psnr_minus_published"]) == pytest.approx(-2.54)
    else:
        assert "PSNR - published" not in report and line.endswith(", Table 1 |")
        assert math.isnan(float(row["psnr_minus_published"])) and float(row["published_psnr"]) == 32.54
        assert "None was measured over the same scenes under the same protocol: the two are not compared." in report


def test_the_mean_over_the_papers_8_scenes_beside_its_rows_and_each_scenes_own_figure(tmp_path):
    # complete and no_posenc on the paper's 8 scenes, seeds 0 and 1; lego's complete has a third seed, so the mean over
    # runs (17 of complete) is not the mean over scenes. Per scene s (0..7): complete 30 + s + seed, no_posenc 28 + s
    scenes = sorted(BLENDER_PSNR)
    for s, scene in enumerate(scenes):
        for seed in range(3 if scene == "blender/lego" else 2):
            measured_run(tmp_path, f"c_{s}_{seed}", "complete", scene_record(scene), seed=seed, psnr=30.0 + s + seed)
        for seed in range(2):
            measured_run(tmp_path, f"p_{s}_{seed}", "no_posenc", scene_record(scene), seed=seed, psnr=28.0 + s)
    write_report([tmp_path], tmp_path, over=("seed", "data.scene"))
    report, table = (tmp_path / "report.md").read_text(), read_csv(tmp_path / "report.csv")
    # by hand: each scene's complete mean is 30 + s + 0.5 (lego, s = 4: 30 + 4 + 1); over scenes 30 + 3.5 + 0.5 + 0.5/8
    complete_mean = statistics.fmean(30 + s + (1.0 if scene == "blender/lego" else 0.5)
                                     for s, scene in enumerate(scenes))
    assert complete_mean == pytest.approx(34.0625)
    lines = published(report)
    mean_lines = [line for line in lines if "mean over 8 scenes (" in line]
    # complete's 8 scenes (Table 1) and its mean; no_posenc on lego (its row on lego alone) and its mean
    assert len(lines) == 8 + 1 + 1 + 1 and len(mean_lines) == 2
    (lego,) = [line for line in lines if line.startswith("| ablation=no_posenc | blender/lego |")]
    assert f"| {28 + 4:.2f} |" in lego and lego.endswith(f"| {28 + 4 - LEGO_ROWS['no_posenc']:+.2f} |")
    complete = next(line for line in mean_lines if line.startswith("| ablation=complete |"))
    assert f"| {complete_mean:.2f} |" in complete and "| 31.01 | 0.947 | mean over 8 scenes |" in complete
    assert complete.endswith(f"| {complete_mean - 31.01:+.2f} |")
    assert float(table["ablation=complete"]["psnr_minus_published"]) == pytest.approx(complete_mean - 31.01)
    assert float(table["ablation=no_posenc"]["psnr_minus_published"]) == pytest.approx(28 + 3.5 - 28.77)
    for s, scene in enumerate(scenes):  # each scene's own: Table 1's
        (line,) = [line for line in lines if line.startswith(f"| ablation=complete | {scene} |")]
        ours = 30 + s + (1.0 if scene == "blender/lego" else 0.5)
        assert f"| {ours:.2f} |" in line and line.endswith(f"| {ours - BLENDER_PSNR[scene]:+.2f} |")
    # the table's mean is over the runs (the variant's scores as everywhere else), the published one over the scenes
    assert float(table["ablation=complete"]["test_psnr_mean"]) != pytest.approx(complete_mean)
    # against the reference, a run is paired with its run of the same seed on the same scene: 16 pairs, each by hand
    # (28 + s) - (30 + s + seed): -2 or -3, mean -2.5
    assert float(table["ablation=no_posenc"]["paired_seeds"]) == 16
    assert float(table["ablation=no_posenc"]["psnr_diff"]) == pytest.approx(-2.5)
    assert "each run paired with the reference's run of the same seed, data.scene," in report
    method = report.split("## How these numbers were computed")[1]  # how the mean over scenes was taken, once
    assert report.count("each scene's mean over its runs, then the mean over the scenes") == 1
    assert "- Published numbers: over several scenes" in method and "SHA-256" not in method  # said where it applies


def test_a_sweep_over_some_of_the_papers_scenes_shows_its_mean_beside_the_papers_without_a_difference(tmp_path):
    for s, scene in enumerate(("blender/chair", "blender/drums", "blender/ficus")):
        measured_run(tmp_path, f"p{s}", "no_posenc", scene_record(scene), psnr=27.0 + s)
    write_report([tmp_path], tmp_path, over=("seed", "data.scene"))
    report = (tmp_path / "report.md").read_text()
    (line,) = published(report)
    assert line.startswith("| ablation=no_posenc | mean over 3 scenes (blender/chair, blender/drums, blender/ficus) "
                           "| 28.00 |") and "| 28.77 | 0.924 | mean over 8 scenes |" in line
    assert "PSNR - published" not in report
    assert math.isnan(float(read_csv(tmp_path / "report.csv")["ablation=no_posenc"]["psnr_minus_published"]))


def test_a_real_forward_facing_scene_beside_table_1_under_the_llff_protocol_and_no_mean_across_datasets(tmp_path):
    llff = {"resolution": (1008, 756), "views": 3, "split": holdout_rule(8)}  # fern: 20 images, 3 held out
    measured_run(tmp_path, "fern", "complete", scene_record("llff/fern"), psnr=26.0, **llff)
    measured_run(tmp_path, "lego", "complete", scene_record("blender/lego"), psnr=31.0, **PAPER)
    write_report([tmp_path], tmp_path, over=("seed", "data.scene"))
    lines = published((tmp_path / "report.md").read_text())
    assert [line.split(" | ")[1] for line in lines] == ["blender/lego", "llff/fern"]  # no mean over both datasets
    fern = lines[1]
    assert "| 1008 x 756 px, 3 test views (every 8th image in file-name order a test view (data.holdout)), " \
           "200,000 steps |" in fern and f"| {LLFF_PSNR['llff/fern']:.2f} |" in fern
    assert "| the scene | 1008 x 756 px, every held-out view (every 8th image" in fern  # protocols differ: per line
    assert fern.endswith(f"| {26.0 - 25.17:+.2f} |")


def test_every_row_of_the_papers_table_has_its_mean_and_its_lego_figure():
    # PAPER.md, written out: the ablation table's means over the 8 scenes, and the same rows on lego alone
    means = {"no_pe_vd_h": 26.67, "no_posenc": 28.77, "no_view_dependence": 27.66, "no_hierarchical": 30.06,
             "far_fewer_images": 27.78, "fewer_images": 29.79, "fewer_frequencies": 30.59, "more_frequencies": 30.81,
             "complete": 31.01}
    lego = {"complete": 32.54, "no_pe_vd_h": 26.38, "no_posenc": 27.75, "no_view_dependence": 29.93,
            "no_hierarchical": 31.42, "fewer_images": 31.53, "far_fewer_images": 27.97, "fewer_frequencies": 30.77,
            "more_frequencies": 32.50}
    eight = frozenset(BLENDER_PSNR)
    assert {f.row: f.psnr for f in FIGURES if f.scenes == eight} == means
    assert means == {row: psnr for row, (_, psnr, _) in PAPER_ABLATION.items()}
    assert {f.row: f.psnr for f in FIGURES if f.scenes == {"blender/lego"}} == lego == {**LEGO_ROWS, "complete": 32.54}
    assert all(name in ENTRIES and ENTRIES[name].sha256 for f in FIGURES for name in f.scenes)  # pinned scenes only


@pytest.mark.parametrize("measured, covered", [
    (Protocol((800, 800), (200, 200), None, (200_000, 200_000)), True),
    (Protocol((800, 800), (200, 200), None, (100_000, 300_000)), True),  # a variant's runs from 100k to 300k steps
    (Protocol((800, 800), (200, 200), None, (50_000, 200_000)), False),  # one of its runs trained 50k
    (Protocol((800, 800), (200, 200), None, None), False),  # steps not recorded
    (Protocol((800, 800), None, None, (200_000, 200_000)), False),  # views not recorded
    (Protocol((800, 800), (200, 200), None, (200_000, 200_000), REFINED), False),
])
def test_a_published_protocol_covers_a_measured_one_only_where_each_part_is_within_it(measured, covered):
    assert BLENDER.covers(measured) is covered


@pytest.mark.slow
def test_real_runs_of_the_catalogues_lego_and_of_a_glossy_folder(tmp_path, monkeypatch):
    # the cache holds blender/lego as a fetch leaves it, its record of the archive the catalogue pins (the folder: a
    # scene nerfexp-scene writes, tiny): nerfexp trains on it offline and records it; the glossy scene is a folder
    cache, scenes = tmp_path / "cache", tmp_path / "scenes"
    for kind in ("builtin", "glossy"):
        written = run_nerfexp(str(scenes / kind), "--scene", kind, "--resolution", "24", "--n-train", "12",
                              "--n-val", "1", "--n-test", "2", cwd=tmp_path, script="nerfexp-scene")
        assert written.returncode == 0, written.stderr[-3000:]
    entry = ENTRIES["blender/lego"]
    shutil.copytree(scenes / "builtin", scene_folder(cache, entry.name))
    scene_record_path(cache, entry.name).write_text(json.dumps(
        {**scene_record(entry.name), "folder": str(scene_folder(cache, entry.name))}))
    monkeypatch.setenv("NERFEXP_DATA", str(cache))
    tiny = [o for o in TINY if not o.startswith(("data.n_test", "scale.image_size", "data.n_train"))]
    for name, where in (("lego", f"data.scene={entry.name}"), ("glossy", f"data.root={scenes / 'glossy'}")):
        done = run_nerfexp("ablation=complete", "data=blender", where, *tiny,
                           f"hydra.run.dir={tmp_path / 'runs' / name}", cwd=tmp_path)
        assert done.returncode == 0, done.stderr[-3000:]
    results = json.loads((tmp_path / "runs" / "lego" / "results.json").read_text())
    assert results["scene"]["sha256"] == entry.sha256 and results["test_resolution"] == [24, 24]
    write_report([tmp_path / "runs"], tmp_path / "runs")
    (line,) = published((tmp_path / "runs" / "report.md").read_text())  # lego's, not the glossy folder's
    views = len(results["test_views"])
    assert line.startswith("| data.scene=blender/lego | blender/lego |")  # ablation=complete: what both share
    report = (tmp_path / "runs" / "report.md").read_text()
    assert f"Ours were measured under: 24 x 24 px, {views} test view{'' if views == 1 else 's'} (the scene's own " \
           "test split), 60 steps." in section(report)
    assert "| 32.54 | – | the scene |" in line and "PSNR - published" not in report
