"""``nerfexp-scene OUT_DIR``: the built-in scene written as a Blender-format dataset."""

import argparse
from pathlib import Path

from nerfexp.arguments import positive
from nerfexp.data.blender import write_blender
from nerfexp.data.procedural import CAMERA_ANGLE_X, load_procedural


def main(argv: list[str] | None = None) -> None:
    """``nerfexp-scene OUT_DIR``: render the three splits in the NeRF Blender format."""
    parser = argparse.ArgumentParser(prog="nerfexp-scene", description=main.__doc__)
    parser.add_argument("out_dir", type=Path, help="folder to write transforms_*.json and the PNGs to")
    parser.add_argument("--resolution", type=positive(int), default=100, help="image width and height")
    parser.add_argument("--n-train", type=positive(int), default=100)
    parser.add_argument("--n-val", type=positive(int), default=10)
    parser.add_argument("--n-test", type=positive(int), default=20)
    parser.add_argument("--supersample", type=positive(int), default=2, help="sub-pixel rays per side")
    args = parser.parse_args(argv)
    for split, n in (("train", args.n_train), ("val", args.n_val), ("test", args.n_test)):
        views = load_procedural(split, n, args.resolution, args.resolution, args.supersample)
        write_blender(args.out_dir, split, views, CAMERA_ANGLE_X)


if __name__ == "__main__":
    main()
