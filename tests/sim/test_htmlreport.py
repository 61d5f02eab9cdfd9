"""sim.htmlreport: one self-contained page (images embedded, every string escaped, no script),
checked as text and in a real headless Chromium (tests/sim/browser_helpers.py)."""

from __future__ import annotations

import io
import os

import imageio.v3 as iio
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from sim.htmlreport import (
    MAX_IMAGE_BYTES,
    REPORT_HTML,
    Bullets,
    Figure,
    Flag,
    Gallery,
    Heading,
    ReportPageError,
    Table,
    Text,
    image_size,
    render_page,
    write_page,
)
from tests.sim.browser_helpers import (
    assert_renders_cleanly,
    colour_pixels,
    console_messages,
    needs_chromium,
    outline,
    render_in_chromium,
)

MAGENTA, GREEN, BLUE = (255, 0, 255), (0, 200, 0), (0, 0, 200)


def _solid(rgb, h=60, w=90) -> np.ndarray:
    return np.broadcast_to(np.array(rgb, np.uint8), (h, w, 3)).copy()


def _gif_bytes(frames) -> bytes:
    buf = io.BytesIO()
    iio.imwrite(buf, np.stack(frames), extension=".gif", duration=100, loop=0)
    return buf.getvalue()


def _page_blocks():
    hostile = '<script>alert(1)</script> & "quoted" <img src=x onerror=alert(2)>'
    return [
        Heading("Summary"),
        Text("**Headline:** attack 60.0 % vs `benign` 10.0 %", strong=True),
        Flag("the clean arm never reached the goal (0 of 4)"),
        Text(hostile),
        Heading("Tables"),
        Table(["condition", "n", "T-ASR"], [["attack", "40", "60.0 [44.6, 73.7]"], [hostile, "0", "n/a"]], "by arm"),
        Bullets(["one", "**two**"]),
        Heading("Figures"),
        Figure.from_array(_solid(MAGENTA), "a magenta PNG"),
        Gallery([Figure(_gif_bytes([_solid(GREEN), _solid(BLUE)]), "a green-then-blue GIF")]),
    ]


def test_the_page_embeds_its_images_escapes_every_string_and_has_no_script(tmp_path):
    path = write_page(tmp_path, "Report <of> a run", _page_blocks())
    assert path == tmp_path / REPORT_HTML
    text = path.read_text()
    assert "<script" not in text and "<img src=x" not in text
    assert "&lt;script&gt;alert(1)&lt;/script&gt;" in text and "&lt;img src=x onerror=alert(2)&gt;" in text
    assert "Content-Security-Policy" in text and "default-src 'none'" in text
    assert text.count('src="data:image/png;base64,') == 1 and text.count('src="data:image/gif;base64,') == 1
    assert "http://" not in text and "https://" not in text  # nothing to fetch
    assert "<strong>Headline:</strong>" in text and "<code>benign</code>" in text
    o = outline(text)
    assert o.headings["h1"] == ["Report <of> a run"] and o.headings["h2"] == ["Summary", "Tables", "Figures"]
    assert o.tables == 1 and [i["width"] for i in o.images] == ["90", "90"]
    assert not [p for p in tmp_path.iterdir() if p.name != REPORT_HTML]  # no temporary file left


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(st.text(min_size=1, max_size=60), st.text(max_size=30))
def test_any_caller_string_comes_back_as_text_and_opens_no_tag(s, cell):
    page = render_page(s, [Heading(s), Text(s.replace("*", "").replace("`", "")), Table(["h"], [[cell]])])
    o = outline(page)
    assert o.scripts == 0 and not o.images and o.tables == 1
    assert o.headings["h1"] == [s.strip()] and o.headings["h2"] == [s.strip()]
    squeeze = lambda x: "".join(x.split())  # noqa: E731
    assert squeeze(s.replace("*", "").replace("`", "")) in squeeze(o.text) and squeeze(cell) in squeeze(o.text)


