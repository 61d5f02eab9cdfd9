"""The one owner of the HTML report format: ``report.html``, one self-contained page a person opens.

A report is a list of blocks (:class:`Heading`, :class:`Text`, :class:`Flag`, :class:`Bullets`,
:class:`Table`, :class:`Figure`, :class:`Gallery`) that :func:`render_page` turns into one HTML
page and :func:`write_page` writes as ``<folder>/report.html``. The page needs nothing else:

* every image is embedded as a base64 ``data:`` URI (PNG or GIF only, checked by their magic bytes
  and read with their pixel size from the header; an animated GIF plays as it is);
* there is no script, and the page's Content-Security-Policy forbids any (and any fetch): it
  renders the same from a file, a mail attachment or a CI artifact, offline;
* every string the caller gives is HTML-escaped. :class:`Text` and :class:`Flag` then turn
  ``**bold**`` and `` `code` `` into ``<strong>`` and ``<code>`` (the Markdown the reports already
  write), on the escaped text, so no caller string can open a tag.

Sizes are checked before any work: an image file above :data:`MAX_IMAGE_BYTES` or a page above
:data:`MAX_PAGE_BYTES` is refused with one :class:`ReportPageError` naming the file. The page is
written to a fresh temporary file in its folder (``O_EXCL``) and renamed over ``report.html``, so a
reader never sees half a page. The attack (``attack.outputs``), the evaluation
(``trials.eval.report``) and the trial session (``trials.real.report``) write their report through
this module; their Markdown ``report.md`` stays beside it, for diffs.
"""

from __future__ import annotations

import base64
import html
import io
import re
import struct
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from sim.errors import AdvobjError
from sim.files import FileRefusedError, read_regular, write_atomic

__all__ = [
    "REPORT_HTML",
    "MAX_IMAGE_BYTES",
    "MAX_PAGE_BYTES",
    "ReportPageError",
    "Heading",
    "Text",
    "Flag",
    "Bullets",
    "Table",
    "Figure",
    "Gallery",
    "image_size",
    "render_page",
    "write_page",
]

REPORT_HTML = "report.html"
MAX_IMAGE_BYTES = 24 * 2**20  # one embedded image (a long rollout GIF is a few MB)
MAX_PAGE_BYTES = 96 * 2**20  # the whole page, base64 included
# How Figure.from_file words a refused image file (sim.files' standard words otherwise).
_IMAGE_FILE_WORDS = {
    "missing": "cannot read ({strerror})",
    "directory": "not a regular file",
    "special": "not a regular file",
    "too_large": "{size} bytes, above the {max_bytes} an embedded image may have",
    "grew": "above the {max_bytes} bytes an embedded image may have",
}

_PNG_MAGIC = b"\x89PNG\r\n\x1a\n"
_GIF_MAGICS = (b"GIF87a", b"GIF89a")


class ReportPageError(AdvobjError, ValueError):
    """An image or a page cannot go into a report: the message names the file and why."""


# ----------------------------------------------------------------------------- blocks
@dataclass(frozen=True)
class Heading:
    """A section heading; ``level`` 2 sections appear in the page's contents list."""

    text: str
    level: int = 2

    def __post_init__(self):
        if self.level not in (2, 3, 4):
            raise ValueError(f"Heading level must be 2, 3 or 4 (1 is the page title), got {self.level}")


@dataclass(frozen=True)
class Text:
    """A paragraph; ``**bold**`` and `` `code` `` are kept as emphasis and code (on escaped text)."""

    text: str
    strong: bool = False


@dataclass(frozen=True)
class Flag:
    """A paragraph a reader must not miss (a warning box): what is wrong and what it means."""

    text: str


@dataclass(frozen=True)
class Bullets:
    """A bulleted list of short lines (same inline markup as :class:`Text`)."""

    items: tuple[str, ...]

    def __init__(self, items):
        object.__setattr__(self, "items", tuple(str(i) for i in items))


@dataclass(frozen=True)
class Table:
    """A table: ``header`` (C,) and ``rows`` (R, C) of plain strings, escaped as they are."""

    header: tuple[str, ...]
    rows: tuple[tuple[str, ...], ...]
    caption: str | None = None

    def __init__(self, header, rows, caption: str | None = None):
        head = tuple(str(h) for h in header)
        body = tuple(tuple(str(c) for c in r) for r in rows)
        bad = [i for i, r in enumerate(body) if len(r) != len(head)]
        if bad:
            raise ValueError(f"Table: row {bad[0]} has {len(body[bad[0]])} cells, the header {len(head)}")
        object.__setattr__(self, "header", head)
        object.__setattr__(self, "rows", body)
        object.__setattr__(self, "caption", caption)


