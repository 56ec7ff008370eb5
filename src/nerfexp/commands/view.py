"""``nerfexp-view RUN_DIR``: a trained run in the browser, live (the viewer: ``nerfexp.products.viewer``;
``docs/viewer.md``)."""

import argparse
import ipaddress
import sys
import time
from pathlib import Path
from typing import NoReturn

from nerfexp.commands.arguments import (
    add_chunk_argument,
    add_run_arguments,
    command_parser,
    fitting,
    port,
    positive,
    say_unfinished,
)
from nerfexp.commands.console import run_command
from nerfexp.commands.signals import ending_signals
from nerfexp.extras import require
from nerfexp.manifest import check_ours
from nerfexp.memory import frame_bytes
from nerfexp.products.frames import KINDS
from nerfexp.products.trained import load_run, run_scene
from nerfexp.products.viewer import SAVE_ADVICE, Viewer, say
from nerfexp.rundir.layout import CAMERA_PATH


def remote_warning(host: str, run_dir: Path) -> str | None:
    """The warning to print where ``host`` is not a loopback address (127.0.0.0/8, ::1, localhost): the viewer
    has no password, so whoever reaches the machine drives it. None for a loopback address."""
    try:
        loopback = ipaddress.ip_address(host).is_loopback
    except ValueError:  # a name: only localhost is known to be this machine alone
        loopback = host == "localhost"
    if loopback:
        return None
    return (f"nerfexp-view: warning: serving on {host}, not this machine alone: anyone who can reach it can watch "
            f"the run, record cameras and write a camera path into {run_dir / CAMERA_PATH}, with no password "
            "(from elsewhere, forward the port over SSH instead: docs/viewer.md)")


def view_run(run: Path, overrides: list[str], host: str, port: int, chunk: int | None,
             max_width: int | None, image: str = KINDS[0]) -> NoReturn:
    """Serve the viewer of the run at ``run`` (a run directory, or a checkpoint file in one) at
    ``http://host:port`` (port 0: any free one) until SIGINT or SIGTERM, which end the process as
    ``nerfexp.commands.signals.ending_signals`` does (exit status 130 or 143)."""
    viser = require("viser", "nerfexp-view")
    run_dir, checkpoint, cfg, module, step = load_run(run, overrides, chunk)
    say_unfinished("nerfexp-view", run_dir, checkpoint, step)
    check_ours(run_dir, [CAMERA_PATH.as_posix()], "nerfexp-view", SAVE_ADVICE)  # where a saved camera path goes
    if warning := remote_warning(host, run_dir):
        print(warning, file=sys.stderr, flush=True)
    scene = run_scene(run_dir, cfg)  # its training cameras as refined, where the run refined them
    max_width = max_width or scene.views("test").width
    with ending_signals():
        server = viser.ViserServer(host=host, port=port, label=f"nerfexp-view {run_dir.name}", verbose=False)
        viewer = Viewer(server, module, scene, run_dir, max_width, image)
        try:
            say(f"nerfexp-view: {run_dir} (step {step}) at http://{host}:{server.get_port()} "
                f"(Ctrl-C to stop)")
            while True:
                time.sleep(3600)
        finally:
            viewer.close()
            server.stop()  # then run_command's ending_signals says "nerfexp-view: stopped (SIGNAL)"


def build_parser() -> argparse.ArgumentParser:
    """``nerfexp-view RUN_DIR`` (or a checkpoint file in it): the trained run in the browser, rendered live
    from the camera you move (coarse at once, finer while it rests), with its training and test cameras,
    and camera paths to save for nerfexp-render --cameras. Stops with Ctrl-C."""
    parser = command_parser("nerfexp-view", build_parser.__doc__)
    add_run_arguments(parser)
    parser.add_argument("--host", default="127.0.0.1",
                        help="address to serve on (default 127.0.0.1: this machine only; any other is warned "
                             "about, the viewer having no password; from elsewhere, forward the port over SSH: "
                             "docs/viewer.md)")
    parser.add_argument("--port", type=port, default=8080,
                        help="port to serve on (default 8080; the next free one where it is taken; 0: any free one)")
    add_chunk_argument(parser, "; a render is abandoned between chunks when the camera moves")
    parser.add_argument("--max-width", type=fitting(positive(int), lambda width: frame_bytes(width, width),
                                                    "a frame of N x N pixels"),
                        help="the finest render's width in pixels at most (default: the test views' width); "
                             "the browser's canvas sets it where narrower, and the height")
    parser.add_argument("--image", choices=KINDS, default=KINDS[0],
                        help="the image shown first (default rgb; the page's dropdown switches)")
    return parser


def main(argv: list[str] | None = None) -> None:
    """The ``nerfexp-view`` command (``build_parser``)."""
    run_command(build_parser(), argv, lambda args: view_run(args.run, args.overrides, args.host, args.port,
                                                            args.chunk, args.max_width, args.image))


if __name__ == "__main__":
    main()