def test_images_are_refused_by_content_size_and_kind_naming_the_file(tmp_path):
    fake = tmp_path / "fake.png"
    fake.write_bytes(b"GIF88a not really")
    with pytest.raises(ReportPageError, match="fake.png: not a PNG or GIF image"):
        Figure.from_file(fake, "x")
    big = tmp_path / "big.gif"
    with open(big, "wb") as f:  # sparse: its size is refused before any byte is read
        f.truncate(MAX_IMAGE_BYTES + 1)
    with pytest.raises(ReportPageError, match=r"big.gif: \d+ bytes, above the"):
        Figure.from_file(big, "x")
    real = tmp_path / "real.png"
    iio.imwrite(real, _solid(MAGENTA, 7, 11))
    link = tmp_path / "link.png"
    os.symlink(real, link)
    with pytest.raises(ReportPageError, match="link.png: not a regular file"):
        Figure.from_file(link, "x")
    with pytest.raises(ReportPageError, match="missing.png: cannot read"):
        Figure.from_file(tmp_path / "missing.png", "x")
    assert Figure.from_file(real, "ok").kind == "png" and image_size(real.read_bytes()) == ("png", (11, 7))
    with pytest.raises(ValueError, match="uint8"):
        Figure.from_array(np.zeros((4, 4, 3), np.float32), "x")
    with pytest.raises(ValueError, match="row 0 has 1 cells, the header 2"):
        Table(["a", "b"], [["only one"]])


def test_a_page_is_swapped_in_whole_and_a_planted_link_is_replaced_not_written_through(tmp_path):
    victim = tmp_path / "victim.txt"
    victim.write_text("keep")
    out = tmp_path / "out"
    out.mkdir()
    os.symlink(victim, out / REPORT_HTML)
    write_page(out, "t", [Text("x")])
    assert victim.read_text() == "keep" and not (out / REPORT_HTML).is_symlink()
    assert "<p>x</p>" in (out / REPORT_HTML).read_text()


def test_the_console_detector_reads_chromium_log_lines():
    log = (
        '[1:1:1203/094105.931678:INFO:CONSOLE:1] "boom", source: file:///x.html (1)\n'
        "[1:2:1203/094107.065738:ERROR:dbus/bus.cc:405] Failed to connect to the bus\n"
        '[3:3:0101/000000.000001:INFO:CONSOLE(7)] "old style", source: file:///x.html (7)\n'
    )
    assert console_messages(log) == ['"boom", source: file:///x.html (1)', '"old style", source: file:///x.html (7)']


@needs_chromium
def test_chromium_renders_the_page_with_its_images_and_no_console_message(tmp_path):
    path = write_page(tmp_path / "page", "A report", _page_blocks())
    r = render_in_chromium(path, tmp_path / "chromium", 1000, 1400)
    assert_renders_cleanly(r)
    assert r.outline.headings["h2"] == ["Summary", "Tables", "Figures"] and r.outline.tables == 1
    assert "<script>alert(1)</script>" in r.outline.text  # shown as text, not run
    # Both embedded images decoded and drawn at their own size: 90 x 60 px of each colour.
    assert colour_pixels(r.screenshot, MAGENTA) >= 0.95 * 90 * 60
    # The GIF loops every 0.2 s: the screenshot catches it at either frame, drawn whole.
    gif = max(colour_pixels(r.screenshot, c, tol=8) for c in (GREEN, BLUE))
    assert gif >= 0.9 * 90 * 60


@needs_chromium
def test_the_browser_check_sees_a_console_error_and_a_blocked_load(tmp_path):
    """The control: the console scan is not blind. A script's console.error, and an image the page's
    own policy blocks, both reach the list."""
    logs = tmp_path / "logs.html"
    logs.write_text('<!DOCTYPE html><html><body><h1>x</h1><script>console.error("marker-42")</script></body></html>')
    r = render_in_chromium(logs, tmp_path / "a", 400, 300)
    assert any("marker-42" in m for m in r.console) and r.outline.scripts == 1
    blocked = render_page("t", [Text("x")]).replace("<p>x</p>", f'<img src="{(tmp_path / "nothing.png").as_uri()}">')
    (tmp_path / "blocked.html").write_text(blocked)
    r = render_in_chromium(tmp_path / "blocked.html", tmp_path / "b", 400, 300)
    assert any("Content Security Policy" in m for m in r.console)
