"""A headless chromium driven over the DevTools protocol, for the editor's tests and benchmark
(software WebGL: SwiftShader through ANGLE). A test helper, not in the wheel: the tests import
it as ``browser``, ``benchmarks/bench_editor.py`` puts ``tests/`` on its path. Needs the
``chromium`` binary (``make test`` installs it) and ``websockets`` (the ``dev`` extra).

Example::

    with Chromium() as tab:
        tab.open("http://127.0.0.1:8080/?t=...")
        tab.wait("window.sdReady === true")
        print(tab.eval("sdStats.lastPoseMs"))
"""

from __future__ import annotations

import base64
import json
import shutil
import subprocess
import tempfile
import time
import urllib.request
from typing import Any

from splatdeform.errors import InputError

FLAGS = ("--headless=new", "--no-sandbox", "--disable-gpu-sandbox", "--use-angle=swiftshader",
         "--enable-unsafe-swiftshader", "--ignore-gpu-blocklist", "--no-first-run",
         "--disable-extensions", "--disable-background-timer-throttling",
         "--disable-renderer-backgrounding", "--remote-allow-origins=*")


class Chromium:
    """One headless chromium with one tab; ``with`` closes it (and its profile folder)."""

    def __init__(self, size: tuple[int, int] = (1000, 700), timeout: float = 60.0) -> None:
        exe = shutil.which("chromium") or shutil.which("chromium-browser")
        if exe is None:
            raise InputError("chromium: not found; `make test` installs it (apt chromium)")
        self.profile = tempfile.TemporaryDirectory(prefix="sd-chromium-",
                                                   ignore_cleanup_errors=True)
        self.proc = subprocess.Popen(
            [exe, *FLAGS, f"--window-size={size[0]},{size[1]}", "--remote-debugging-port=0",
             f"--user-data-dir={self.profile.name}", "about:blank"],
            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        self.timeout = timeout
        port_file = f"{self.profile.name}/DevToolsActivePort"
        end = time.monotonic() + timeout
        while True:
            try:
                port = int(open(port_file).read().split()[0])
                break
            except (OSError, ValueError, IndexError):
                if time.monotonic() > end or self.proc.poll() is not None:
                    self.close()
                    raise RuntimeError("chromium did not start its DevTools endpoint") from None
                time.sleep(0.1)
        with urllib.request.urlopen(f"http://127.0.0.1:{port}/json/list", timeout=10) as r:
            pages = [t for t in json.load(r) if t["type"] == "page"]
        from websockets.sync.client import connect

        self.ws = connect(pages[0]["webSocketDebuggerUrl"], max_size=None,
                          open_timeout=timeout)
        self._id = 0
        self.console: list[str] = []
        self.call("Runtime.enable")
        self.call("Page.enable")

    def call(self, method: str, **params: Any) -> dict[str, Any]:
        self._id += 1
        mid = self._id
        self.ws.send(json.dumps({"id": mid, "method": method, "params": params}))
        while True:
            msg = json.loads(self.ws.recv(timeout=self.timeout * 4))
            if msg.get("method") == "Runtime.consoleAPICalled":
                self.console.append(" ".join(str(a.get("value", a.get("description", "")))
                                             for a in msg["params"]["args"]))
            elif msg.get("method") == "Runtime.exceptionThrown":
                d = msg["params"]["exceptionDetails"]
                self.console.append("exception: " + str(d.get("exception", {}).get(
                    "description", d.get("text"))))
            if msg.get("id") == mid:
                if "error" in msg:
                    raise RuntimeError(f"{method}: {msg['error']}")
                return msg["result"]

    def open(self, url: str) -> None:
        self.call("Page.navigate", url=url)

    def eval(self, expression: str) -> Any:
        """Evaluate JS (promises awaited); returns its JSON value; JS errors raise."""
        r = self.call("Runtime.evaluate", expression=expression, awaitPromise=True,
                      returnByValue=True)
        if "exceptionDetails" in r:
            d = r["exceptionDetails"]
            raise RuntimeError("page: " + str(d.get("exception", {}).get("description",
                                                                          d.get("text"))))
        return r["result"].get("value")

    def wait(self, expression: str, timeout: float | None = None) -> Any:
        end = time.monotonic() + (timeout or self.timeout)
        while True:
            value = self.eval(expression)
            if value:
                return value
            if time.monotonic() > end:
                raise TimeoutError(f"page: waited for {expression}; console: "
                                   f"{self.console[-5:]}")
            time.sleep(0.1)

    def screenshot(self) -> bytes:
        """PNG bytes of the tab."""
        return base64.b64decode(self.call("Page.captureScreenshot", format="png")["data"])

    def mouse(self, kind: str, x: float, y: float, **extra: Any) -> None:
        """One DevTools mouse event (kind: mousePressed / mouseMoved / mouseReleased)."""
        self.call("Input.dispatchMouseEvent", type=kind, x=x, y=y, **extra)

    def close(self) -> None:
        ws = getattr(self, "ws", None)
        if ws is not None:
            ws.close()
        if self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(10)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
        self.profile.cleanup()

    def __enter__(self) -> Chromium:
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()
