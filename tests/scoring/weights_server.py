"""A web server on 127.0.0.1 for the LPIPS download tests, so that no test reaches the internet: it serves
the files it is given by name (``serving``), a body cut short (``Cut``), 404 for any other name, and
records the names asked for; ``refused_url`` is an address where nothing listens, ``silent`` one where nothing
answers."""

import hashlib
import socket
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer


@dataclass
class Cut:
    """A body sent cut short: its Content-Length says all of ``data``, ``sent`` bytes of it go out, and the
    connection closes."""

    data: bytes
    sent: int


def hashed_name(stem: str, data: bytes, ext: str = ".pth") -> str:
    """``data``'s file name as torch hub names a checked file: ``stem-<first 8 hex digits of its SHA-256>ext``."""
    return f"{stem}-{hashlib.sha256(data).hexdigest()[:8]}{ext}"


def misnamed(stem: str, data: bytes, ext: str = ".pth") -> str:
    """A name of ``hashed_name``'s form whose hex digits are not those of ``data``'s SHA-256 (its first one
    changed)."""
    digits = hashlib.sha256(data).hexdigest()[:8]
    return f"{stem}-{(int(digits[0], 16) + 1) % 16:x}{digits[1:]}{ext}"


class Handler(BaseHTTPRequestHandler):
    def do_GET(self):
        name = self.path.rsplit("/", 1)[-1]
        self.server.requests.append(name)
        body = self.server.files.get(name)
        if body is None:
            self.send_error(404)
            return
        data, sent = (body.data, body.sent) if isinstance(body, Cut) else (body, len(body))
        self.send_response(200)
        self.send_header("Content-Type", "application/octet-stream")
        self.send_header("Content-Length", str(len(data)))
        self.end_headers()
        self.wfile.write(data[:sent])  # HTTP/1.0: the connection closes after the response

    def log_message(self, format, *args):  # quiet: pytest shows stderr of failing tests
        pass


class WeightsServer(ThreadingHTTPServer):
    """``files``: name -> body (bytes, or a ``Cut``); ``requests``: the names asked for, in order."""

    def __init__(self, files: dict[str, bytes | Cut]):
        super().__init__(("127.0.0.1", 0), Handler)
        self.files = files
        self.requests: list[str] = []

    def url(self, name: str) -> str:
        return f"http://127.0.0.1:{self.server_port}/models/{name}"


@contextmanager
def running(server: ThreadingHTTPServer) -> Iterator[ThreadingHTTPServer]:
    """``server`` answering from a thread until the block ends, then shut down and closed."""
    thread = threading.Thread(target=server.serve_forever, kwargs={"poll_interval": 0.01}, daemon=True)
    thread.start()
    try:
        yield server
    finally:
        server.shutdown()
        server.server_close()
        thread.join()


def serving(files: dict[str, bytes | Cut]):
    """A ``WeightsServer`` of ``files`` on a free port, answering from a thread until the block ends."""
    return running(WeightsServer(files))


def refused_url(name: str) -> str:
    """An address for ``name`` on a port of 127.0.0.1 that was free a moment ago: a connection is refused."""
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        port = probe.getsockname()[1]
    return f"http://127.0.0.1:{port}/models/{name}"


@contextmanager
def silent() -> Iterator[str]:
    """A port of 127.0.0.1 that takes connections (the kernel completes them) and never answers, as a server that
    hangs: the address of its folder ``http://127.0.0.1:PORT/models``, until the block ends."""
    with socket.socket() as listener:
        listener.bind(("127.0.0.1", 0))
        listener.listen(8)
        yield f"http://127.0.0.1:{listener.getsockname()[1]}/models"