@dataclass(frozen=True)
class Figure:
    """An embedded PNG or GIF with its caption; ``width_px``/``height_px`` read from the header."""

    data: bytes = field(repr=False)
    caption: str
    kind: str = field(init=False)
    width_px: int = field(init=False)
    height_px: int = field(init=False)

    def __post_init__(self):
        if len(self.data) > MAX_IMAGE_BYTES:
            raise ReportPageError(
                f"{self.caption!r}: {len(self.data)} bytes, above the {MAX_IMAGE_BYTES} an embedded image may have"
            )
        kind, (w, h) = _kind_and_size(self.data, repr(self.caption))
        object.__setattr__(self, "kind", kind)
        object.__setattr__(self, "width_px", w)
        object.__setattr__(self, "height_px", h)

    @classmethod
    def from_file(cls, path: str | Path, caption: str) -> Figure:
        """A figure of an image file: a regular file (not a link) of at most :data:`MAX_IMAGE_BYTES`,
        its size checked before it is read (:func:`sim.files.read_regular`)."""
        p = Path(path)
        try:
            data = read_regular(p, MAX_IMAGE_BYTES, follow_symlinks=False)
        except FileRefusedError as err:
            raise ReportPageError(f"{p}: {err.problem(_IMAGE_FILE_WORDS)}") from None
        _kind_and_size(data, str(p))  # refused naming the file, not the caption
        return cls(data, caption)

    @classmethod
    def from_array(cls, rgb: np.ndarray, caption: str) -> Figure:
        """A PNG figure of ``rgb (H, W, 3)`` (or ``(H, W)``) uint8."""
        from PIL import Image  # lazy: CLI start-up (PIL)

        a = np.asarray(rgb)
        if a.dtype != np.uint8 or a.ndim not in (2, 3) or (a.ndim == 3 and a.shape[2] not in (3, 4)) or a.size == 0:
            raise ValueError(f"Figure.from_array: need (H, W[, 3|4]) uint8, got {a.shape} {a.dtype}")
        buf = io.BytesIO()
        Image.fromarray(a).save(buf, format="PNG")
        return cls(buf.getvalue(), caption)

    def data_uri(self) -> str:
        return f"data:image/{self.kind};base64," + base64.b64encode(self.data).decode("ascii")


@dataclass(frozen=True)
class Gallery:
    """Figures side by side (wrapping on a narrow window)."""

    figures: tuple[Figure, ...]

    def __init__(self, figures):
        object.__setattr__(self, "figures", tuple(figures))


Block = Heading | Text | Flag | Bullets | Table | Figure | Gallery


def image_size(data: bytes) -> tuple[str, tuple[int, int]]:
    """``(kind, (width_px, height_px))`` of PNG or GIF ``data`` from its header; ValueError otherwise."""
    return _kind_and_size(data, "image")


def _kind_and_size(data: bytes, what: str) -> tuple[str, tuple[int, int]]:
    if data[:8] == _PNG_MAGIC and len(data) >= 24 and data[12:16] == b"IHDR":
        w, h = struct.unpack(">II", data[16:24])
        kind = "png"
    elif data[:6] in _GIF_MAGICS and len(data) >= 10:
        w, h = struct.unpack("<HH", data[6:10])
        kind = "gif"
    else:
        raise ReportPageError(f"{what}: not a PNG or GIF image")
    if w <= 0 or h <= 0:
        raise ReportPageError(f"{what}: a {kind.upper()} of {w} x {h} px")
    return kind, (int(w), int(h))


# ----------------------------------------------------------------------------- rendering
_STRONG = re.compile(r"\*\*(.+?)\*\*")
_CODE = re.compile(r"`([^`]+)`")

_CSS = """
body { font: 15px/1.45 system-ui, -apple-system, "Segoe UI", Roboto, sans-serif; color: #1b1b1b;
  max-width: 1280px; margin: 0 auto; padding: 16px 24px 48px; background: #fff; }
h1 { font-size: 26px; margin: 8px 0 12px; }
h2 { font-size: 20px; margin: 28px 0 8px; padding-top: 8px; border-top: 1px solid #ddd; }
h3 { font-size: 17px; margin: 18px 0 6px; }
h4 { font-size: 15px; margin: 14px 0 4px; }
p { margin: 6px 0; }
p.strong { font-size: 16px; background: #eef4fb; border-left: 4px solid #2b6cb0; padding: 8px 12px; }
p.flag { background: #fff4e5; border-left: 4px solid #c05621; padding: 8px 12px; font-weight: 600; }
code { font: 13px ui-monospace, SFMono-Regular, Menlo, Consolas, monospace; background: #f3f3f3;
  padding: 0 3px; border-radius: 3px; }
nav { font-size: 14px; margin: 4px 0 12px; }
nav a { margin-right: 12px; color: #2b6cb0; }
.tablewrap { overflow-x: auto; margin: 8px 0; }
table { border-collapse: collapse; font-size: 13.5px; }
caption { caption-side: top; text-align: left; color: #444; padding: 2px 0 4px; }
th, td { border: 1px solid #ccc; padding: 3px 8px; text-align: left; vertical-align: top; }
th { background: #f2f2f2; }
tr:nth-child(even) td { background: #fafafa; }
figure { margin: 10px 0; display: inline-block; vertical-align: top; max-width: 100%; }
figure img { max-width: 100%; height: auto; border: 1px solid #ddd; }
figcaption { font-size: 13px; color: #444; max-width: 100%; }
.gallery figure { margin-right: 14px; }
"""

