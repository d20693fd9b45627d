"""HTML reports: the builder (stereorepro.workflows.html_report): self-contained pages (no URL, nothing to fetch),
well-formed markup, PNGs that decode, atomic writes."""

from __future__ import annotations

import io
import os
import re
from html.parser import HTMLParser

import numpy as np
import pytest

from stereorepro.errors import ParameterError, ParameterTypeError, ShapeError
from stereorepro.workflows import html_report
from stereorepro.workflows.html_report import (
    Crop,
    Page,
    abs_error,
    colorbar,
    colorize,
    full_frame,
    mask_image,
    png_bytes,
    tonemap,
    worst_crop,
)

#: Elements without an end tag.
_VOID = {"meta", "img", "input", "br", "hr", "link"}


class _Structure(HTMLParser):
    """Checks that every element is closed in order and collects the URLs the page refers to."""

    def __init__(self):
        super().__init__()
        self.stack, self.errors, self.urls, self.tags = [], [], [], []

    def handle_starttag(self, tag, attrs):
        self.tags.append(tag)
        self.urls += [v for k, v in attrs if k in ("src", "href", "action", "poster", "srcset") and v is not None]
        if tag not in _VOID:
            self.stack.append(tag)

    def handle_endtag(self, tag):
        if not self.stack or self.stack[-1] != tag:
            self.errors.append(f"</{tag}> closes {self.stack[-1:] or 'nothing'}")
        else:
            self.stack.pop()


def check_self_contained(text: str) -> _Structure:
    """The page's markup is well formed and refers to nothing outside itself: every src / href is a data: URI or a
    fragment, and no "://" occurs anywhere (base64 has no ':', so a data URI never holds one by chance)."""
    s = _Structure()
    s.feed(text)
    s.close()
    assert s.errors == [] and s.stack == [], (s.errors, s.stack)
    assert [s.tags.count(t) for t in ("html", "head", "body")] == [1, 1, 1]
    assert [u for u in s.urls if not (u.startswith("data:image/png;base64,") or u.startswith("#"))] == []
    assert "://" not in text
    assert not re.search(r"url\(|@import|<link|<iframe|<object|<embed", text)
    return s


def decode_png(data: bytes) -> np.ndarray:
    from PIL import Image

    return np.asarray(Image.open(io.BytesIO(data)))


def sample_page() -> Page:
    rng = np.random.default_rng(0)
    ref = rng.random((3, 20, 30)).astype(np.float32)
    noisy = ref + 0.3 * rng.standard_normal(ref.shape).astype(np.float32)
    page = Page("A <report> & more")
    page.section("Settings")
    page.text("Ten frames, **one** seed, `ldr` metric.\n\nSecond paragraph <script>alert(1)</script>.")
    page.section("Tables")
    page.table([["stereo", 1.5, 3], ["temporal", None, 4]], header=["scheme", "spp", "n"], caption="Table 2")
    page.section("Images")
    err = abs_error(noisy, ref)
    page.compare({"noisy": noisy, "blurred": ref * 0.8}, ref, crops=[full_frame(ref), worst_crop(err, 8)])
    page.gallery({"error": colorize(err), "mask": mask_image(err > 0.2), "scale": colorbar()})
    page.image(png_bytes(tonemap(ref)), caption="as PNG bytes")
    return page


class TestPng:
    @pytest.mark.parametrize("shape", [(5, 7), (5, 7, 3), (5, 7, 4), (1, 1, 3), (64, 3, 3)])
    def test_round_trip(self, shape):
        a = np.random.default_rng(1).integers(0, 256, shape, dtype=np.uint8)
        assert np.array_equal(decode_png(png_bytes(a)), a)

    def test_exception(self):
        with pytest.raises(ParameterTypeError, match="uint8"):
            png_bytes(np.zeros((2, 2, 3)))
        with pytest.raises(ShapeError, match="non-empty"):
            png_bytes(np.zeros((0, 2, 3), np.uint8))
        with pytest.raises(ShapeError):
            png_bytes(np.zeros((2, 2, 2), np.uint8))


