"""Self-contained HTML pages of results: headings, text, tables, images and image comparisons in one file that
opens in any browser without a network (every image a ``data:`` URI, the style and the few lines of script
inline, no fonts or scripts fetched; a Content-Security-Policy in the page forbids fetching anything else).

The builder, in use::

    page = Page("Experiment: living_room")
    page.section("Tables")                        # a heading (level 2: listed in the page's contents)
    page.text("Effective spp, **higher is better**.")  # paragraphs (blank-line separated), **bold**, `code`
    page.table([["stereo", 1.5]], header=["scheme", "spp"])
    page.image(rgb, caption="...")                # an image: array, tensor, PNG bytes or a .png file's path
    page.gallery({"stereo": err1, "temporal": err2})  # images side by side, one caption each
    page.compare({"stereo": a, "temporal": b}, reference, crops=[full_frame(a), worst_crop(error, 48)])
    page.write("runs/a/report.html")              # atomic (stereorepro.io.atomic.atomic_write)

:meth:`Page.compare` is the comparison widget: for each crop the chosen method's pixels lie over the reference's,
a slider (or dragging on the image) wipes between them, a menu picks the method; one slider and one menu drive
all crops of the comparison. Images are ``(3, H, W)``, ``(1, 3, H, W)``, ``(H, W, 3)`` or ``(H, W)`` arrays or
torch tensors: floats are linear radiance, shown clamped to [0, 1] with gamma 2.2 (:func:`tonemap`, the
experiment's figures do the same); ``uint8`` arrays are shown as they are. :func:`abs_error`, :func:`colorize`
and :func:`colorbar` make error maps, :func:`mask_image` shows a mask, :func:`downscale` box-averages a large image
to a width, :func:`png_bytes` encodes a PNG (zlib and struct: no imaging library). Nothing here imports torch or
matplotlib.

Examples:
    >>> import tempfile, pathlib
    >>> import numpy as np
    >>> from stereorepro.workflows.html_report import Page, full_frame
    >>> ref = np.linspace(0, 1, 4 * 6 * 3).reshape(4, 6, 3)
    >>> page = Page("Two methods")
    >>> page.section("Comparison")
    >>> page.compare({"noisy": ref + 0.1, "blurred": ref * 0.9}, ref, crops=[full_frame(ref)])
    >>> with tempfile.TemporaryDirectory() as d:
    ...     path = page.write(pathlib.Path(d) / "report.html")
    ...     html = path.read_text()
    >>> html.startswith("<!DOCTYPE html>"), html.count('class="top"'), "://" in html  # no URL: nothing to fetch
    (True, 2, False)
"""

from __future__ import annotations

import base64
import html
import os
import re
import struct
import zlib
from pathlib import Path
from typing import NamedTuple

import numpy as np

from ..errors import ParameterError, ParameterTypeError, ShapeError
from ..io.atomic import atomic_write

__all__ = [
    "Page",
    "Crop",
    "full_frame",
    "worst_crop",
    "tonemap",
    "abs_error",
    "colorize",
    "colorbar",
    "mask_image",
    "downscale",
    "png_bytes",
]


class Crop(NamedTuple):
    """A rectangle of an image: its label, top-left pixel ``(y, x)`` and size ``(height, width)`` in pixels.

    Examples:
        >>> from stereorepro.workflows.html_report import Crop
        >>> Crop("corner", 0, 0, 16, 16).width
        16
    """

    label: str
    y: int
    x: int
    height: int
    width: int


def full_frame(image, label: str = "full frame") -> Crop:
    """The crop covering all of ``image`` (an array or tensor in any layout :func:`tonemap` takes).

    Examples:
        >>> import numpy as np
        >>> from stereorepro.workflows.html_report import full_frame
        >>> full_frame(np.zeros((3, 4, 6)))
        Crop(label='full frame', y=0, x=0, height=4, width=6)
    """
    h, w = _hwc(image, "image").shape[:2]
    return Crop(label, 0, 0, h, w)


