"""Files fetched over HTTP(S): a download into a partial file, continued where an earlier attempt stopped, its
size bounded and its SHA-256 taken as the bytes arrive; and every way one can fail said in a few words.

``download`` writes only into the partial file its caller names (beside where the file goes, on the same file
system); the caller moves it into place once its digest is the one expected, or removes it. Bytes already in the
partial file (an attempt that broke off, or one a killed process left) are hashed and the rest asked for with an
HTTP Range request; a server that answers with the whole file (it ignores Range), with another range, or with 416
(the partial file is not a start of its file) is read from the first byte again, the partial file emptied. A
transfer that breaks off (the connection closed, or silent for ``TIMEOUT_S``) is continued, until ``ATTEMPTS`` in a
row bring nothing more; an HTTP status, a refused connection or a failed name lookup ends the download at once.
Only ``http`` and ``https`` addresses are fetched (urllib would read ``file://`` and ``ftp://`` ones too).

A mirror (``mirrored``) stands for every source: each address's scheme and host are replaced by the mirror's, its
path put after the mirror's own, so that a site without access to the sources (or a test) serves the same files.
"""

import hashlib
import http.client
import logging
import os
import re
import socket
from pathlib import Path
from urllib.error import HTTPError, URLError
from urllib.parse import urlsplit, urlunsplit
from urllib.request import Request, urlopen

from tqdm import tqdm

from nerfexp.errors import NerfexpError

TIMEOUT_S = 15  # seconds a download waits for the server to connect or send more (pip's default --timeout)
ATTEMPTS = 5  # transfers of one download that may break off in a row with nothing more, each continued from there
BLOCK = 1 << 20  # bytes read, written and hashed at a time
SCHEMES = ("http", "https")
USER_AGENT = "nerfexp"  # some servers refuse requests that name no client
CONTENT_RANGE = re.compile(r"bytes (\d+)-(\d+)/(\d+|\*)")  # a 206 answer's range: first-last/total
RANGE_NOT_SATISFIABLE = 416
WEB_PAGE = "text/html"  # what a server sends in place of a file it will not give (a sign-in or a warning page)

log = logging.getLogger(__name__)


class DownloadFailed(NerfexpError):
    """A download that failed, or whose bytes are not those expected; the message says why in a few words
    (``failure_reason``)."""


class Restart(Exception):
    """The server will not continue the partial file (see the module's docstring): read from the first byte."""


def failure_reason(error: Exception) -> str:
    """Why a download failed, in a few words: an HTTP status, a failed name lookup (no network), a refused or
    broken connection, or the system's words for a local failure (a full disk, a folder it may not write)."""
    if isinstance(error, HTTPError):
        return f"HTTP {error.code} {error.reason}"
    if isinstance(error, URLError):
        reason = error.reason
        if isinstance(reason, socket.gaierror):
            return f"name lookup failed: {reason.strerror}"
        return (reason.strerror or str(reason)) if isinstance(reason, OSError) else str(reason)
    if isinstance(error, http.client.HTTPException):  # before OSError: RemoteDisconnected is both
        return f"the connection broke off ({type(error).__name__})"
    return (error.strerror if isinstance(error, OSError) else None) or str(error)


def is_web_address(value: object, base: bool = False) -> bool:
    """Whether ``value`` is an ``http`` or ``https`` address with a host (``base``: without a query or a
    fragment, as a mirror is given)."""
    if not isinstance(value, str) or not value.isprintable() or any(c.isspace() for c in value):
        return False
    try:
        parts = urlsplit(value)
        parts.port  # noqa: B018 -- a port that is not a number raises here
    except ValueError:
        return False
    return parts.scheme in SCHEMES and bool(parts.hostname) and not (base and (parts.query or parts.fragment))


MIRROR = ("an http(s)://HOST[:PORT][/PATH] address without a query", lambda v: is_web_address(v, base=True))


def mirrored(url: str, mirror: str | None) -> str:
    """``url`` with its scheme and host (and port) replaced by ``mirror``'s and its path put after the mirror's
    own (None: ``url`` itself).

    >>> mirrored("https://storage.googleapis.com/gresearch/refraw360/360_v2.zip?x=1", "http://127.0.0.1:8000/m")
    'http://127.0.0.1:8000/m/gresearch/refraw360/360_v2.zip?x=1'
    """
    if mirror is None:
        return url
    source, base = urlsplit(url), urlsplit(mirror)
    return urlunsplit((base.scheme, base.netloc, base.path.rstrip("/") + source.path, source.query, ""))


