"""``nerfexp-scene OUT_DIR [--scene {builtin,glossy}]``: an analytic scene written as a Blender-format dataset.

``builtin`` is the built-in still life (``data/procedural.py``, ``data=procedural``); ``glossy`` a
strongly view-dependent one (``data/glossy.py``): a mirror sphere, a glossy torus and a clear-coated
checker base reflecting a procedural sky. Both use the same cameras.
"""

import argparse
from pathlib import Path

from nerfexp.arguments import command_parser, positive
from nerfexp.data.blender import write_blender
from nerfexp.data.glossy import load_glossy
from nerfexp.data.procedural import CAMERA_ANGLE_X, load_procedural

LOADERS = {"builtin": load_procedural, "glossy": load_glossy}  # --scene: the function rendering a split


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


def main(argv: list[str] | None = None) -> None:
    """The ``nerfexp-scene`` command (``build_parser``)."""
    args = build_parser().parse_args(argv)
    load = LOADERS[args.scene]
    for split, n in (("train", args.n_train), ("val", args.n_val), ("test", args.n_test)):
        views = load(split, n, args.resolution, args.resolution, args.supersample)
        write_blender(args.out_dir, split, views, CAMERA_ANGLE_X)


if __name__ == "__main__":
    main()
