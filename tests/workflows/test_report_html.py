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


# --- the experiment's report.html ---------------------------------------------------------------------------------

SMALL = dict(
    scene="living_room", frames=3, width=48, height=27, reference_spp=16, ladder_spp=4, progress=False, alphas=(0.5,)
)


@pytest.fixture(scope="module")
def experiment(tmp_path_factory):
    """A tiny experiment run: its folder, ``results`` and the images it kept for its figures (``keep``, captured
    from ``write_outputs``), and its ``report.html``."""
    pytest.importorskip("embreex")
    from stereorepro.workflows.experiment import ExperimentConfig
    from stereorepro.workflows.experiment import run as run_module

    out, captured = tmp_path_factory.mktemp("exp"), {}
    write_outputs = run_module.write_outputs

    def capture(where, results, per_frame, keep, cfg):
        captured.update(results=results, keep=keep)
        write_outputs(where, results, per_frame, keep, cfg)

    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(run_module, "write_outputs", capture)
        run_module.run_experiment(ExperimentConfig(out=str(out), flip=False, **SMALL), log=lambda *a: None)
    assert (out / "report.html").is_file()  # written by the run itself
    assert "last_frame" in captured["keep"]
    return out, captured["results"], captured["keep"]


def last_frame_from(keep: dict) -> dict:
    """A ``keep["last_frame"]`` entry (the layout report_html documents) made of the run's Figure-4 images."""
    f4 = keep["fig4"]
    return {
        "images": {"stereo_temporal": f4["method"], "stereo": f4["one"] * 0.5 + f4["ref"] * 0.5, "temporal": f4["ref"]},
        "eyes": {"stereo_temporal": "left", "stereo": "left", "temporal": "right"},
        "references": {"left": f4["ref"], "right": f4["ref"] * 0.9},
        "one_spp": {"left": f4["one"], "right": f4["one"]},
    }


class TestExperimentPage:
    def test_smoke(self, experiment):
        out, results, keep = experiment
        text = (out / "report.html").read_text()
        check_self_contained(text)
        for part in ("Table 1", "Table 2", "Resampling bias", "Left eye", "Error maps", "Discarded pixels"):
            assert part in text, part
        assert "fig_cost.png" in text and "fig3_rmse.png" in text  # both plots embedded
        menus = [re.findall(r">([^<]+)</option>", m) for m in re.findall(r"<select>(.*?)</select>", text)]
        assert {"stereo_temporal", "1 spp", "path tracing, 4 spp"} <= set(menus[0])  # the left eye's comparison
        for block, menu in zip(text.split('class="cmp"')[1:], menus):  # each method's image on every crop
            assert block.count('class="top"') == len(menu) * block.count('class="stack"') >= 2 * len(menu)
        assert not list(out.glob("*.tmp"))

    def test_every_scheme_of_the_last_frame(self, experiment):
        from stereorepro.workflows.experiment.report_html import report_page

        out, results, keep = experiment
        text = report_page(results, dict(keep, last_frame=last_frame_from(keep)), figures=out).render()
        check_self_contained(text)
        assert text.count('class="cmp"') == 2 and "Right eye" in text
        menus = re.findall(r"<select>(.*?)</select>", text)
        assert [re.findall(r">([^<]+)</option>", m) for m in menus] == [
            ["stereo_temporal", "stereo", "1 spp", "path tracing, 4 spp"],
            ["temporal", "1 spp"],
        ]

    def test_without_kept_images(self, experiment):
        from stereorepro.workflows.experiment.report_html import report_page

        out, results, _ = experiment
        text = report_page(results, {}).render()
        check_self_contained(text)
        assert "Table 2" in text and 'class="cmp"' not in text and "<img" not in text


# --- in a real browser --------------------------------------------------------------------------------------------

#: Set (to 1) where the browser check must run: CI (.ci/run), which installs Chromium first. Elsewhere the browser
#: tests skip when Chromium or playwright is missing.
REQUIRE_BROWSER = "STEREOREPRO_REQUIRE_BROWSER"