def worst_crop(error, size: int | tuple[int, int], label: str = "highest error") -> Crop:
    """The ``size`` window (``(height, width)``, or one number for a square) of ``error`` ``(H, W)`` whose pixels
    add up to the most error: where a comparison should zoom in. The window is clipped to the image.

    Examples:
        >>> import numpy as np
        >>> from stereorepro.workflows.html_report import worst_crop
        >>> e = np.zeros((10, 12)); e[6, 9] = 1.0
        >>> worst_crop(e, 4)
        Crop(label='highest error', y=3, x=6, height=4, width=4)

    Raises:
        ShapeError: ``error`` is not 2-D or is empty.
        ParameterError: ``size`` is not positive.
    """
    e = np.nan_to_num(np.asarray(_numpy(error), dtype=np.float64), nan=0.0, posinf=0.0, neginf=0.0)
    if e.ndim != 2 or e.size == 0:
        raise ShapeError(f"worst_crop: error must be a non-empty (H, W) array, got shape {tuple(e.shape)}")
    h, w = (size, size) if isinstance(size, (int, np.integer)) else size
    if h < 1 or w < 1:
        raise ParameterError(f"worst_crop: size must be positive, got {size}")
    h, w = min(int(h), e.shape[0]), min(int(w), e.shape[1])
    s = np.zeros((e.shape[0] + 1, e.shape[1] + 1))
    s[1:, 1:] = e.cumsum(0).cumsum(1)  # summed-area table: a window's sum from its four corners
    box = s[h:, w:] - s[:-h, w:] - s[h:, :-w] + s[:-h, :-w]
    y, x = np.unravel_index(int(np.argmax(box)), box.shape)
    return Crop(label, int(y), int(x), h, w)


def _numpy(x) -> np.ndarray:
    """A torch tensor (any device, with or without grad) or array-like as a numpy array, without importing torch."""
    if hasattr(x, "detach") and hasattr(x, "cpu"):
        x = x.detach().cpu().numpy()
    return np.asarray(x)


def _hwc(image, what: str) -> np.ndarray:
    """``image`` as an ``(H, W, C)`` array (C = 1, 3 or 4) from ``(1, C, H, W)``, ``(C, H, W)``, ``(H, W, C)`` or
    ``(H, W)``."""
    a = _numpy(image)
    if a.ndim == 4 and a.shape[0] == 1:
        a = a[0]
    if a.ndim == 3 and a.shape[0] in (1, 3, 4) and a.shape[2] not in (1, 3, 4):
        a = a.transpose(1, 2, 0)
    elif a.ndim == 2:
        a = a[:, :, None]
    if a.ndim != 3 or a.shape[2] not in (1, 3, 4) or a.shape[0] == 0 or a.shape[1] == 0:
        raise ShapeError(
            f"{what}: expected a non-empty image (1, C, H, W), (C, H, W), (H, W, C) or (H, W) with C in 1, 3, 4, "
            f"got shape {tuple(_numpy(image).shape)}"
        )
    return a


def tonemap(image, gamma: float = 2.2) -> np.ndarray:
    """An image as 8-bit RGB ``(H, W, 3)``: floats (linear radiance) clamped to [0, 1] and raised to ``1 / gamma``;
    ``uint8`` as it is; booleans white where true; one channel repeated to three; alpha dropped.

    Examples:
        >>> import numpy as np
        >>> from stereorepro.workflows.html_report import tonemap
        >>> tonemap(np.array([[0.0, 0.25, 4.0]])).tolist()
        [[[0, 0, 0], [136, 136, 136], [255, 255, 255]]]

    Raises:
        ShapeError: not an image layout (see the module's docstring).
        ParameterTypeError: a dtype other than float, bool or uint8.
    """
    a = _hwc(image, "tonemap")[:, :, :3]
    if a.dtype == np.bool_:
        a = a.astype(np.uint8) * 255
    elif np.issubdtype(a.dtype, np.floating):
        x = np.nan_to_num(np.clip(a.astype(np.float64), 0.0, 1.0), nan=0.0)
        a = np.round(255.0 * x ** (1.0 / gamma)).astype(np.uint8)
    elif a.dtype != np.uint8:
        raise ParameterTypeError(f"tonemap: expected a float, bool or uint8 image, got dtype {a.dtype}")
    return np.ascontiguousarray(np.repeat(a, 3, axis=2) if a.shape[2] == 1 else a)


