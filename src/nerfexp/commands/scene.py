"""``nerfexp-scene OUT_DIR [--scene {builtin,glossy,unbounded}] [--format {blender,nerfstudio}]
[--lens {pinhole,real}] [--occluders]``: an analytic scene written as a dataset, ground truth to test a format
and a camera model on.

``builtin`` is the built-in still life (``data/procedural.py``, ``data=procedural``); ``glossy`` a
strongly view-dependent one (``data/glossy.py``): a mirror sphere, a glossy torus and a clear-coated
checker base reflecting a procedural sky; ``unbounded`` the still life inside a painted room far beyond the
cameras (``data/unbounded.py``), ground truth for ``contraction=mipnerf360``. All use the same cameras.

``--format blender`` (the default) writes NeRF's Blender format (``transforms_{split}.json``, an ideal
centred pinhole); ``--format nerfstudio`` nerfstudio's (``transforms.json``, ``data=nerfstudio``), seen
through ``--lens pinhole`` (the Blender camera) or ``--lens real`` (``procedural.real_lens``: the principal
point off the centre, fx != fy, OPENCV distortion), and with ``--occluders`` a transient square in every
image that its mask leaves out (``procedural.occlude``). ``--appearance-changes train`` gives each training image
its own exposure and white balance (``procedural.vary_appearance``), the validation and test images none; ``all``,
every image.

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
from nerfexp.data.procedural import (
    APPEARANCE_CHANGES,
    APPEARANCE_SEEDS,
    CAMERA_ANGLE_X,
    appearance_gains,
    load_procedural,
    occlude,
    real_lens,
    vary_appearance,
)
from nerfexp.data.transforms_file import write_nerfstudio
from nerfexp.data.unbounded import load_unbounded
from nerfexp.errors import NerfexpError
from nerfexp.files import atomic_directory, folder_entries, foreign_message
from nerfexp.manifest import BOOKKEEPING, check_ours, record
from nerfexp.memory import require_memory, scene_bytes

# --scene: the function rendering a split
LOADERS = {"builtin": load_procedural, "glossy": load_glossy, "unbounded": load_unbounded}
SPLITS = ("train", "val", "test")
FORMATS = ("blender", "nerfstudio")
LENSES = ("pinhole", "real")
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
                             "glossy torus and a clear-coated base reflecting a sky; unbounded: the still life "
                             "inside a painted room ten times the cameras' distance away (every pixel opaque)")
    parser.add_argument("--resolution", type=positive(int), default=100, help="image width and height (default 100)")
    parser.add_argument("--n-train", type=positive(int), default=100, help="training views (default 100)")
    parser.add_argument("--n-val", type=positive(int), default=10, help="validation views (default 10)")
    parser.add_argument("--n-test", type=positive(int), default=20, help="test views (default 20)")
    parser.add_argument("--supersample", type=positive(int), default=2,
                        help="rays per pixel side, averaged (default 2: 4 rays per pixel)")
    parser.add_argument("--format", choices=FORMATS, default="blender",
                        help="blender: transforms_{train,val,test}.json (data=blender); nerfstudio: transforms.json "
                             "with the lens and the splits (data=nerfstudio)")
    parser.add_argument("--lens", choices=LENSES, default="pinhole",
                        help="pinhole: the Blender camera (centred, one focal length); real (nerfstudio only): the "
                             "principal point off the centre, fx != fy and OPENCV lens distortion")
    parser.add_argument("--occluders", action="store_true",
                        help="nerfstudio only: a magenta square in every image, left out by the image's mask")
    parser.add_argument("--appearance-changes", choices=APPEARANCE_CHANGES, default="none",
                        help="train: each training image its own exposure and white balance (seeded), the others "
                             "neutral; all: every image (default none); ground truth for appearance=embedding")
    return parser


def write_scene(args: argparse.Namespace) -> str:
    """Render the scene ``args`` describe into ``args.out_dir`` (after ``nerfexp.memory.require_memory`` for
    its splits and ``check_out_dir``), with its ``MARKER``; returns a one-line summary. A real lens or
    occluders with the Blender format, which holds neither, is a NerfexpError before any work."""
    if args.format == "blender" and (args.lens != "pinhole" or args.occluders):
        given = " and ".join(flag for flag, on in (("--lens real", args.lens != "pinhole"),
                                                  ("--occluders", args.occluders)) if on)
        raise NerfexpError(f"{given} need --format nerfstudio: the Blender format holds one centred pinhole "
                           "and no masks")
    counts = dict(zip(SPLITS, (args.n_train, args.n_val, args.n_test), strict=True))
    largest = max(counts, key=counts.get)  # a split is rendered whole before it is written
    require_memory(f"--resolution {args.resolution} --n-{largest} {counts[largest]} --supersample {args.supersample}",
                   f"a split of {counts[largest]} views", scene_bytes(counts[largest], args.resolution,
                                                                      args.resolution, args.supersample))
    check_out_dir(args.out_dir)
    load = LOADERS[args.scene]
    size = args.resolution
    lens = real_lens(size, size) if args.lens == "real" else None
    with atomic_directory(args.out_dir, replace=True) as new:
        splits = ((split, load(split, n, size, size, args.supersample, lens=lens)) for split, n in counts.items())
        if args.appearance_changes != "none":
            splits = ((split, vary_appearance(views, appearance_gains(len(views), APPEARANCE_SEEDS[split]))
                       if args.appearance_changes == "all" or split == "train" else views) for split, views in splits)
        if args.occluders:  # one seed per split
            splits = ((split, occlude(views, seed)) for seed, (split, views) in enumerate(splits))
        if args.format == "nerfstudio":
            write_nerfstudio(new, splits)
        else:
            for split, views in splits:
                write_blender(new, split, views, CAMERA_ANGLE_X)
        settings = {"scene": args.scene, "resolution": args.resolution, "views": counts,
                    "supersample": args.supersample, "format": args.format, "lens": args.lens,
                    "occluders": args.occluders, "appearance_changes": args.appearance_changes,
                    "nerfexp": version("nerfexp")}
        (new / MARKER).write_text(json.dumps(settings, indent=2) + "\n")
        record(new, folder_entries(new))  # paths relative to the folder: true once it is renamed into place
    views = ", ".join(f"{n} {split}" for split, n in counts.items())
    return f"the {args.scene} scene ({views} views, {args.format} format) written to {args.out_dir}"


def main(argv: list[str] | None = None) -> None:
    """The ``nerfexp-scene`` command (``build_parser``)."""
    run_command(build_parser(), argv, write_scene)


if __name__ == "__main__":
    main()