def _chromium() -> str | None:
    """The Chromium (or Chrome) executable: $STEREOREPRO_CHROMIUM (None if it names no executable), else the first
    of the usual names on PATH."""
    import shutil

    if os.environ.get("STEREOREPRO_CHROMIUM"):
        return shutil.which(os.environ["STEREOREPRO_CHROMIUM"])
    names = ("chromium", "chromium-browser", "google-chrome", "google-chrome-stable")
    return next(filter(None, map(shutil.which, names)), None)


@pytest.fixture(scope="module")
def browser():
    """Headless Chromium driven by playwright (the system's browser: playwright downloads none)."""
    missing = []
    try:
        from playwright.sync_api import sync_playwright
    except ImportError:
        missing.append("playwright (pip install '.[test]')")
    exe = _chromium()
    if exe is None:
        missing.append("chromium (apt-get install chromium; or set STEREOREPRO_CHROMIUM)")
    if missing:
        why = "the browser check needs " + " and ".join(missing)
        if os.environ.get(REQUIRE_BROWSER) == "1":
            pytest.fail(f"{why}, and {REQUIRE_BROWSER}=1 requires it")
        pytest.skip(why)
    with sync_playwright() as pw:
        b = pw.chromium.launch(executable_path=exe, args=["--disable-dev-shm-usage"])
        try:
            yield b
        finally:
            b.close()


def open_page(browser, path):
    """The page at ``path`` loaded from file://, with what it logged: console errors and warnings, uncaught
    exceptions and every request other than the page itself and its data: images."""
    page = browser.new_page(viewport={"width": 1280, "height": 900})
    log = {"console": [], "errors": [], "requests": []}
    page.on("console", lambda m: m.type in ("error", "warning") and log["console"].append(f"{m.type}: {m.text}"))
    page.on("pageerror", lambda e: log["errors"].append(str(e)))
    url = path.resolve().as_uri()
    page.on("request", lambda r: r.url != url and not r.url.startswith("data:") and log["requests"].append(r.url))
    page.goto(url, wait_until="load")
    return page, log


class TestInBrowser:
    def test_builder_page(self, browser, tmp_path):
        page, log = open_page(browser, sample_page().write(tmp_path / "sample.html"))
        assert log == {"console": [], "errors": [], "requests": []}
        assert page.evaluate("[...document.images].every(i => i.complete && i.naturalWidth > 0)")
        page.close()

    def test_experiment_report(self, browser, experiment):
        out, _, _ = experiment
        page, log = open_page(browser, out / "report.html")
        assert page.evaluate("[...document.images].every(i => i.complete && i.naturalWidth > 0)")
        # the first comparison (left eye): its slider drives its own crops only
        visible = "[...document.querySelector('.cmp').querySelectorAll('img.top')].filter(i => !i.hidden)"
        clips = f"{visible}.map(i => i.style.clipPath)"
        assert set(page.evaluate(clips)) == {"inset(0px 50% 0px 0px)"}  # the script ran: the wipe at its middle
        page.evaluate(
            "() => { const r = document.querySelector('.cmp input[type=range]'); r.value = '30';"
            " r.dispatchEvent(new Event('input')); }"
        )
        assert set(page.evaluate(clips)) == {"inset(0px 70% 0px 0px)"}
        stack = page.locator(".cmp .stack").first
        stack.scroll_into_view_if_needed()
        box = stack.bounding_box()
        page.mouse.click(box["x"] + 0.8 * box["width"], box["y"] + box["height"] / 2)  # dragging on the image
        assert 78 <= int(page.evaluate("document.querySelector('.cmp input[type=range]').value")) <= 82
        page.select_option(".cmp select", "1")  # the menu shows the second method on every crop
        assert set(page.evaluate(f"{visible}.map(i => i.dataset.i)")) == {"1"}
        assert page.inner_text(".cmp .who") == page.evaluate("document.querySelector('.cmp option[value=\"1\"]').text")
        shot = out / "report_screenshot.png"
        page.screenshot(path=str(shot), full_page=True)
        assert decode_png(shot.read_bytes()).shape[1] == 1280
        assert log == {"console": [], "errors": [], "requests": []}
        page.close()
