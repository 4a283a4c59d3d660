"""A headless Chromium driven over the DevTools protocol, for tests of browser views (Debian's ``chromium``).

:func:`find_chromium` is None where no browser is installed (the tests then skip). :class:`Chromium` opens a page
and takes screenshots as RGB arrays; every wait is on an event (a file appearing, a reply, a pixel condition)
bounded by a generous deadline, never a fixed sleep."""

from __future__ import annotations

import base64
import io
import itertools
import json
import shutil
import subprocess
import tempfile
import time
import urllib.request
from pathlib import Path

import numpy as np

DEADLINE_S = 60.0


def find_chromium() -> str | None:
    return next((p for p in map(shutil.which, ("chromium", "chromium-browser", "google-chrome")) if p), None)


def wait_for(condition, what: str, deadline_s: float = DEADLINE_S, pause_s: float = 0.05):
    """Poll ``condition()`` until it returns something truthy (returned), or fail naming ``what``."""
    end = time.monotonic() + deadline_s
    while True:
        value = condition()
        if value:
            return value
        if time.monotonic() > end:
            raise TimeoutError(f"{what}: not within {deadline_s:g} s")
        time.sleep(pause_s)


class Chromium:
    """``with Chromium() as browser: browser.open(url); image = browser.screenshot()``."""

    def __init__(self, width: int = 900, height: int = 700):
        self.width, self.height = width, height
        self._ids = itertools.count(1)

    def __enter__(self) -> Chromium:
        self.profile = Path(tempfile.mkdtemp(prefix="ivc-chromium-"))
        self.process = subprocess.Popen(
            [find_chromium(), "--headless=new", "--no-sandbox", "--no-first-run", "--no-default-browser-check",
             "--use-angle=swiftshader", "--enable-unsafe-swiftshader", "--ignore-gpu-blocklist",
             f"--window-size={self.width},{self.height}", "--remote-debugging-port=0",
             f"--user-data-dir={self.profile}", "about:blank"],
            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        active = self.profile / "DevToolsActivePort"
        self.port = wait_for(lambda: active.exists() and active.read_text().split("\n")[0].strip(),
                             "Chromium's DevTools")
        self.socket = None
        return self

    def call(self, method: str, **params) -> dict:
        ident = next(self._ids)
        self.socket.send(json.dumps({"id": ident, "method": method, "params": params}))
        while True:
            message = json.loads(self.socket.recv(timeout=DEADLINE_S))
            if message.get("id") == ident:
                if "error" in message:
                    raise RuntimeError(f"{method}: {message['error']}")
                return message.get("result", {})

    def open(self, url: str) -> None:
        """A new tab showing ``url``, driven from now on."""
        from websockets.sync.client import connect

        request = urllib.request.Request(f"http://127.0.0.1:{self.port}/json/new?{url}", method="PUT")
        page = json.load(urllib.request.urlopen(request, timeout=DEADLINE_S))
        if self.socket is not None:
            self.socket.close()
        self.socket = connect(page["webSocketDebuggerUrl"], max_size=2**26)

    def screenshot(self) -> np.ndarray:
        """The page as an (H, W, 3) uint8 RGB array."""
        from PIL import Image

        data = base64.b64decode(self.call("Page.captureScreenshot", format="png")["data"])
        return np.asarray(Image.open(io.BytesIO(data)).convert("RGB"))

    def __exit__(self, *exc) -> None:
        try:
            if self.socket is not None:
                self.socket.close()
        finally:
            self.process.terminate()
            try:
                self.process.wait(timeout=DEADLINE_S)
            except subprocess.TimeoutExpired:
                self.process.kill()
            shutil.rmtree(self.profile, ignore_errors=True)