def abs_error(image, reference) -> np.ndarray:
    """Per-pixel error ``(H, W)``: the mean over channels of ``|image - reference|`` (float64; NaN counts as 0).

    Examples:
        >>> import numpy as np
        >>> from stereorepro.workflows.html_report import abs_error
        >>> abs_error(np.full((3, 1, 2), 0.5), np.zeros((3, 1, 2))).tolist()
        [[0.5, 0.5]]

    Raises:
        ShapeError: the two images differ in shape.
    """
    a, b = _hwc(image, "abs_error image"), _hwc(reference, "abs_error reference")
    if a.shape != b.shape:
        raise ShapeError(f"abs_error: image {a.shape[:2]} and reference {b.shape[:2]} differ in (H, W, C)")
    d = np.abs(a.astype(np.float64) - b.astype(np.float64)).mean(axis=2)
    return np.nan_to_num(d, nan=0.0, posinf=0.0)


#: The error maps' colour ramp (an inferno-like ramp: black, purple, red, orange, light yellow), at 0, ¼, ½, ¾, 1.
_RAMP = np.array([[0, 0, 4], [87, 16, 110], [188, 55, 84], [249, 142, 9], [252, 255, 164]], dtype=np.float64)


def colorize(values, vmax: float | None = None) -> np.ndarray:
    """``values`` ``(H, W)`` (≥ 0) as 8-bit RGB ``(H, W, 3)`` on a black → purple → orange → light-yellow ramp,
    0 black and ``vmax`` (default: the 99th percentile, so that a few outliers do not darken the rest) and above
    light yellow.

    Examples:
        >>> import numpy as np
        >>> from stereorepro.workflows.html_report import colorize
        >>> colorize(np.array([[0.0, 1.0, 2.0]]), vmax=1.0).tolist()
        [[[0, 0, 4], [252, 255, 164], [252, 255, 164]]]

    Raises:
        ShapeError: ``values`` is not 2-D.
    """
    v = np.nan_to_num(np.asarray(_numpy(values), dtype=np.float64), nan=0.0)
    if v.ndim != 2:
        raise ShapeError(f"colorize: values must be (H, W), got shape {tuple(v.shape)}")
    if vmax is None:
        vmax = float(np.percentile(v, 99)) if v.size else 1.0
    t = np.clip(v / max(float(vmax), 1e-12), 0.0, 1.0) * (len(_RAMP) - 1)
    i = np.minimum(t.astype(np.int64), len(_RAMP) - 2)
    f = (t - i)[..., None]
    return np.round(_RAMP[i] * (1 - f) + _RAMP[i + 1] * f).astype(np.uint8)


def colorbar(width: int = 256, height: int = 12) -> np.ndarray:
    """The ramp of :func:`colorize` from 0 (left) to ``vmax`` (right), as an 8-bit RGB ``(height, width, 3)`` image.

    Examples:
        >>> from stereorepro.workflows.html_report import colorbar
        >>> colorbar(5, 2).shape
        (2, 5, 3)
    """
    return colorize(np.tile(np.linspace(0.0, 1.0, width), (height, 1)), vmax=1.0)


def mask_image(mask, color: tuple[int, int, int] = (255, 255, 255), background: tuple[int, int, int] = (0, 0, 0)):
    """A mask ``(H, W)`` (or ``(1, 1, H, W)``; nonzero is true) as 8-bit RGB ``(H, W, 3)``: ``color`` where true,
    ``background`` elsewhere.

    Examples:
        >>> import numpy as np
        >>> from stereorepro.workflows.html_report import mask_image
        >>> mask_image(np.array([[True, False]]), color=(255, 0, 0)).tolist()
        [[[255, 0, 0], [0, 0, 0]]]

    Raises:
        ShapeError: more than one channel.
    """
    m = _hwc(mask, "mask_image")
    if m.shape[2] != 1:
        raise ShapeError(f"mask_image: expected one channel, got {m.shape[2]}")
    on = m[:, :, 0] != 0
    return np.where(on[..., None], np.array(color, np.uint8), np.array(background, np.uint8))