class TestImages:
    def test_layouts(self):
        torch = pytest.importorskip("torch")
        x = torch.rand(1, 3, 4, 5, requires_grad=True)
        hwc = x.detach()[0].permute(1, 2, 0).numpy()
        for layout in (x, x[0], hwc, hwc.astype(np.float64)):
            assert np.array_equal(tonemap(layout), tonemap(hwc))
        assert tonemap(np.ones((2, 3), bool)).tolist() == [[[255] * 3] * 3] * 2
        assert tonemap(np.array([[np.nan, -1.0, np.inf]])).tolist() == [[[0] * 3, [0] * 3, [255] * 3]]

    def test_error_maps(self):
        ref = np.zeros((4, 6, 3))
        img = ref.copy()
        img[1:3, 4:6] = 0.6
        err = abs_error(img, ref)
        assert err.shape == (4, 6) and err.max() == pytest.approx(0.6)
        assert worst_crop(err, (2, 2)) == Crop("highest error", 1, 4, 2, 2)
        assert worst_crop(err, 100) == Crop("highest error", 0, 0, 4, 6)  # clipped to the image
        rgb = colorize(err, vmax=0.6)
        assert rgb.dtype == np.uint8 and rgb[0, 0].tolist() == [0, 0, 4] and rgb[1, 4].tolist() == [252, 255, 164]
        assert colorbar(10, 3)[0, 0].tolist() == [0, 0, 4] and colorbar(10, 3)[0, -1].tolist() == [252, 255, 164]

    def test_exception(self):
        with pytest.raises(ShapeError, match="differ"):
            abs_error(np.zeros((3, 4, 4)), np.zeros((3, 4, 5)))
        with pytest.raises(ShapeError, match="expected a non-empty image"):
            tonemap(np.zeros((2, 3, 4, 5)))
        with pytest.raises(ParameterTypeError, match="int64"):
            tonemap(np.zeros((2, 3), np.int64))
        with pytest.raises(ShapeError, match="one channel"):
            mask_image(np.zeros((2, 3, 3), bool))
        with pytest.raises(ParameterError, match="size"):
            worst_crop(np.zeros((3, 3)), 0)


class TestPage:
    def test_self_contained(self):
        text = sample_page().render()
        s = check_self_contained(text)
        assert s.tags.count("img") == 3 * 2 + 3 + 1  # two crops x (reference + two methods), gallery, image
        assert "&lt;script&gt;alert(1)&lt;/script&gt;" in text and "<strong>one</strong>" in text
        assert "A &lt;report&gt; &amp; more" in text
        assert text.count("<script>") == 1 and "Content-Security-Policy" in text

    def test_images_decode(self):
        text = sample_page().render()
        uris = re.findall(r'src="data:image/png;base64,([^"]+)"', text)
        import base64

        shapes = [decode_png(base64.b64decode(u)).shape for u in uris]
        assert shapes[:3] == [(20, 30, 3)] * 3  # the full frame: reference, then each method
        assert shapes[3:6] == [(8, 8, 3)] * 3  # the zoomed crop

    def test_compare_downscales_wide_crops(self):
        ref = np.zeros((10, 100, 3))
        page = Page("t")
        page.compare({"a": ref}, ref, max_width=30)
        text = page.render()
        assert "averaged 4×4" in text and 'style="width:25px;height:2px"' in text

    def test_write_is_atomic(self, tmp_path, monkeypatch):
        path = tmp_path / "report.html"
        path.write_text("old")

        def fail(src, dst):
            raise OSError(28, "No space left on device")

        monkeypatch.setattr(os, "replace", fail)
        with pytest.raises(OSError):
            sample_page().write(path)
        assert path.read_text() == "old" and sorted(p.name for p in tmp_path.iterdir()) == ["report.html"]
        monkeypatch.undo()
        assert sample_page().write(path) == path and path.read_text().startswith("<!DOCTYPE html>")

    def test_image_sources(self, tmp_path):
        png = tmp_path / "plot.png"
        png.write_bytes(png_bytes(np.zeros((3, 4, 3), np.uint8)))
        page = Page("t")
        page.image(png, caption="from a file")
        page.image(str(png), scale=2)
        assert page.render().count('src="data:image/png;base64,') == 2
        assert 'width="8" height="6"' in page.render()

    def test_exception(self, tmp_path):
        ref = np.zeros((4, 4, 3))
        page = Page("t")
        with pytest.raises(ShapeError, match="'b' has shape"):
            page.compare({"a": ref, "b": np.zeros((4, 5, 3))}, ref)
        with pytest.raises(ParameterError, match="outside"):
            page.compare({"a": ref}, ref, crops=[Crop("x", 2, 2, 4, 4)])
        with pytest.raises(ParameterError, match="empty"):
            page.compare({}, ref)
        with pytest.raises(ParameterError, match="not a PNG"):
            (tmp_path / "a.png").write_text("text")
            page.image(tmp_path / "a.png")
        with pytest.raises(ParameterError, match="cannot read"):
            page.image(tmp_path / "missing.png")
        with pytest.raises(ParameterError, match="level"):
            page.section("x", level=1)

    def test_light_import(self):
        assert "matplotlib" not in html_report.__dict__ and "torch" not in html_report.__dict__
