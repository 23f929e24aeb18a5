"""Headless Chromium driven over the DevTools protocol on a pipe (``--remote-debugging-pipe``: no port,
no websocket library): a page opened under device emulation and a script's value read from it."""

from __future__ import annotations

import fcntl
import json
import os
import select
import shutil
import subprocess
import time
from pathlib import Path


def chromium() -> str | None:
    return shutil.which("chromium") or shutil.which("chromium-browser")


class _Pipe:
    """DevTools messages, each JSON ended by a NUL, to Chromium's fd 3 and from its fd 4."""

    def __init__(self, write_fd: int, read_fd: int, timeout_s: float):
        self.write_fd, self.read_fd, self.timeout_s = write_fd, read_fd, timeout_s
        self.buffer, self.last_id = b"", 0

    def call(self, method: str, params: dict | None = None, session: str | None = None) -> dict:
        self.last_id += 1
        message = {"id": self.last_id, "method": method, "params": params or {}}
        if session:
            message["sessionId"] = session
        os.write(self.write_fd, json.dumps(message).encode() + b"\0")
        deadline = time.monotonic() + self.timeout_s
        while True:
            while b"\0" not in self.buffer:
                left = deadline - time.monotonic()
                if left <= 0 or not select.select([self.read_fd], [], [], left)[0]:
                    raise TimeoutError(f"chromium did not answer {method}")
                chunk = os.read(self.read_fd, 1 << 16)
                if not chunk:
                    raise RuntimeError(f"chromium closed its pipe during {method}")
                self.buffer += chunk
            raw, self.buffer = self.buffer.split(b"\0", 1)
            reply = json.loads(raw)
            if reply.get("id") == self.last_id:
                if "error" in reply:
                    raise RuntimeError(f"{method}: {reply['error']}")
                return reply["result"]


def _above_4(fd: int) -> int:
    high = fcntl.fcntl(fd, fcntl.F_DUPFD, 10)
    os.close(fd)
    return high


def evaluate_emulated(page: Path, script: str, profile_dir: Path, width: int, height: int, mobile: bool,
                      scale: float = 3.0, timeout_s: float = 60.0):
    """The value of ``script`` (a JavaScript expression) in ``page`` once it has loaded, in a tab that
    emulates a screen ``width`` x ``height`` CSS pixels (``mobile``: a phone's, where the page's viewport
    meta tag decides the layout width, else 980 px, as on a phone)."""
    to_chromium, ours_w = os.pipe()
    ours_r, from_chromium = os.pipe()
    # the child's ends above 4 first, so that moving them to 3 and 4 overwrites neither
    to_chromium, from_chromium = (_above_4(fd) for fd in (to_chromium, from_chromium))

    def fds_3_and_4() -> None:
        os.dup2(to_chromium, 3)
        os.dup2(from_chromium, 4)
    proc = subprocess.Popen(
        [chromium(), "--headless", "--no-sandbox", "--disable-gpu", "--no-first-run", "--disable-sync",
         "--disable-background-networking", "--disable-component-update", f"--user-data-dir={profile_dir}",
         "--remote-debugging-pipe", "about:blank"],
        pass_fds=(3, 4), preexec_fn=fds_3_and_4, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    os.close(to_chromium)
    os.close(from_chromium)
    pipe = _Pipe(ours_w, ours_r, timeout_s)
    try:
        target = pipe.call("Target.createTarget", {"url": "about:blank"})["targetId"]
        tab = pipe.call("Target.attachToTarget", {"targetId": target, "flatten": True})["sessionId"]
        pipe.call("Emulation.setDeviceMetricsOverride", {"width": width, "height": height,
                                                         "deviceScaleFactor": scale, "mobile": mobile}, tab)
        pipe.call("Page.navigate", {"url": page.resolve().as_uri()}, tab)
        deadline = time.monotonic() + timeout_s
        while pipe.call("Runtime.evaluate", {"expression": "document.readyState", "returnByValue": True},
                        tab)["result"]["value"] != "complete":
            assert time.monotonic() < deadline, f"{page} did not finish loading"
            time.sleep(0.1)
        result = pipe.call("Runtime.evaluate", {"expression": script, "returnByValue": True}, tab)
        assert "exceptionDetails" not in result, result["exceptionDetails"]
        return result["result"]["value"]
    finally:
        try:
            pipe.call("Browser.close")
        except (RuntimeError, TimeoutError, OSError):
            proc.kill()
        proc.wait(timeout=30)
        os.close(ours_w)
        os.close(ours_r)