def downscale(image, max_width: int) -> np.ndarray:
    """``image`` as ``(H, W, C)``, box-averaged by the smallest integer factor that makes it at most ``max_width``
    pixels wide (floats averaged as they are; ``uint8`` averaged and rounded); as it is when it fits.

    Examples:
        >>> import numpy as np
        >>> from stereorepro.workflows.html_report import downscale
        >>> downscale(np.arange(8.0).reshape(2, 4), 2)[..., 0].tolist()
        [[2.5, 4.5]]

    Raises:
        ParameterError: ``max_width`` below 1.
    """
    if max_width < 1:
        raise ParameterError(f"downscale: max_width must be >= 1, got {max_width!r}")
    a = _hwc(image, "downscale")
    return _region(a, Crop("", 0, 0, a.shape[0], a.shape[1]), int(max_width))[0]


def png_bytes(image) -> bytes:
    """An 8-bit image ``(H, W)`` (grey), ``(H, W, 3)`` (RGB) or ``(H, W, 4)`` (RGBA) encoded as a PNG file's bytes
    (every row with PNG's "up" filter, zlib level 6).

    Examples:
        >>> import numpy as np
        >>> from stereorepro.workflows.html_report import png_bytes
        >>> png = png_bytes(np.zeros((2, 3, 3), np.uint8))
        >>> png[:8], png[12:16], int.from_bytes(png[16:20], "big"), int.from_bytes(png[20:24], "big")
        (b'\\x89PNG\\r\\n\\x1a\\n', b'IHDR', 3, 2)

    Raises:
        ParameterTypeError: not ``uint8``.
        ShapeError: not one of the three layouts, or empty.
    """
    a = _numpy(image)
    if a.dtype != np.uint8:
        raise ParameterTypeError(f"png_bytes: expected a uint8 image, got dtype {a.dtype} (see tonemap)")
    kinds = {1: 0, 3: 2, 4: 6}  # channels -> PNG colour type: grey, RGB, RGBA
    c = 1 if a.ndim == 2 else (a.shape[2] if a.ndim == 3 else 0)
    if c not in kinds or a.shape[0] == 0 or a.shape[1] == 0:
        raise ShapeError(f"png_bytes: expected a non-empty (H, W), (H, W, 3) or (H, W, 4) image, got {a.shape}")
    h, w = a.shape[:2]
    rows = np.ascontiguousarray(a).reshape(h, w * c)
    up = rows.copy()
    up[1:] -= rows[:-1]  # uint8 arithmetic wraps modulo 256, as the filter is defined
    raw = np.concatenate([np.full((h, 1), 2, np.uint8), up], axis=1).tobytes()

    def chunk(tag: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + tag + data + struct.pack(">I", zlib.crc32(tag + data) & 0xFFFFFFFF)

    header = struct.pack(">IIBBBBB", w, h, 8, kinds[c], 0, 0, 0)
    return b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", header) + chunk(b"IDAT", zlib.compress(raw, 6)) + chunk(b"IEND", b"")


_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


def _data_uri(image) -> tuple[str, int, int]:
    """``(data URI, width, height)`` of an image: an array or tensor (:func:`tonemap`), PNG bytes, or the path of
    a PNG file."""
    if isinstance(image, (str, os.PathLike)):
        path = Path(image)
        try:
            image = path.read_bytes()
        except OSError as e:
            raise ParameterError(f"image {path}: cannot read it ({e.strerror or e})") from None
        if not image.startswith(_PNG_SIGNATURE):
            raise ParameterError(f"image {path}: not a PNG file")
    if isinstance(image, (bytes, bytearray)):
        png = bytes(image)
        if not png.startswith(_PNG_SIGNATURE) or len(png) < 24:
            raise ParameterError("image: bytes that are not a PNG file")
        w, h = struct.unpack(">II", png[16:24])
    else:
        rgb = tonemap(image)
        png, (h, w) = png_bytes(rgb), rgb.shape[:2]
    return "data:image/png;base64," + base64.b64encode(png).decode("ascii"), w, h


def _esc(x) -> str:
    return html.escape(str(x), quote=True)


def _inline(text: str) -> str:
    """Escaped text with ``**bold**`` and ```code``` marked up."""
    t = _esc(text)
    t = re.sub(r"\*\*(.+?)\*\*", r"<strong>\1</strong>", t)
    return re.sub(r"`([^`]+)`", r"<code>\1</code>", t)


#: Text cells that read as numbers (right-aligned like them): "1.5", "-2", "12.3 %", "1e-05", "–".
_NUMBER = re.compile(r"[-+]?(\d[\d,]*\.?\d*|\.\d+)([eE][-+]?\d+)?( ?%)?|–")


def _cell(x) -> tuple[str, bool]:
    """A table cell's text and whether it is a number (right-aligned)."""
    if x is None:
        return "–", True
    if isinstance(x, (bool, np.bool_)):
        return str(bool(x)), False
    if isinstance(x, (int, np.integer)):
        return str(int(x)), True
    if isinstance(x, (float, np.floating)):
        return f"{float(x):.4g}", True
    return str(x), bool(_NUMBER.fullmatch(str(x)))


def _region(a: np.ndarray, crop: Crop, max_width: int) -> tuple[np.ndarray, int]:
    """The crop of an ``(H, W, C)`` image, box-averaged by the smallest integer factor that fits ``max_width``
    (floats averaged as they are, before tonemapping); returns it and the factor."""
    r = a[crop.y : crop.y + crop.height, crop.x : crop.x + crop.width]
    f = max(1, -(-r.shape[1] // max_width))
    if f == 1:
        return r, 1
    h, w = r.shape[0] // f * f, r.shape[1] // f * f
    if h == 0:
        return r[:, ::f], f
    m = r[:h, :w].astype(np.float64).reshape(h // f, f, w // f, f, -1).mean(axis=(1, 3))
    return (np.round(m).astype(np.uint8) if r.dtype == np.uint8 else m), f


_STYLE = """
body{font-family:system-ui,-apple-system,"Segoe UI",sans-serif;margin:1.5em auto;max-width:1200px;padding:0 1em;
color:#222;background:#fff;line-height:1.45}
h1{font-size:1.6em}h2{font-size:1.3em;border-bottom:1px solid #ddd;padding-bottom:.2em;margin-top:1.8em}
h3{font-size:1.1em}code{background:#f2f2f2;padding:0 .25em;border-radius:3px}
nav{font-size:.92em}nav a{margin-right:1em}
table{border-collapse:collapse;margin:.6em 0;font-size:.92em}
th,td{border:1px solid #ccc;padding:.2em .6em}th{background:#f4f4f4}td.n{text-align:right;
font-variant-numeric:tabular-nums}p.tcap{margin:1em 0 .2em}
figure{display:inline-block;margin:.4em 1em .8em 0;vertical-align:top}figcaption{font-size:.85em;color:#444;
max-width:640px}img.px{image-rendering:pixelated}figure>img{max-width:100%;height:auto}
.cmp{border:1px solid #ddd;border-radius:6px;padding:.6em;margin:.8em 0}
.ctl{display:flex;gap:1em;align-items:center;flex-wrap:wrap;font-size:.92em}
.ctl input{width:16em}
.stack{position:relative;display:inline-block;line-height:0;user-select:none;touch-action:none;cursor:ew-resize;
outline:1px solid #999}
.stack img{display:block;width:100%;image-rendering:pixelated}
.stack img.top{position:absolute;left:0;top:0}.stack img[hidden]{display:none}
.bar{position:absolute;top:0;bottom:0;width:2px;margin-left:-1px;background:#fff;box-shadow:0 0 2px #000;
pointer-events:none}
"""

#: The comparison widget's script: a slider wipes the chosen method over the reference (clip-path on the method's
#: image), dragging on an image moves the slider, the menu shows one method's images and hides the others.
_SCRIPT = """
(function () {
  function setup(c) {
    var range = c.querySelector("input[type=range]"), menu = c.querySelector("select");
    var who = c.querySelector(".who"), tops = c.querySelectorAll("img.top"), bars = c.querySelectorAll(".bar");
    function wipe() {
      var v = Number(range.value);
      tops.forEach(function (img) { img.style.clipPath = "inset(0 " + (100 - v) + "% 0 0)"; });
      bars.forEach(function (bar) { bar.style.left = v + "%"; });
    }
    function pick() {
      tops.forEach(function (img) { img.hidden = img.dataset.i !== menu.value; });
      who.textContent = menu.options[menu.selectedIndex].text;
    }
    function drag(e) {
      if (e.type === "pointermove" && !e.buttons) return;
      var box = e.currentTarget.getBoundingClientRect();
      range.value = String(Math.round(100 * (e.clientX - box.left) / box.width));
      wipe();
    }
    c.querySelectorAll(".stack").forEach(function (s) {
      s.addEventListener("pointerdown", drag);
      s.addEventListener("pointermove", drag);
    });
    range.addEventListener("input", wipe);
    menu.addEventListener("change", pick);
    pick();
    wipe();
  }
  document.querySelectorAll(".cmp").forEach(setup);
})();
"""

#: Nothing but inline style, inline script and data: images may load: a page that tried to fetch anything would
#: be blocked by the browser (and say so on its console).
_CSP = "default-src 'none'; img-src data:; style-src 'unsafe-inline'; script-src 'unsafe-inline'"


class Page:
    """An HTML page being built: add parts in order, then :meth:`render` or :meth:`write` it (see the module's
    docstring for the whole API).

    Args:
        title: the page's title and first heading.

    Examples:
        >>> from stereorepro.workflows.html_report import Page
        >>> page = Page("Results <draft>")
        >>> page.section("Numbers")
        >>> page.table([["a", 1.23456], ["b", None]], header=["name", "value"])
        >>> html = page.render()
        >>> "<title>Results &lt;draft&gt;</title>" in html, '<td class="n">1.235</td>' in html
        (True, True)
    """

    def __init__(self, title: str):
        self.title = str(title)
        self._parts: list[str] = []
        self._toc: list[tuple[str, str]] = []
        self._ids = 0

    def _id(self, prefix: str) -> str:
        self._ids += 1
        return f"{prefix}-{self._ids}"

    def section(self, title: str, level: int = 2) -> None:
        """A heading of ``level`` 2 (listed in the contents at the top of the page) or 3.

        Examples:
            >>> from stereorepro.workflows.html_report import Page
            >>> page = Page("t"); page.section("Tables")
            >>> '<a href="#s-1">Tables</a>' in page.render()
            True

        Raises:
            ParameterError: ``level`` is not 2 or 3.
        """
        if level not in (2, 3):
            raise ParameterError(f"Page.section: level must be 2 or 3, got {level!r}")
        anchor = self._id("s")
        if level == 2:
            self._toc.append((anchor, title))
        self._parts.append(f'<h{level} id="{anchor}">{_esc(title)}</h{level}>')

    def text(self, text: str) -> None:
        """Paragraphs of plain text (HTML-escaped), separated by blank lines; ``**bold**`` and ```code``` marked up.

        Examples:
            >>> from stereorepro.workflows.html_report import Page
            >>> page = Page("t"); page.text("a <b> **c**\\n\\nnext")
            >>> page.render().count("<p>"), "a &lt;b&gt; <strong>c</strong>" in page.render()
            (2, True)
        """
        for para in re.split(r"\n\s*\n", str(text).strip()):
            if para.strip():
                self._parts.append(f"<p>{_inline(para.strip())}</p>")

    def html(self, markup: str) -> None:
        """Markup added as it is (trusted: the caller's own; it must fetch nothing, like the rest of the page).

        Examples:
            >>> from stereorepro.workflows.html_report import Page
            >>> page = Page("t"); page.html("<hr>")
            >>> "<hr>" in page.render()
            True
        """
        self._parts.append(str(markup))

    def table(self, rows, header=None, caption: str | None = None) -> None:
        """A table: ``rows`` a sequence of rows (sequences of cells), ``header`` the column titles, ``caption`` a line
        above it (marked up as :meth:`text` does). Numbers are right-aligned, floats written with 4 significant
        digits (pass strings to choose another format), None as "–".

        Examples:
            >>> from stereorepro.workflows.html_report import Page
            >>> page = Page("t"); page.table([["x", 2]], header=["k", "v"], caption="T")
            >>> '<p class="tcap">T</p>' in page.render(), '<td class="n">2</td>' in page.render()
            (True, True)
        """
        out = [f'<p class="tcap">{_inline(caption)}</p>'] if caption else []
        out.append("<table>")
        if header is not None:
            out.append("<tr>" + "".join(f"<th>{_esc(h)}</th>" for h in header) + "</tr>")
        for row in rows:
            cells = [_cell(x) for x in row]
            out.append(
                "<tr>"
                + "".join(f'<td class="n">{_esc(t)}</td>' if n else f"<td>{_esc(t)}</td>" for t, n in cells)
                + "</tr>"
            )
        self._parts.append("\n".join(out + ["</table>"]))

    def _figure(self, image, caption: str, scale: int) -> str:
        uri, w, h = _data_uri(image)
        style = f' class="px" width="{w * scale}" height="{h * scale}"' if scale > 1 else f' width="{w}" height="{h}"'
        cap = f"<figcaption>{_inline(caption)}</figcaption>" if caption else ""
        return f'<figure><img src="{uri}" alt="{_esc(caption)}"{style}>{cap}</figure>'

    def image(self, image, caption: str = "", scale: int = 1) -> None:
        """One image (an array or tensor, PNG bytes, or a .png file's path) with a caption, shown ``scale`` times
        its size (pixelated).

        Examples:
            >>> import numpy as np
            >>> from stereorepro.workflows.html_report import Page
            >>> page = Page("t"); page.image(np.zeros((2, 3)), caption="black", scale=4)
            >>> 'width="12" height="8"' in page.render()
            True

        Raises:
            ParameterError: a path or bytes that are not a readable PNG file; ``scale`` below 1.
            ShapeError: an array that is not an image.
        """
        if scale < 1:
            raise ParameterError(f"Page.image: scale must be >= 1, got {scale!r}")
        self._parts.append(self._figure(image, caption, int(scale)))

    def gallery(self, images: dict, scale: int = 1) -> None:
        """Images side by side: ``images`` maps each caption to an image (as :meth:`image` takes them).

        Examples:
            >>> import numpy as np
            >>> from stereorepro.workflows.html_report import Page
            >>> page = Page("t"); page.gallery({"a": np.zeros((2, 2)), "b": np.ones((2, 2))})
            >>> page.render().count("<figure>")
            2
        """
        if scale < 1:
            raise ParameterError(f"Page.gallery: scale must be >= 1, got {scale!r}")
        figures = "".join(self._figure(img, cap, int(scale)) for cap, img in images.items())
        self._parts.append(f"<div>{figures}</div>")

    def compare(
        self,
        images: dict,
        reference,
        crops=None,
        reference_label: str = "reference",
        caption: str = "",
        max_width: int = 480,
        min_width: int = 256,
    ) -> None:
        """The comparison widget: ``images`` (method name → image, each the shape of ``reference``) against
        ``reference``, over each of ``crops`` (:class:`Crop`; default: the full frame). A crop wider than
        ``max_width`` pixels is box-averaged down by an integer factor; one narrower than ``min_width`` is shown
        enlarged by an integer factor, pixelated. One slider wipes between the method (left) and the reference
        (right) on every crop; a menu picks the method.

        Examples:
            >>> import numpy as np
            >>> from stereorepro.workflows.html_report import Crop, Page
            >>> ref = np.zeros((8, 8, 3)); page = Page("t")
            >>> page.compare({"a": ref + 0.5, "b": ref + 1.0}, ref, crops=[Crop("corner", 0, 0, 4, 4)])
            >>> html = page.render()
            >>> html.count('class="top"'), html.count("<option"), 'width:256px' in html
            (2, 2, True)

        Raises:
            ParameterError: no images, a crop outside the reference, or widths below 1.
            ShapeError: an image whose shape differs from the reference's.
        """
        ref = _hwc(reference, "compare reference")
        if not images:
            raise ParameterError("Page.compare: images is empty")
        if max_width < 1 or min_width < 1:
            raise ParameterError(f"Page.compare: max_width and min_width must be >= 1, got {max_width}, {min_width}")
        arrays = {}
        for name, img in images.items():
            a = _hwc(img, f"compare image {name!r}")
            if a.shape != ref.shape:
                raise ShapeError(f"Page.compare: image {name!r} has shape {a.shape}, the reference {ref.shape}")
            arrays[name] = a
        crops = [Crop("full frame", 0, 0, ref.shape[0], ref.shape[1])] if crops is None else list(crops)
        for c in crops:
            if (
                c.height < 1
                or c.width < 1
                or c.y < 0
                or c.x < 0
                or c.y + c.height > ref.shape[0]
                or c.x + c.width > ref.shape[1]
            ):
                raise ParameterError(f"Page.compare: crop {c} lies outside the reference (H, W) = {ref.shape[:2]}")
        figures = [self._compare_crop(arrays, ref, c, reference_label, max_width, min_width) for c in crops]
        options = "".join(f'<option value="{i}">{_esc(n)}</option>' for i, n in enumerate(arrays))
        first = _esc(next(iter(arrays)))
        controls = (
            f'<div class="ctl"><label>method <select>{options}</select></label>'
            f'<input type="range" min="0" max="100" value="50" aria-label="wipe between the method and the '
            f'reference"><span>left: <b class="who">{first}</b> · right: {_esc(reference_label)}</span></div>'
        )
        cap = f"<p>{_inline(caption)}</p>" if caption else ""
        self._parts.append(f'<div class="cmp" id="{self._id("c")}">{cap}{controls}<div>{"".join(figures)}</div></div>')

    def _compare_crop(self, arrays: dict, ref, crop: Crop, reference_label: str, max_width: int, min_width: int) -> str:
        r, f = _region(ref, crop, max_width)
        h, w = r.shape[:2]
        z = 1 if f > 1 else max(1, min_width // w)  # enlarge small crops, never a box-averaged one
        imgs = [f'<img class="ref" src="{_data_uri(r)[0]}" alt="{_esc(reference_label)}" draggable="false">']
        for i, (name, a) in enumerate(arrays.items()):
            uri = _data_uri(_region(a, crop, max_width)[0])[0]
            imgs.append(f'<img class="top" data-i="{i}" src="{uri}" alt="{_esc(name)}" draggable="false">')
        scale = f", averaged {f}×{f}" if f > 1 else (f", shown {z}× enlarged" if z > 1 else "")
        label = f"{_esc(crop.label)} (x {crop.x}, y {crop.y}, {crop.width}×{crop.height} px{scale})"
        return (
            f'<figure><div class="stack" style="width:{w * z}px;height:{h * z}px">{"".join(imgs)}'
            f'<div class="bar"></div></div><figcaption>{label}</figcaption></figure>'
        )

    def render(self) -> str:
        """The page's HTML: one string, everything inline.

        Examples:
            >>> from stereorepro.workflows.html_report import Page
            >>> Page("t").render().splitlines()[0]
            '<!DOCTYPE html>'
        """
        toc = "".join(f'<a href="#{a}">{_esc(t)}</a>' for a, t in self._toc)
        return "\n".join(
            [
                "<!DOCTYPE html>",
                '<html lang="en"><head><meta charset="utf-8">',
                f'<meta http-equiv="Content-Security-Policy" content="{_CSP}">',
                '<meta name="viewport" content="width=device-width, initial-scale=1">',
                f"<title>{_esc(self.title)}</title><style>{_STYLE}</style></head>",
                f"<body><h1>{_esc(self.title)}</h1>",
                f"<nav>{toc}</nav>" if toc else "",
                *self._parts,
                f"<script>{_SCRIPT}</script>",
                "</body></html>",
                "",
            ]
        )

    def write(self, path: str | os.PathLike) -> Path:
        """Write the page to ``path`` atomically (:func:`~stereorepro.io.atomic.atomic_write`); returns the path.

        Examples:
            >>> import tempfile, pathlib
            >>> from stereorepro.workflows.html_report import Page
            >>> with tempfile.TemporaryDirectory() as d:
            ...     print(Page("t").write(pathlib.Path(d) / "r.html").name)
            r.html
        """
        path = Path(path)
        atomic_write(path, self.render())
        return path
