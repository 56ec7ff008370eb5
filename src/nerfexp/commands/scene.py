"""``nerfexp-scene OUT_DIR [--scene {builtin,glossy}]``: an analytic scene written as a Blender-format dataset.

``builtin`` is the built-in still life (``data/procedural.py``, ``data=procedural``); ``glossy`` a
strongly view-dependent one (``data/glossy.py``): a mirror sphere, a glossy torus and a clear-coated
checker base reflecting a procedural sky. Both use the same cameras.

``OUT_DIR`` is new, empty, or a scene this command wrote (its ``nerfexp-scene.json``, which records the
settings, says so, and every file in it is one the folder's manifest shows this command wrote:
``nerfexp.manifest``), which is then replaced as a whole: a folder holding anything else, a Blender dataset
from elsewhere above all (it has the same file names), or a file of the scene changed since, is refused with
one line and left as it is. The scene is written beside ``OUT_DIR`` and renamed into place once complete.
"""

import argparse
import json
from importlib.metadata import version
from pathlib import Path

from nerfexp.commands.arguments import command_parser, positive
from nerfexp.commands.console import run_command
from nerfexp.data.blender import write_blender
from nerfexp.data.glossy import load_glossy
from nerfexp.data.procedural import CAMERA_ANGLE_X, load_procedural
from nerfexp.errors import NerfexpError
from nerfexp.files import atomic_directory, folder_entries, foreign_message
from nerfexp.manifest import BOOKKEEPING, check_ours, record
from nerfexp.memory import require_memory, scene_bytes

LOADERS = {"builtin": load_procedural, "glossy": load_glossy}  # --scene: the function rendering a split
SPLITS = ("train", "val", "test")
MARKER = "nerfexp-scene.json"  # the settings of the scene written: the folder is this command's


def check_out_dir(out_dir: Path) -> None:
    """A NerfexpError where ``out_dir`` holds files (its manifest's own aside) and is not a scene this command
    wrote: any, where it holds no ``MARKER``; else those its manifest does not show to be this command's
    (``nerfexp.manifest.check_ours``)."""
    entries = [entry for entry in folder_entries(out_dir) if entry not in BOOKKEEPING]
    if entries and not (out_dir / MARKER).is_file():
        raise NerfexpError(foreign_message(out_dir, entries, "nerfexp-scene", "choose a new or empty folder"))
    check_ours(out_dir, entries, "nerfexp-scene", "move {it} elsewhere, or choose a new or empty folder")


def build_parser() -> argparse.ArgumentParser:
    """``nerfexp-scene OUT_DIR``: render the three splits of an analytic scene in the NeRF Blender format."""
    parser = command_parser("nerfexp-scene", build_parser.__doc__)
    parser.add_argument("out_dir", type=Path, help="folder to write transforms_*.json and the PNGs to")
    parser.add_argument("--scene", choices=sorted(LOADERS), default="builtin",
                        help="builtin: the built-in still life (data=procedural); glossy: a mirror sphere, a "
                             "glossy torus and a clear-coated base reflecting a sky")
    parser.add_argument("--resolution", type=positive(int), default=100, help="image width and height (default 100)")
    parser.add_argument("--n-train", type=positive(int), default=100, help="training views (default 100)")
    parser.add_argument("--n-val", type=positive(int), default=10, help="validation views (default 10)")
    parser.add_argument("--n-test", type=positive(int), default=20, help="test views (default 20)")
    parser.add_argument("--supersample", type=positive(int), default=2,
                        help="rays per pixel side, averaged (default 2: 4 rays per pixel)")
    return parser


def write_scene(args: argparse.Namespace) -> str:
    """Render the scene ``args`` describe into ``args.out_dir`` (after ``nerfexp.memory.require_memory`` for
    its largest split and ``check_out_dir``), with its ``MARKER``; returns a one-line summary."""
    counts = dict(zip(SPLITS, (args.n_train, args.n_val, args.n_test), strict=True))
    largest = max(counts, key=counts.get)  # a split is rendered whole before it is written
    require_memory(f"--resolution {args.resolution} --n-{largest} {counts[largest]} --supersample {args.supersample}",
                   f"a split of {counts[largest]} views", scene_bytes(counts[largest], args.resolution,
                                                                      args.resolution, args.supersample))
    check_out_dir(args.out_dir)
    load = LOADERS[args.scene]
    with atomic_directory(args.out_dir, replace=True) as new:
        for split, n in counts.items():
            views = load(split, n, args.resolution, args.resolution, args.supersample)
            write_blender(new, split, views, CAMERA_ANGLE_X)
        settings = {"scene": args.scene, "resolution": args.resolution, "views": counts,
                    "supersample": args.supersample, "nerfexp": version("nerfexp")}
        (new / MARKER).write_text(json.dumps(settings, indent=2) + "\n")
        record(new, folder_entries(new))  # paths relative to the folder: true once it is renamed into place
    views = ", ".join(f"{n} {split}" for split, n in counts.items())
    return f"the {args.scene} scene ({views} views) written to {args.out_dir}"


def main(argv: list[str] | None = None) -> None:
    """The ``nerfexp-scene`` command (``build_parser``)."""
    run_command(build_parser(), argv, write_scene)


if __name__ == "__main__":
    main()