def served_total(response: http.client.HTTPResponse, start: int) -> int | None:
    """The size of the whole file ``response`` serves from byte ``start`` (None where it does not say); a
    ``Restart`` where it serves another range, or the whole file to a request for its rest."""
    if response.status == 206:
        found = CONTENT_RANGE.fullmatch(response.headers.get("Content-Range", "").strip())
        if found is None or int(found[1]) != start:
            raise Restart
        return None if found[3] == "*" else int(found[3])
    if start:
        raise Restart
    length = response.headers.get("Content-Length", "")
    return int(length) if length.isdigit() else None


def check_total(total: int | None, size: int | None, limit: int) -> None:
    """A ``DownloadFailed`` where the server's file is ``total`` bytes (None: it does not say) and the file
    expected is ``size`` bytes (None: not known), or more than ``limit``."""
    if total is not None and size is not None and total != size:
        raise DownloadFailed(f"size mismatch: the server's file is {total:,} bytes, expected {size:,}")
    if total is not None and total > limit:
        raise DownloadFailed(f"the server's file is {total:,} bytes, more than the {limit:,} nerfexp downloads")


def partial_state(partial: Path, size: int | None) -> tuple["hashlib._Hash", int]:
    """The SHA-256 of the bytes in ``partial`` so far and their count, made empty where it is longer than
    ``size``: what a download continues from."""
    digest = hashlib.sha256()
    partial.touch()
    if size is not None and partial.stat().st_size > size:
        partial.write_bytes(b"")
    with open(partial, "rb") as file:
        for block in iter(lambda: file.read(BLOCK), b""):
            digest.update(block)
    return digest, partial.stat().st_size


def download(url: str, partial: Path, size: int | None, limit: int, label: str) -> str:
    """The file at ``url`` downloaded into ``partial`` (continuing the bytes there: the module's docstring), with a
    progress bar named ``label`` where standard error is a terminal; its SHA-256 (hexadecimal). ``size``: its bytes
    where known, else at most ``limit``. A ``DownloadFailed`` saying why (``failure_reason``, a size that is not
    ``size``, a web page served instead of the file, ``ATTEMPTS`` transfers in a row broken off with nothing more); an
    OSError of writing
    ``partial`` as it is. ``partial`` is left as it is, for the caller to move or remove."""
    if not is_web_address(url):
        raise DownloadFailed(f"not an http(s) address: {url!r}")
    digest, have = partial_state(partial, size)
    stalled, broken_at = 0, None  # transfers in a row that broke off with nothing more, and where the last did
    with open(partial, "ab") as file, tqdm(total=size, initial=have, unit="B", unit_scale=True, unit_divisor=1024,
                                           desc=label, disable=None) as bar:
        while True:
            headers = {"User-Agent": USER_AGENT, **({"Range": f"bytes={have}-"} if have else {})}
            try:
                with urlopen(Request(url, headers=headers), timeout=TIMEOUT_S) as response:
                    total = served_total(response, have)
                    check_total(total, size, limit)
                    if response.headers.get_content_type() == WEB_PAGE:
                        raise DownloadFailed("the server sent a web page (text/html), not the file")
                    for block in iter(lambda: response.read(BLOCK), b""):
                        if have + len(block) > (limit if size is None else size):
                            raise DownloadFailed(f"size mismatch: more than the {size or limit:,} bytes expected")
                        file.write(block)
                        digest.update(block)
                        have += len(block)
                        bar.update(len(block))
                    if total is not None and have < total:  # urllib ends a body cut short without an error
                        raise http.client.IncompleteRead(b"", total - have)
                break
            except (Restart, HTTPError) as error:
                if not have or (isinstance(error, HTTPError) and error.code != RANGE_NOT_SATISFIABLE):
                    raise DownloadFailed(failure_reason(error)) from None
                log.info("%s: the server does not continue the %d bytes downloaded: from the start again", url, have)
                file.truncate(0)
                digest, have = hashlib.sha256(), 0
                bar.reset(total=size)
            except URLError as error:  # no connection: no network, a refused one, a failed name lookup
                raise DownloadFailed(failure_reason(error)) from None
            except (http.client.HTTPException, ConnectionError, TimeoutError) as error:  # broke off mid-transfer
                stalled = stalled + 1 if have == broken_at else 1
                broken_at = have
                if stalled == ATTEMPTS:
                    raise DownloadFailed(f"the transfer broke off {ATTEMPTS} times in a row at byte {have:,} "
                                         f"({failure_reason(error)})") from None
                log.warning("%s: the transfer broke off at byte %d (%s): continuing from there", url, have,
                            failure_reason(error))
        file.flush()
        os.fsync(file.fileno())  # on the disk before the caller renames it into place
    if size is not None and have != size:
        raise DownloadFailed(f"size mismatch: {have:,} bytes, expected {size:,}")
    return digest.hexdigest()
