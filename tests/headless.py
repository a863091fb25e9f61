"""A page in headless Chromium, driven over the DevTools protocol (websockets, which viser brings), in real time:
open a file with every network address refused, then take screenshots until one shows what a test waits for.

Chromium's own ``--screenshot`` either fires at load, before WebGL has drawn, or with ``--virtual-time-budget``
sometimes never returns (seen here: about one run in three hung on the same page), so the tests wait on real
time instead.
"""

from __future__ import annotations

import base64
import itertools
import json
import re
import shutil
import subprocess
import threading
import time
from collections.abc import Callable
from pathlib import Path

CHROMIUM = next((p for p in map(shutil.which, ("chromium", "chromium-browser", "google-chrome")) if p), None)
"""The browser, where one is installed (Debian: ``apt-get install chromium``)."""

OFFLINE = ["--proxy-server=127.0.0.1:9", "--host-resolver-rules=MAP * ~NOTFOUND", "--disable-background-networking"]
"""Every address refused: a page that needs the network draws nothing."""


def screenshot_when(
    page: Path, ready: Callable[[bytes], bool], profile: Path, size=(640, 480), timeout_s: float = 90.0
) -> bytes:
    """Open ``page`` (a file) in headless Chromium, offline, and return the first PNG screenshot (two a second)
    for which ``ready(png)`` holds; the last one taken if none did within ``timeout_s``."""
    from websockets.sync.client import connect

    flags = ["--headless", "--no-sandbox", "--disable-gpu", "--enable-unsafe-swiftshader", "--use-angle=swiftshader"]
    flags += ["--no-first-run", "--disable-component-update", "--disable-sync", f"--user-data-dir={profile}"]
    flags += [f"--window-size={size[0]},{size[1]}", "--remote-debugging-port=0", "--remote-allow-origins=*"]
    browser = subprocess.Popen([CHROMIUM, *flags, *OFFLINE, "about:blank"], stderr=subprocess.PIPE, text=True)
    try:
        with connect(_devtools_url(browser), max_size=None, open_timeout=30) as ws:
            ids = itertools.count(1)

            def call(method: str, session: str | None = None, **params) -> dict:
                message = {"id": next(ids), "method": method, "params": params}
                ws.send(json.dumps(message | ({"sessionId": session} if session else {})))
                while True:
                    reply = json.loads(ws.recv(timeout=60))
                    if reply.get("id") == message["id"]:
                        return reply.get("result", {})

            target = call("Target.createTarget", url=page.as_uri())["targetId"]
            session = call("Target.attachToTarget", targetId=target, flatten=True)["sessionId"]
            png = b""
            deadline = time.monotonic() + timeout_s
            while time.monotonic() < deadline:
                time.sleep(0.5)
                png = base64.b64decode(call("Page.captureScreenshot", session).get("data", ""))
                if png and ready(png):
                    break
            return png
    finally:
        browser.kill()
        browser.wait()


def _devtools_url(browser: subprocess.Popen) -> str:
    """The browser's DevTools websocket address, from the line it prints on stderr at start; the rest of stderr
    is read by a thread, so that the browser never blocks on a full pipe."""
    assert browser.stderr is not None
    for line in browser.stderr:
        match = re.search(r"DevTools listening on (ws://\S+)", line)
        if match:
            threading.Thread(target=browser.stderr.read, daemon=True).start()
            return match.group(1)
    raise RuntimeError("Chromium printed no DevTools address")


if __name__ == "__main__":  # python tests/headless.py PAGE.html OUT.png [SECONDS]: a screenshot after SECONDS (5)
    import sys

    after = float(sys.argv[3]) if len(sys.argv) > 3 else 5.0
    start = time.monotonic()
    shot = screenshot_when(
        Path(sys.argv[1]).resolve(), lambda _: time.monotonic() - start >= after, Path(sys.argv[2] + ".profile")
    )
    Path(sys.argv[2]).write_bytes(shot)
    shutil.rmtree(sys.argv[2] + ".profile", ignore_errors=True)
    print(f"{sys.argv[2]}: taken {time.monotonic() - start:.1f} s after opening {sys.argv[1]}")
