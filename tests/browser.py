"""A real browser for the tests that check what a person sees: Debian's chromium, headless (``.ci/run``
installs it where it is missing). A test that needs it fails, not skips, where it is absent."""

import io
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

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
