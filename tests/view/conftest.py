"""The view's tests drive Debian's chromium headless through Playwright (no browser download), and record
every request the page makes."""

from __future__ import annotations

import shutil
import subprocess
import sys
from urllib.parse import urlparse

import numpy as np
import pytest

from doubles.process import popen

PRIME = [sys.executable, "-m", "humanoid_prime"]
CHROMIUM = "/usr/bin/chromium"
BROWSER_ARGS = ["--no-sandbox", "--disable-gpu", "--no-first-run", "--disable-background-networking",
                "--disable-component-update", "--disable-sync", "--disable-features=AutofillServerCommunication"]


class Page:
    """A chromium page and every URL it asked for (documents, scripts, workers, websockets)."""

    def __init__(self, context) -> None:
        self.context = context
        self.urls: list[str] = []
        context.on("request", lambda request: self.urls.append(request.url))
        self.page = context.pages[0] if context.pages else context.new_page()
        self.page.on("websocket", lambda socket: self.urls.append(socket.url))

    def hosts(self) -> set[str]:
        return {urlparse(url).hostname for url in self.urls if urlparse(url).scheme not in ("blob", "data")}


@pytest.fixture
def browser(tmp_path):
    if not shutil.which(CHROMIUM):
        pytest.fail("the view's tests need Debian's chromium; `make test` installs it")
    from playwright.sync_api import sync_playwright

    with sync_playwright() as playwright:
        context = playwright.chromium.launch_persistent_context(
            str(tmp_path / "chromium"), executable_path=CHROMIUM, headless=True, args=BROWSER_ARGS,
            viewport={"width": 1280, "height": 800})
        try:
            yield Page(context)
        finally:
            context.close()


def start(*args: str):
    """A prime command whose output announces a URL ("... http://127.0.0.1:PORT/ ..."); returns (process, url)."""
    process = popen([*PRIME, *args], stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    for line in process.stdout:
        if "http://127.0.0.1:" in line:
            url = line[line.index("http://"):].split()[0]
            return process, url
    raise AssertionError(f"prime {' '.join(args)} announced no URL (exit {process.wait()})")


def drawn(png: bytes) -> dict[str, float]:
    """How much of a canvas screenshot is robot: distinct colours, spread, and eRob-blue pixels."""
    import io

    from PIL import Image

    pixels = np.asarray(Image.open(io.BytesIO(png)).convert("RGB")).reshape(-1, 3).astype(int)
    blue = np.abs(pixels - np.array([79, 110, 148])).max(axis=1) < 40  # the eRob links, lit or shaded
    return {"colours": len(np.unique(pixels, axis=0)), "std": float(pixels.std()), "erob_pixels": int(blue.sum())}


def answering(socket: str, process, timeout: float = 120.0) -> None:
    """Wait until the prime instance ``process`` answers on its control socket."""
    import time

    from humanoid_prime.errors import PrimeError
    from humanoid_prime.runtime.socket import request

    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        assert process.poll() is None, f"the instance ended with {process.returncode}"
        try:
            if request(socket, {"op": "ping"}, timeout=0.5)["ready"]:
                return
        except PrimeError:
            pass
        time.sleep(0.1)
    raise AssertionError(f"nothing answered on {socket} within {timeout:g} s")
