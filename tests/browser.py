"""A real browser for the tests that check what a person sees: Debian's chromium, headless (``.ci/run``
installs it where it is missing). A test that needs it fails, not skips, where it is absent."""

import base64
import io
import json
import shutil
import subprocess
import time
import urllib.request
from pathlib import Path

import numpy as np
import pytest
from PIL import Image
from websockets.sync.client import connect

NAMES = ("chromium", "chromium-browser", "google-chrome")
FLAGS = ("--headless", "--no-sandbox", "--disable-gpu", "--hide-scrollbars", "--no-first-run",
         "--disable-background-networking", "--disable-extensions", "--mute-audio")


def chromium() -> str:
    """The path of the chromium executable; the test fails, saying how to install it, where there is none."""
    for name in NAMES:
        if path := shutil.which(name):
            return path
    pytest.fail("no chromium on PATH: this test renders a page in a real headless browser; "
                "install it with `apt-get install chromium` (.ci/run does)")


def screenshot(url: str, out: Path, width: int, height: int, budget_ms: int = 2000,
               timeout_s: float = 120) -> np.ndarray:
    """Load ``url`` in headless chromium in a window ``width`` x ``height`` (CSS pixels, scale 1), wait
    ``budget_ms`` of the page's virtual time (chromium advances it as fast as loading allows), save the
    screenshot to ``out`` and return it: [height, width, 3] uint8."""
    profile = out.with_suffix(".profile")  # a fresh profile: nothing cached from another page
    command = [chromium(), *FLAGS, f"--user-data-dir={profile}", f"--window-size={width},{height}",
               "--force-device-scale-factor=1", f"--virtual-time-budget={budget_ms}", f"--screenshot={out}", url]
    result = subprocess.run(command, capture_output=True, text=True, timeout=timeout_s)
    assert result.returncode == 0 and out.exists(), result.stderr[-2000:]
    return np.asarray(Image.open(io.BytesIO(out.read_bytes())).convert("RGB"))


def open_page(url: str, profile: Path, width: int, height: int) -> subprocess.Popen:
    """Headless chromium showing ``url`` in real time (no virtual time: a page that talks over a websocket
    keeps talking) in a window ``width`` x ``height``, until the caller ends it (``close_page``)."""
    command = [chromium(), *FLAGS, f"--user-data-dir={profile}", f"--window-size={width},{height}",
               "--force-device-scale-factor=1", "--remote-debugging-port=0", url]
    return subprocess.Popen(command, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)


def close_page(browser: subprocess.Popen, timeout_s: float = 10) -> None:
    """End a browser ``open_page`` started: SIGTERM, then SIGKILL where it is still there after ``timeout_s``."""
    browser.terminate()
    try:
        browser.wait(timeout_s)
    except subprocess.TimeoutExpired:
        browser.kill()
        browser.wait()


def page_screenshot(profile: Path, timeout_s: float = 30) -> np.ndarray:
    """A screenshot [H, W, 3] (uint8) of the page a browser ``open_page`` started with ``profile`` shows
    now, taken over the DevTools protocol (``Page.captureScreenshot``) at the port chromium wrote to the
    profile's ``DevToolsActivePort``."""
    deadline = time.monotonic() + timeout_s
    port_file = profile / "DevToolsActivePort"
    while not port_file.is_file() or not port_file.read_text().strip():
        assert time.monotonic() < deadline, f"chromium wrote no {port_file}"
        time.sleep(0.1)
    port = int(port_file.read_text().split()[0])
    with urllib.request.urlopen(f"http://127.0.0.1:{port}/json/list", timeout=timeout_s) as response:
        pages = [target for target in json.load(response) if target["type"] == "page"]
    with connect(pages[0]["webSocketDebuggerUrl"], open_timeout=timeout_s, max_size=None) as socket:
        socket.send(json.dumps({"id": 1, "method": "Page.captureScreenshot", "params": {"format": "png"}}))
        while (reply := json.loads(socket.recv(timeout=timeout_s))).get("id") != 1:
            pass  # an event, not the reply
    return np.asarray(Image.open(io.BytesIO(base64.b64decode(reply["result"]["data"]))).convert("RGB"))
