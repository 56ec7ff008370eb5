"""Check that a change leaves what every existing variant computes as it was: train the same variants with two
installs of nerfexp (clean clones, each with its own environment) and compare their scores and test images.

    python benchmarks/checks/same_variants.py run BEFORE_VENV/bin/nerfexp OUT/before [NAME ...]
    python benchmarks/checks/same_variants.py run AFTER_VENV/bin/nerfexp OUT/after [NAME ...]
    python benchmarks/checks/same_variants.py compare OUT/before OUT/after

``run`` trains each variant of ``VARIANTS`` (300 steps; the default experiment at its own length), or the NAMEs
given, into ``OUT/NAME``, one process at a time; run it alone on the machine: beside another process that trained, the
hash grid's variants once came out different in the fourth decimal of PSNR (docs/testing.md).
``compare`` writes ``benchmarks/results/same_variants.md`` and ``.json``: per variant trained in both folders,
whether the scores in results.json and every image under ``test/`` are identical.
"""

import hashlib
import json
import platform
import subprocess
import sys
from pathlib import Path

from nerfexp.files import atomic_write

RESULTS = Path(__file__).parents[1] / "results"  # benchmarks/results
SHORT = ["scale.steps=300", "scale.val_every=300"]
VARIANTS = {
    "default": [],  # the README's default experiment, the paper's complete model at scale=cpu
    "complete": SHORT,  # the same at 300 steps
    "single": ["hierarchical=false", *SHORT],
    "no_posenc": ["ablation=no_posenc", *SHORT],
    "fewer_images": ["ablation=fewer_images", *SHORT],
    "fast": ["experiment=fast", *SHORT],
    "hashgrid": ["encoding=hashgrid", *SHORT],
    "occupancy": ["acceleration=occupancy", *SHORT],
    "hash_occ": ["encoding=hashgrid", "acceleration=occupancy", *SHORT],
    "proposal": ["hierarchical=proposal", *SHORT],
    "sh": ["view_dependence=sh", *SHORT],
    "ref": ["view_dependence=ref", "scale.steps=100", "scale.val_every=100"],
    "blender": ["data=blender", "data.root={scene}", *SHORT],
}
SCORES = ("steps", "n_params", "evaluations_per_ray", "val_psnr", "val_ssim", "test_psnr", "test_ssim",
          "test_psnr_per_view", "test_ssim_per_view")


def run(nerfexp: Path, out: Path, names: list[str]) -> None:
    """Train each variant ``names`` names (none: every one) with the ``nerfexp`` executable given into
    ``out/NAME``."""
    unknown = sorted(set(names) - set(VARIANTS))
    if unknown:
        sys.exit(f"same_variants: no variant {unknown} (choose from {', '.join(VARIANTS)})")
    out.mkdir(parents=True, exist_ok=True)
    scene = out / "scene"
    if not scene.exists():  # a small Blender-format scene, written by the same install
        subprocess.run([str(nerfexp.with_name("nerfexp-scene")), str(scene), "--resolution", "32", "--n-train", "20",
                        "--n-val", "1", "--n-test", "2"], check=True, stdout=subprocess.DEVNULL)
    for name, overrides in VARIANTS.items():
        if names and name not in names:
            continue
        print(f"{name}: nerfexp {' '.join(overrides)}", flush=True)
        with open(out / f"{name}.log", "w") as log:
            subprocess.run([str(nerfexp), *(o.format(scene=scene) for o in overrides),
                            "trainer.enable_progress_bar=false", f"hydra.run.dir={out / name}"],
                           check=True, stdout=log, stderr=subprocess.STDOUT)


def images(run_dir: Path) -> dict[str, str]:
    """The sha256 of each test image the run wrote."""
    return {p.name: hashlib.sha256(p.read_bytes()).hexdigest() for p in sorted((run_dir / "test").glob("*.png"))}


def compare(before: Path, after: Path) -> None:
    rows = []
    trained = [n for n in VARIANTS if all((folder / n / "results.json").exists() for folder in (before, after))]
    for name in trained:
        old = json.loads((before / name / "results.json").read_text())
        new = json.loads((after / name / "results.json").read_text())
        rows.append({"variant": name, "overrides": VARIANTS[name], "test_psnr_before": old["test_psnr"],
                     "test_psnr_after": new["test_psnr"],
                     "scores_differ": [k for k in SCORES if old.get(k) != new.get(k)],
                     "images": len(images(before / name)),
                     "images_identical": images(before / name) == images(after / name)})
    cpu = next((line.split(":", 1)[1].strip() for line in Path("/proc/cpuinfo").read_text().splitlines()
                if line.startswith("model name")), platform.processor())
    record = {"cpu": cpu, "before": str(before), "after": str(after), "variants": rows}
    atomic_write(RESULTS / "same_variants.json", (json.dumps(record, indent=1) + "\n").encode())
    lines = [f"# Variants before and after a change ({cpu})", "",
             f"`python benchmarks/checks/same_variants.py compare {before} {after}`", "",
             "| variant | overrides | test PSNR before | after | scores | test images |", "|---|---|---|---|---|---|"]
    for r in rows:
        scores = "identical" if not r["scores_differ"] else "differ: " + ", ".join(r["scores_differ"])
        shown = f"{r['images']} identical" if r["images_identical"] else "differ"
        lines.append(f"| {r['variant']} | `{' '.join(r['overrides']) or '(none)'}` | {r['test_psnr_before']:.4f} | "
                     f"{r['test_psnr_after']:.4f} | {scores} | {shown} |")
    atomic_write(RESULTS / "same_variants.md", ("\n".join(lines) + "\n").encode())
    print("\n".join(lines))


if __name__ == "__main__":
    if len(sys.argv) < 4 or sys.argv[1] not in ("run", "compare") or sys.argv[1] == "compare" and len(sys.argv) > 4:
        sys.exit(__doc__)
    if sys.argv[1] == "run":
        run(Path(sys.argv[2]), Path(sys.argv[3]), sys.argv[4:])
    else:
        compare(Path(sys.argv[2]), Path(sys.argv[3]))
