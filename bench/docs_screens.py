"""Screenshots of the documentation site in headless Chromium: its home page, a tutorial and a report page.

    .venv/bin/python bench/docs_screens.py [--site DIR] [--report lab/report/index.html] [--out DIR]

Builds the site (``mkdocs build --strict``) unless ``--site`` names a built one, loads each page, prints what
each page logged as an error (console errors, uncaught exceptions, failed loads) and saves the PNGs in a
folder it prints (under /tmp unless ``--out``). Chromium is driven over its DevTools protocol on a pipe
(``--remote-debugging-pipe``): the page's console is observed, not guessed from a log. tests/test_docs.py
uses :class:`Browser` too.
"""

from __future__ import annotations

import argparse
import base64
import fcntl
import json
import os
import queue
import shutil
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
CHROMIUM_FLAGS = (
    "--headless", "--no-sandbox", "--disable-gpu", "--disable-background-networking",
    "--disable-component-update", "--disable-sync", "--no-first-run", "--hide-scrollbars",
)  # fmt: skip
HOME, TUTORIAL = "index.html", "tutorials/twin-end-to-end.html"


class BrowserError(RuntimeError):
    """Chromium did not answer as the DevTools protocol says."""


class Browser:
    """One headless Chromium, one tab, spoken to in DevTools protocol messages (JSON, NUL-terminated) on
    file descriptors 3 (to it) and 4 (from it)."""

    def __init__(self, chromium: str, profile: Path, width: int = 1280, height: int = 900) -> None:
        # every end above 4, so that putting Chromium's two ends at 3 and 4 never overwrites another
        to_read, self._to, self._from, from_write = (_high(fd) for fd in (*os.pipe(), *os.pipe()))

        def fds() -> None:
            os.dup2(to_read, 3)
            os.dup2(from_write, 4)

        args = [chromium, *CHROMIUM_FLAGS, f"--user-data-dir={profile}", "--remote-debugging-pipe"]
        self.proc = subprocess.Popen(args, preexec_fn=fds, close_fds=False, stdout=subprocess.DEVNULL,
                                     stderr=subprocess.DEVNULL)  # fmt: skip
        os.close(to_read)
        os.close(from_write)
        self._messages: queue.Queue[dict] = queue.Queue()
        threading.Thread(target=self._read, daemon=True).start()
        self._id = 0
        target = self.call("Target.createTarget", url="about:blank")["targetId"]
        self.session = self.call("Target.attachToTarget", targetId=target, flatten=True)["sessionId"]
        for domain in ("Page", "Runtime", "Log"):
            self.call(f"{domain}.enable", session=True)
        self.call("Emulation.setDeviceMetricsOverride", session=True, width=width, height=height,
                  deviceScaleFactor=1, mobile=False)  # fmt: skip
        self.events: list[dict] = []

    def _read(self) -> None:
        buffer = b""
        while chunk := os.read(self._from, 1 << 16):
            buffer += chunk
            *whole, buffer = buffer.split(b"\0")
            for raw in whole:
                self._messages.put(json.loads(raw))

    def _next(self, deadline: float) -> dict | None:
        try:
            return self._messages.get(timeout=max(0.0, deadline - time.monotonic()))
        except queue.Empty:
            return None

    def call(self, method: str, session: bool = False, timeout_s: float = 30.0, **params) -> dict:
        """Send one command and wait for its answer (events meanwhile are kept in ``events``)."""
        self._id += 1
        message = {"id": self._id, "method": method, "params": params}
        if session:
            message["sessionId"] = self.session
        os.write(self._to, json.dumps(message).encode() + b"\0")
        deadline = time.monotonic() + timeout_s
        while (reply := self._next(deadline)) is not None:
            if reply.get("id") == self._id:
                if "error" in reply:
                    raise BrowserError(f"{method}: {reply['error']}")
                return reply.get("result", {})
            getattr(self, "events", []).append(reply)
        raise BrowserError(f"{method}: no answer in {timeout_s} s")

    def load(self, url: str, settle_s: float = 1.0, timeout_s: float = 30.0) -> list[str]:
        """Open ``url``, wait for its load event and ``settle_s`` more; every error it logged meanwhile."""
        self.events = []
        self.call("Page.navigate", session=True, url=url)
        deadline = time.monotonic() + timeout_s
        while not any(e.get("method") == "Page.loadEventFired" for e in self.events):
            if (event := self._next(deadline)) is None:
                raise BrowserError(f"{url}: not loaded in {timeout_s} s")
            self.events.append(event)
        settle = time.monotonic() + settle_s
        while (event := self._next(settle)) is not None:
            self.events.append(event)
        return errors(self.events)

    def screenshot(self, path: Path) -> Path:
        """The page as it is shown now (its full height), as a PNG."""
        tall = "document.documentElement.scrollHeight"
        height = self.call("Runtime.evaluate", session=True, expression=tall,
                           returnByValue=True)["result"]["value"]  # fmt: skip
        clip = {"x": 0, "y": 0, "width": 1280, "height": min(int(height), 4000), "scale": 1}
        data = self.call("Page.captureScreenshot", session=True, format="png", clip=clip,
                         captureBeyondViewport=True)["data"]  # fmt: skip
        path.write_bytes(base64.b64decode(data))
        return path

    def close(self) -> None:
        try:
            self.call("Browser.close", timeout_s=5)
        except (BrowserError, OSError):
            pass
        finally:
            try:
                self.proc.wait(timeout=10)
            except subprocess.TimeoutExpired:
                self.proc.kill()
            os.close(self._to)

    def __enter__(self) -> Browser:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def _high(fd: int) -> int:
    """``fd`` moved to a number above 9 (not inherited)."""
    moved = fcntl.fcntl(fd, fcntl.F_DUPFD_CLOEXEC, 10)
    os.close(fd)
    return moved