_CSP = "default-src 'none'; img-src data:; style-src 'unsafe-inline'; base-uri 'none'; form-action 'none'"


def _inline(text: str) -> str:
    """``text`` HTML-escaped, then ``**x**`` and `` `x` `` as strong and code."""
    s = html.escape(str(text), quote=True)
    s = _CODE.sub(r"<code>\1</code>", s)
    return _STRONG.sub(r"<strong>\1</strong>", s)


def _figure(f: Figure) -> str:
    return (
        f'<figure><img src="{f.data_uri()}" alt="{html.escape(f.caption, quote=True)}" '
        f'width="{f.width_px}" height="{f.height_px}"><figcaption>{_inline(f.caption)}</figcaption></figure>'
    )


def _block(b, anchor: str | None) -> str:
    if isinstance(b, Heading):
        ident = f' id="{anchor}"' if anchor else ""
        return f"<h{b.level}{ident}>{html.escape(b.text)}</h{b.level}>"
    if isinstance(b, Text):
        return f'<p class="strong">{_inline(b.text)}</p>' if b.strong else f"<p>{_inline(b.text)}</p>"
    if isinstance(b, Flag):
        return f'<p class="flag">{_inline(b.text)}</p>'
    if isinstance(b, Bullets):
        return "<ul>" + "".join(f"<li>{_inline(i)}</li>" for i in b.items) + "</ul>"
    if isinstance(b, Table):
        cap = f"<caption>{html.escape(b.caption)}</caption>" if b.caption else ""
        head = "".join(f"<th>{html.escape(h)}</th>" for h in b.header)
        rows = "".join("<tr>" + "".join(f"<td>{html.escape(c)}</td>" for c in r) + "</tr>" for r in b.rows)
        return f'<div class="tablewrap"><table>{cap}<thead><tr>{head}</tr></thead><tbody>{rows}</tbody></table></div>'
    if isinstance(b, Figure):
        return _figure(b)
    if isinstance(b, Gallery):
        return '<div class="gallery">' + "".join(_figure(f) for f in b.figures) + "</div>"
    raise TypeError(f"not a report block: {type(b).__name__}")


def render_page(title: str, blocks) -> str:
    """The page of ``blocks`` under ``title``: a contents line of the level-2 headings, then the
    blocks in order. Raises :class:`ReportPageError` when the page would exceed :data:`MAX_PAGE_BYTES`."""
    blocks = list(blocks)
    embedded = sum(
        len(f.data) for b in blocks for f in (b.figures if isinstance(b, Gallery) else (b,)) if isinstance(f, Figure)
    )
    if embedded * 4 // 3 > MAX_PAGE_BYTES:
        raise ReportPageError(f"{title!r}: {embedded} bytes of images, above the {MAX_PAGE_BYTES} a page may hold")
    anchors, toc, n = [], [], 0
    for b in blocks:
        if isinstance(b, Heading) and b.level == 2:
            n += 1
            anchors.append(f"s{n}")
            toc.append(f'<a href="#s{n}">{html.escape(b.text)}</a>')
        else:
            anchors.append(None)
    body = "\n".join(_block(b, a) for b, a in zip(blocks, anchors))
    nav = f"<nav>{' '.join(toc)}</nav>\n" if toc else ""
    t = html.escape(title)
    return (
        "<!DOCTYPE html>\n"
        '<html lang="en">\n<head>\n<meta charset="utf-8">\n'
        f'<meta http-equiv="Content-Security-Policy" content="{_CSP}">\n'
        '<meta name="viewport" content="width=device-width, initial-scale=1">\n'
        f"<title>{t}</title>\n<style>{_CSS}</style>\n</head>\n<body>\n<h1>{t}</h1>\n{nav}{body}\n</body>\n</html>\n"
    )


def write_page(out_dir: str | Path, title: str, blocks) -> Path:
    """Write ``out_dir/report.html`` (:func:`render_page`): a fresh temporary file in ``out_dir``
    (``O_EXCL``), renamed over the page. Returns its path."""
    out = Path(out_dir)
    text = render_page(title, blocks).encode("utf-8")
    if len(text) > MAX_PAGE_BYTES:
        raise ReportPageError(f"{out / REPORT_HTML}: {len(text)} bytes, above the {MAX_PAGE_BYTES} a page may hold")
    out.mkdir(parents=True, exist_ok=True)
    return write_atomic(out / REPORT_HTML, text)
