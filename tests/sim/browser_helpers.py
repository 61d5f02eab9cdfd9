"""A real headless browser for the HTML reports (sim.htmlreport): Debian's Chromium.

:func:`render_in_chromium` opens a page from its file twice, once for a screenshot and once for the
DOM after parsing (``--dump-dom``). Console messages are read from Chromium's own log on stderr
(``--enable-logging=stderr --v=0``), where each is one line with ``CONSOLE`` in its prefix
(``[pid:tid:time:INFO:CONSOLE:1] "message", source: file:///... (1)``): a script's
``console.error``, a Content-Security-Policy violation (a blocked image, font or script), a failed
load. The reports have no script, so any such line is a defect; the detector itself is checked on
pages that log (tests/sim/test_htmlreport.py), so an empty list means none, not a blind scan.

No network: the browser runs with a throw-away profile, background networking, component updates
and sync off, and every host name resolving to nothing; the pages load from ``file://`` and their
own CSP allows only ``data:`` images.
"""

from __future__ import annotations

import re
import shutil
import subprocess
from dataclasses import dataclass, field
from html.parser import HTMLParser
from pathlib import Path

import imageio.v3 as iio
import numpy as np
import pytest

CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")
needs_chromium = pytest.mark.skipif(
    CHROMIUM is None,
    reason="chromium is not installed (Debian: apt-get install -y chromium; .ci/run installs it before the tests)",
)
_CONSOLE = re.compile(r"^\[[^\]]*:CONSOLE[^\]]*\]\s*(?P<message>.*)$")
TIMEOUT_S = 120


@dataclass
class Outline:
    """What the parsed DOM holds: heading texts by level, how many images and tables, all text."""

    headings: dict[str, list[str]] = field(default_factory=lambda: {"h1": [], "h2": [], "h3": [], "h4": []})
    images: list[dict] = field(default_factory=list)
    tables: int = 0
    scripts: int = 0
    text: str = ""


class _Outliner(HTMLParser):
    def __init__(self):
        super().__init__(convert_charrefs=True)
        self.out = Outline()
        self._in: str | None = None
        self._parts: list[str] = []
        self._all: list[str] = []

    def handle_starttag(self, tag, attrs):
        if tag in self.out.headings:
            self._in, self._parts = tag, []
        elif tag == "img":
            self.out.images.append(dict(attrs))
        elif tag == "table":
            self.out.tables += 1
        elif tag == "script":
            self.out.scripts += 1

    def handle_endtag(self, tag):
        if tag == self._in:
            self.out.headings[tag].append("".join(self._parts).strip())
            self._in = None

    def handle_data(self, data):
        if self._in:
            self._parts.append(data)
        self._all.append(data)

    def close(self):
        super().close()
        self.out.text = " ".join("".join(self._all).split())


def outline(dom: str) -> Outline:
    p = _Outliner()
    p.feed(dom)
    p.close()
    return p.out


@dataclass
class Rendered:
    screenshot: np.ndarray  # (H, W, 3) uint8
    dom: str
    outline: Outline
    console: list[str]  # console messages, one per line Chromium logged


def _chromium(args: list[str], profile: Path) -> subprocess.CompletedProcess:
    cmd = [
        CHROMIUM,
        "--headless",
        "--no-sandbox",
        "--disable-gpu",
        "--no-first-run",
        "--no-default-browser-check",
        "--disable-background-networking",
        "--disable-component-update",
        "--disable-sync",
        "--disable-extensions",
        "--host-resolver-rules=MAP * ~NOTFOUND",
        f"--user-data-dir={profile}",
        "--enable-logging=stderr",
        "--v=0",
        *args,
    ]
    return subprocess.run(cmd, capture_output=True, text=True, timeout=TIMEOUT_S, check=False)


def console_messages(stderr: str) -> list[str]:
    """The console messages in Chromium's stderr log (see the module docstring)."""
    return [m["message"] for line in stderr.splitlines() if (m := _CONSOLE.match(line.strip()))]


def render_in_chromium(page: Path, work: Path, width_px: int = 1280, height_px: int = 2400) -> Rendered:
    """Screenshot (``width_px`` x ``height_px`` window) and parsed DOM of ``page``, with the console."""
    work.mkdir(parents=True, exist_ok=True)
    shot = work / "screenshot.png"
    url = Path(page).resolve().as_uri()
    a = _chromium(
        [f"--screenshot={shot}", f"--window-size={width_px},{height_px}", "--hide-scrollbars", url], work / "profile-a"
    )
    assert a.returncode == 0 and shot.is_file(), f"chromium screenshot failed ({a.returncode}): {a.stderr[-2000:]}"
    b = _chromium(["--dump-dom", url], work / "profile-b")
    assert b.returncode == 0 and "<html" in b.stdout, f"chromium --dump-dom failed ({b.returncode}): {b.stderr[-2000:]}"
    img = iio.imread(shot)[..., :3]
    return Rendered(img, b.stdout, outline(b.stdout), console_messages(a.stderr) + console_messages(b.stderr))


def colour_pixels(img: np.ndarray, rgb, tol: int = 0) -> int:
    """How many pixels of ``img (H, W, 3)`` are ``rgb`` within ``tol`` per channel."""
    return int((np.abs(img.astype(int) - np.asarray(rgb, int)) <= tol).all(-1).sum())


def assert_renders_cleanly(r: Rendered) -> None:
    """No console message, no script, and a screenshot that is not one flat colour."""
    assert r.console == [], f"console messages: {r.console}"
    assert r.outline.scripts == 0
    assert r.screenshot.ndim == 3 and r.screenshot.shape[0] > 100 and r.screenshot.shape[1] > 100
    assert r.screenshot.reshape(-1, 3).std(0).max() > 10, "the screenshot is blank"