def errors(events: list[dict]) -> list[str]:
    """The errors among DevTools events: console.error/assert, uncaught exceptions, log entries at error level
    (a resource that failed to load, a blocked request)."""
    out = []
    for event in events:
        method, params = event.get("method"), event.get("params", {})
        if method == "Runtime.consoleAPICalled" and params.get("type") in ("error", "assert"):
            out.append(
                "console.error: "
                + " ".join(str(a.get("value", a.get("description"))) for a in params["args"])
            )
        elif method == "Runtime.exceptionThrown":
            details = params["exceptionDetails"]
            out.append(
                "exception: " + details.get("exception", {}).get("description", details.get("text", ""))
            )
        elif method == "Log.entryAdded" and params["entry"].get("level") == "error":
            entry = params["entry"]
            out.append(f"log: {entry.get('text')} {entry.get('url', '')}".strip())
    return out


def build_site(out: Path) -> Path:
    """``mkdocs build --strict`` into ``out``."""
    mkdocs = Path(sys.executable).parent / "mkdocs"
    subprocess.run(
        [str(mkdocs), "build", "--strict", "--quiet", "--site-dir", str(out)], cwd=ROOT, check=True
    )
    return out


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--site", type=Path, help="a built site (default: build one)")
    parser.add_argument("--report", type=Path, help="a report page (lab/report/index.html)")
    parser.add_argument("--out", type=Path, help="where the PNGs go (default: a new folder under /tmp)")
    parser.add_argument("--chromium", default=shutil.which("chromium") or "/usr/bin/chromium")
    args = parser.parse_args()
    out = args.out or Path(tempfile.mkdtemp(prefix="vslab-docs-screens-"))
    out.mkdir(parents=True, exist_ok=True)
    site = args.site or build_site(out / "site")
    pages = {"home": site / HOME, "tutorial": site / TUTORIAL}
    if args.report:
        pages["report"] = args.report
    failed = False
    with tempfile.TemporaryDirectory() as profile, Browser(args.chromium, Path(profile)) as browser:
        for name, page in pages.items():
            found = browser.load(page.resolve().as_uri())
            png = browser.screenshot(out / f"{name}.png")
            print(f"{png}  {'errors: ' + '; '.join(found) if found else 'no console errors'}")
            failed |= bool(found)
    print(f"screenshots in {out}")
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
