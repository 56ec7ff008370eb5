"""A web server on 127.0.0.1 for the scene download tests, so that no test reaches another address: it serves the
files it is given by path (the query included, as Google Drive's addresses have one), honours HTTP Range requests
(``bytes=N-``) unless told not to, can cut a transfer short a given number of times, answer with a status alone, or
send a file as a web page; it records each request's path and Range header. ``local_only`` lets a test's process
connect to (and look up) 127.0.0.1 alone, ``no_network`` to nothing at all."""

import socket
from dataclasses import dataclass
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer

from tests.scoring.weights_server import running


@dataclass
class Served:
    """A file the server sends: ``data``; ``status``: another (404, 500) sends that status alone; ``ranges``: whether
    Range requests are honoured (else the whole file, 200); ``cut_at``: the byte of the file at which the connection
    closes, on the next ``cuts`` requests (its Content-Length says the whole; a request for the rest from there gets
    its headers and nothing); ``content_type``."""

    data: bytes
    status: int = 200
    ranges: bool = True
    cut_at: int = 0
    cuts: int = 0
    content_type: str = "application/zip"


class Handler(BaseHTTPRequestHandler):
    def do_GET(self):
        self.server.requests.append((self.path, self.headers.get("Range")))
        served = self.server.files.get(self.path)
        if served is None or served.status != 200:
            self.send_error(404 if served is None else served.status)
            return
        data, start = served.data, 0
        asked = self.headers.get("Range")
        if asked and served.ranges:
            start = int(asked.removeprefix("bytes=").removesuffix("-"))
            if start >= len(data):
                self.send_error(416)
                return
            self.send_response(206)
            self.send_header("Content-Range", f"bytes {start}-{len(data) - 1}/{len(data)}")
        else:
            self.send_response(200)
        self.send_header("Content-Type", served.content_type)
        self.send_header("Content-Length", str(len(data) - start))
        self.end_headers()
        end = len(data)
        if served.cuts > 0:  # cut at the same byte of the file: a transfer from there on sends nothing
            served.cuts -= 1
            end = max(start, served.cut_at)
        self.wfile.write(data[start:end])  # HTTP/1.0: the connection closes after the response, cut or whole

    def log_message(self, format, *args):  # quiet: pytest shows stderr of failing tests
        pass


class ArchiveServer(ThreadingHTTPServer):
    """``files``: path (with its query) -> ``Served``; ``requests``: (path, Range header or None), in order."""

    def __init__(self, files: dict[str, Served]):
        super().__init__(("127.0.0.1", 0), Handler)
        self.files = files
        self.requests: list[tuple[str, str | None]] = []

    @property
    def address(self) -> str:
        """The server's scheme and host, for ``data.mirror``."""
        return f"http://127.0.0.1:{self.server_port}"

    def url(self, path: str) -> str:
        return f"{self.address}{path}"


def serving(files: dict[str, Served]):
    """An ``ArchiveServer`` of ``files`` on a free port, answering from a thread until the block ends."""
    return running(ArchiveServer(files))


def refused_address() -> str:
    """The scheme and host of a port of 127.0.0.1 that was free a moment ago: a connection is refused."""
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return f"http://127.0.0.1:{probe.getsockname()[1]}"


def local_only(monkeypatch) -> list:
    """This process's sockets connect to (and look up) 127.0.0.1 alone (another address fails the test); the addresses tried,
    in order."""
    tried, connect, lookup = [], socket.socket.connect, socket.getaddrinfo

    def looked_up(host, *rest, **named):
        assert host == "127.0.0.1", f"a test looked up {host}"
        return lookup(host, *rest, **named)

    def checked(sock, address):
        tried.append(address)
        assert address[0] == "127.0.0.1", f"a test connected to {address}"
        return connect(sock, address)
    monkeypatch.setattr(socket, "getaddrinfo", looked_up)
    monkeypatch.setattr(socket.socket, "connect", checked)
    return tried


def no_network(monkeypatch) -> list:
    """This process's sockets connect nowhere (an attempt is refused, as offline), and no name is looked up (a host
    reads as 192.0.2.1, a documentation address, with no DNS query sent): the addresses tried, in order."""
    tried = []

    def unlooked(host, port, *rest, **named):
        return [(socket.AF_INET, socket.SOCK_STREAM, socket.IPPROTO_TCP, "", ("192.0.2.1", port))]

    def refused(sock, address):
        tried.append(address)
        raise ConnectionRefusedError(111, "offline (the test's no_network)")
    monkeypatch.setattr(socket, "getaddrinfo", unlooked)
    monkeypatch.setattr(socket.socket, "connect", refused)
    return tried
