"""``nerfexp-data list [--catalog FILE]`` and ``nerfexp-data fetch NAME [--catalog FILE] [--mirror URL]``: the scenes
nerfexp knows by name (``data.scene=NAME``: its own catalogue and yours), which are in the cache, and one fetched
into it now.

``list`` prints a line per scene: its name, the data group it is read with, whether it is in the cache, the archive's
SHA-256 and how it is known (pinned by the catalogue, or recorded on the first download, with the digest once
recorded), and its source's host. ``fetch`` downloads, verifies and unpacks a scene as training does
(``nerfexp.data.scene_cache``), or finds it there, and prints its folder. The cache is ``$NERFEXP_DATA``, else
``~/.cache/nerfexp/data``.
"""

import argparse
import logging
from urllib.parse import urlsplit

from nerfexp.commands.arguments import command_parser
from nerfexp.commands.console import run_command
from nerfexp.data.catalog import catalog_entries, find_entry
from nerfexp.data.scene_cache import (
    PINNED,
    RECORDED,
    data_cache,
    expected_checksum,
    fetch_scene,
    scene_folder,
    scene_record,
)
from nerfexp.downloads import MIRROR
from nerfexp.errors import ConfigError

PROG = "nerfexp-data"


def checksum_text(digest: str | None, how: str) -> str:
    """How an archive's SHA-256 is known, in a few words: ``pinned f01fd1b4...``, ``recorded 3a2b...`` or ``recorded
    on first download (none yet)``."""
    if digest is None:
        return f"{RECORDED} (none yet)"
    return f"{PINNED if how.startswith(PINNED) else 'recorded'} {digest}"


def listing(catalog: str | None) -> str:
    """``list``'s lines: a header naming the cache, then a line per scene of nerfexp's catalogue and ``catalog``."""
    cache = data_cache()
    rows = [("NAME", "FORMAT", "CACHED", "SHA-256", "SOURCE")]
    for entry in catalog_entries(catalog).values():
        digest, _, how = expected_checksum(cache, entry)
        needs = " ".join(f"data.{key}={value}" for key, value in entry.needs)
        rows.append((entry.name, f"data={entry.format}" + (f" {needs}" if needs else ""),
                     "yes" if scene_record(cache, entry) is not None else "no", checksum_text(digest, how),
                     urlsplit(entry.urls[0]).hostname))
    widths = [max(len(row[column]) for row in rows) for column in range(len(rows[0]) - 1)]
    lines = ["  ".join(cell.ljust(width) for cell, width in zip(row, widths)) + "  " + row[-1] for row in rows]
    return "\n".join([f"scenes by name (data.scene=NAME); the cache: {cache}", *lines])


def fetched(name: str, catalog: str | None, mirror: str | None) -> str:
    """``fetch``'s line: the scene ``name`` in the cache (``fetch_scene``), its folder and its archive's digest."""
    if mirror is not None and not MIRROR[1](mirror):
        raise ConfigError(f"--mirror {mirror}: expected {MIRROR[0]}")
    entry = find_entry(name, catalog)
    record = fetch_scene(entry, mirror)
    folder = scene_folder(data_cache(), name)
    return f"{name}: {folder} (data={entry.format}; its archive's SHA-256 {record['sha256']}, {record['checksum']})"


def build_parser() -> argparse.ArgumentParser:
    parser = command_parser(PROG, __doc__)
    actions = parser.add_subparsers(dest="action", required=True, metavar="{list,fetch}", help="what to do")
    shown = actions.add_parser("list", help="the scenes by name, and which are in the cache")
    got = actions.add_parser("fetch", help="download, verify and unpack one scene into the cache now")
    got.add_argument("name", help="the scene's name, as nerfexp-data list shows it (e.g. blender/lego)")
    got.add_argument("--mirror", help="an http(s)://HOST[:PORT][/PATH] to download from in place of each source's "
                                      "scheme and host (data.mirror)")
    for sub in (shown, got):
        sub.add_argument("--catalog", help="a YAML file of your own scenes by name, beside nerfexp's (data.catalog)")
    return parser


def show_log_lines() -> None:
    """nerfexp's lines (a download's address, a digest recorded) on standard error, as ``nerfexp-data: LINE``."""
    handler = logging.StreamHandler()
    handler.setFormatter(logging.Formatter(f"{PROG}: %(message)s"))
    logger = logging.getLogger("nerfexp")
    logger.addHandler(handler)
    logger.setLevel(logging.INFO)


def main(argv: list[str] | None = None) -> None:
    def work(args: argparse.Namespace) -> str:
        show_log_lines()
        if args.action == "list":
            return listing(args.catalog)
        return fetched(args.name, args.catalog, args.mirror)
    run_command(build_parser(), argv, work)
