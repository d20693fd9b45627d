"""The experiment command: schema of results.json, content cache, resume, atomic outputs, CLI errors."""

import json

import pytest
import torch

from stereorepro.cli import main
from stereorepro.workflows.experiment import ExperimentConfig, RenderCache, run_experiment, tables_markdown

SMALL = dict(
    scene="living_room", frames=3, width=48, height=27, reference_spp=16, ladder_spp=4, progress=False, alphas=(0.5,)
)


@pytest.fixture(scope="module")
def first_run(tmp_path_factory):
    out = tmp_path_factory.mktemp("exp")
    return out, run_experiment(ExperimentConfig(out=str(out), **SMALL), log=lambda *a: None)


class TestExperiment:
    def test_history_rounding(self, tmp_path):
        """``history_rounding="bmfr"`` reaches the drivers and results.json; the discards do not depend on it, the
        temporal scheme's colours do from frame 3 on (rounded lengths first differ in what frame 3 reads)."""
        common = dict(SMALL, frames=4, flip=False, ssim=False)
        cache = str(tmp_path / "cache")
        runs = {
            mode: run_experiment(
                ExperimentConfig(out=str(tmp_path / mode), cache_dir=cache, history_rounding=mode, **common),
                log=lambda *a: None,
            )
            for mode in ("none", "bmfr")
        }
        none, bmfr = runs["none"], runs["bmfr"]
        assert (none["history_rounding"], bmfr["history_rounding"]) == ("none", "bmfr")
        assert none["footprint_weighting"] is False
        assert bmfr["cache"]["misses"] == 0 and bmfr["table1"] == none["table1"]
        assert bmfr["table2"]["stereo"] == none["table2"]["stereo"]
        rmse = [(a["rmse"]["temporal"], b["rmse"]["temporal"]) for a, b in zip(none["per_frame"], bmfr["per_frame"])]
        assert all(a == b for a, b in rmse[:3]) and rmse[3][0] != rmse[3][1], rmse

    def test_option_variants(self, tmp_path):
        """``option_variants=True`` adds the paper's temporal schemes with each history option alone: the options reach
        their drivers (their colours differ from the plain scheme's), every variant's bias is measured without
        reference noise, and the other schemes are those of a run without them, number for number."""
        from stereorepro.workflows.experiment.config import OPTION_VARIANTS

        # loose position tests: whole 4x4 footprints pass at this size, so Catmull-Rom acts
        common = dict(SMALL, frames=4, flip=False, ssim=False, reference_chunk_spp=8, alphas=(), threshold_scale=10.0)
        cache = str(tmp_path / "cache")
        plain = run_experiment(
            ExperimentConfig(out=str(tmp_path / "a"), cache_dir=cache, **common), log=lambda *a: None
        )
        res = run_experiment(
            ExperimentConfig(out=str(tmp_path / "b"), cache_dir=cache, option_variants=True, **common),
            log=lambda *a: None,
        )
        assert res["option_variants"] and not plain["option_variants"] and res["cache"]["misses"] == 0
        names = [f"{s}_{o}" for o in OPTION_VARIANTS for s in ("temporal", "stereo_temporal")]
        assert set(names) <= set(res["table2_variants"]) and not set(names) & set(plain["table2_variants"])
        assert res["table2"] == plain["table2"] and res["table1"] == plain["table1"]
        for name in names:
            assert res["bias"][name]["bias_mse"]["n"] == 4, name
            assert res["bias"][name]["rmse_noise_free"]["n"] == 0, name
            base = "temporal" if name.startswith("temporal_") else "stereo_temporal"
            rm = [(r["rmse"][base], r["rmse"][name]) for r in res["per_frame"]]
            assert any(a != b for a, b in rm), (name, rm)
            bias = [(r["bias_mse"][base], r["bias_mse"][name]) for r in res["per_frame"]]
            assert any(a != b for a, b in bias), (name, bias)  # the reference halves ran with the option too
        (tmp_path / "b" / "report.md").read_text().index("stereo_temporal_footprint")

    def test_smoke(self, first_run):
        out, res = first_run
        for f in (
            "results.json",
            "tables.md",
            "report.md",
            "report.html",
            "fig1_discards.png",
            "fig3_rmse.png",
            "fig4_comparison.png",
            "fig_cost.png",
        ):
            assert (out / f).is_file(), f
        assert not list(out.glob("*.tmp")) and not list((out / "cache").glob("*.tmp"))

    def test_results_schema(self, first_run):
        out, res = first_run
        data = json.loads((out / "results.json").read_text())
        assert data["scene"] == "living_room" and data["frames"] == 3 and data["resolution"] == "48x27"
        assert data["reference_spp"] == 16
        for k in ("stereo", "temporal"):
            assert set(data["table1"][k]) >= {"avg", "min", "max"}
        for k in ("stereo", "temporal", "stereo_temporal"):
            t = data["table2"][k]
            assert t["min"] <= t["avg"] <= t["max"]
        assert len(data["per_frame"]) == 3 and "timing_ms" in data
        # frame 0 has no history: the temporal output is the right eye's 1-spp rung itself
        f0 = data["per_frame"][0]
        assert f0["rmse"]["temporal"] == pytest.approx(f0["ladder_rmse"]["right"][0], rel=1e-12)
        if f0["flags"]["temporal"] == "exact":
            assert f0["effective_spp"]["temporal"] == 1.0
        assert "temporal_alpha0.5" in data["table2_variants"] and "stereo_nearest" in data["table2_variants"]
        # the masked trace of the left eye's discarded pixels reproduces the full 1-spp render there
        assert all(r.get("masked_trace_matches", True) for r in data["per_frame"])

    def test_flip_reported(self, first_run, tmp_path):
        from stereorepro.measure.metrics import flip_available

        if not flip_available():
            pytest.skip("flip-evaluator is not installed")
        out, res = first_run
        data = json.loads((out / "results.json").read_text())
        assert set(data["flip"]) == set(data["table2"]) | set(data["table2_variants"])
        for r in data["per_frame"]:
            assert all(0.0 <= v <= 1.0 for v in r["flip"].values())
        # frame 0 has no history: the temporal output is the 1-spp image, the noisiest; stereo+temporal beats it later
        assert data["flip"]["stereo_temporal"]["avg"] < data["per_frame"][0]["flip"]["temporal"]
        assert "## FLIP" in (out / "report.md").read_text()
        off = run_experiment(
            ExperimentConfig(out=str(tmp_path), cache_dir=str(out / "cache"), flip=False, **dict(SMALL, frames=1))
        )
        assert off["flip"] is None and off["cache"]["misses"] == 0

    def test_ssim_reported(self, first_run, tmp_path):
        from stereorepro.measure.metrics import ssim

        out, res = first_run
        assert set(res["ssim"]) == {"stereo", "temporal", "stereo_temporal"}
        assert all(0.0 < v["avg"] <= 1.0 for v in res["ssim"].values())
        # frame 0's temporal output is the right eye's 1-spp image itself
        f0 = res["per_frame"][0]["ssim"]["temporal"]
        assert "## SSIM" in (out / "report.md").read_text()
        off = run_experiment(
            ExperimentConfig(out=str(tmp_path), cache_dir=str(out / "cache"), ssim=False, **dict(SMALL, frames=1))
        )
        assert off["ssim"] is None and off["per_frame"][0]["ssim"] == {}
        from stereorepro.workflows.experiment.config import RIGHT
        from stereorepro.workflows.experiment.inputs import RenderContext, reference, spec_for
        from stereorepro.scenes import load_scene

        cfg = ExperimentConfig(out=str(out), **SMALL)
        ctx = RenderContext(spec_for(cfg, load_scene(cfg.scene), out / "cache"))
        from stereorepro.workflows.experiment.inputs import ladder_task

        one = torch.from_numpy(ladder_task(ctx, 0, RIGHT)[0]["first"])
        assert f0 == float(ssim(one, reference(ctx, 0, RIGHT)[0], tonemap="clamp")[0])

    @pytest.mark.parametrize("every, scored", [(2, [True, False, True]), (3, [False, False, True])])
    def test_perceptual_every(self, first_run, tmp_path, every, scored):
        """``perceptual_every=K`` scores FLIP and SSIM on every K-th frame counted back from the last (the last frame
        always), with the values of a run that scores every frame; RMSE stays per frame."""
        from stereorepro.measure.metrics import flip_available

        out, res = first_run
        sub = run_experiment(
            ExperimentConfig(out=str(tmp_path), cache_dir=str(out / "cache"), perceptual_every=every, **SMALL)
        )
        assert sub["perceptual_every"] == every and sub["cache"]["misses"] == 0
        for key in ("ssim", "flip") if flip_available() else ("ssim",):
            assert [bool(r[key]) for r in sub["per_frame"]] == scored, key
            for f in range(3):
                assert sub["per_frame"][f][key] == (res["per_frame"][f][key] if scored[f] else {}), key
            assert all(v["n"] == sum(scored) for v in sub[key].values()), key
        assert all(r["rmse"] == q["rmse"] for r, q in zip(sub["per_frame"], res["per_frame"]))
        report = (tmp_path / "report.md").read_text()
        assert f"one frame in {every}, counted back from the last ({sum(scored)} frames)" in report

    def test_temporal_error_reported(self, first_run):
        out, res = first_run
        data = json.loads((out / "results.json").read_text())
        schemes = set(data["table2"]) | set(data["table2_variants"])
        assert set(data["temporal_error"]) == schemes
        # frame 0 has no previous frame: frames 1.. are scored, every scheme in each
        assert all(v["n"] == SMALL["frames"] - 1 for v in data["temporal_error"].values())
        assert data["per_frame"][0]["temporal_error"] == {}
        for r in data["per_frame"][1:]:
            assert set(r["temporal_error"]) == schemes and all(0.0 < v < 1.0 for v in r["temporal_error"].values())
        assert data["timing_ms"]["temporal_error_ms"] > 0
        assert "**Temporal error** (lower = steadier)" in (out / "tables.md").read_text()
        assert "## Temporal stability" in (out / "report.md").read_text()

    def test_temporal_error_value(self, first_run, tmp_path, monkeypatch):
        """Frame 1 of the temporal scheme, recomputed from the cache: its previous image is the right eye's frame-0
        1-spp render (no history yet), warped by the right eye's G-buffers with the run's thresholds."""
        from stereorepro.measure import temporal_error
        from stereorepro.reproject import View
        from stereorepro.scenes import load_scene
        from stereorepro.workflows.experiment import run as run_module
        from stereorepro.workflows.experiment.config import RIGHT
        from stereorepro.workflows.experiment.inputs import RenderContext, ladder_task, render_eye, spec_for

        out, _ = first_run
        seen = []

        def spy(image, *args, **kwargs):
            seen.append(image)
            return temporal_error(image, *args, **kwargs)

        monkeypatch.setattr(run_module, "temporal_error", spy)
        cfg = ExperimentConfig(out=str(tmp_path), cache_dir=str(out / "cache"), **dict(SMALL, frames=2))
        res = run_experiment(cfg)
        assert res["cache"]["misses"] == 0 and res["temporal_error"]["temporal"]["n"] == 1
        image = seen[list(res["per_frame"][1]["temporal_error"]).index("temporal")]  # the scheme's frame-1 output
        ctx = RenderContext(spec_for(cfg, load_scene(cfg.scene), out / "cache"), scene=load_scene(cfg.scene))
        now, before = render_eye(ctx, 1, RIGHT), render_eye(ctx, 0, RIGHT)
        one = torch.from_numpy(ladder_task(ctx, 0, RIGHT)[0]["first"])
        th = res["thresholds"]

        def view(e):
            return View(e.depth, e.normal, e.K, e.cam_from_world)

        expected = temporal_error(
            image, now.reference, one, before.reference, view(now), view(before), (th["position"], th["normal"])
        )
        assert res["per_frame"][1]["temporal_error"]["temporal"] == float(expected[0])
        one_frame = run_experiment(
            ExperimentConfig(out=str(tmp_path), cache_dir=str(out / "cache"), **dict(SMALL, frames=1))
        )
        assert one_frame["temporal_error"] is None and "Temporal error" not in (tmp_path / "tables.md").read_text()

    def test_cached_run_is_identical(self, first_run, tmp_path):
        out, res = first_run
        again = run_experiment(ExperimentConfig(out=str(out), **SMALL))
        assert again["cache"]["misses"] == 0 and again["cache"]["hits"] > 0
        assert tables_markdown(again) == tables_markdown(res)
        assert again["table2"] == res["table2"] and again["table1"] == res["table1"]

    def test_resume_after_interruption(self, tmp_path):
        cfg = dict(SMALL, frames=2)
        part = run_experiment(ExperimentConfig(out=str(tmp_path), **cfg))
        full = run_experiment(ExperimentConfig(out=str(tmp_path), **dict(SMALL)))
        per_frame = 3 * 2  # gbuffer + reference + lean ladder, both eyes
        assert part["cache"]["misses"] == 2 * per_frame
        # the new frame's reference is read back once per eye after its ladder was scored against it
        assert full["cache"]["misses"] == per_frame and full["cache"]["hits"] == 2 * per_frame + 2

    def test_force_recomputes(self, tmp_path):
        cfg = dict(SMALL, frames=1)
        run_experiment(ExperimentConfig(out=str(tmp_path), **cfg))
        forced = run_experiment(ExperimentConfig(out=str(tmp_path), force=True, **cfg))
        # every entry recomputed exactly once (G-buffer, reference, ladder per eye), then read back as made
        assert forced["cache"]["misses"] == 3 * 2 and forced["cache"]["recomputed_corrupt"] == []

    @pytest.mark.parametrize("damage", ["garbage", "zero_bytes", "truncated", "no_meta"])
    def test_corrupt_cache_entry_is_recomputed(self, tmp_path, damage):
        """A zero-byte or truncated entry (EOFError, BadZipFile) crashed the next run instead of being recomputed."""
        import numpy as np

        cache = RenderCache(tmp_path)
        key = {"a": 1}
        cache.get_or_make(key, lambda: ({"x": np.ones(1000)}, {"ms": 1.0}))
        path = next(tmp_path.glob("*.npz"))
        data = path.read_bytes()
        path.write_bytes(
            {"garbage": b"not a zip", "zero_bytes": b"", "truncated": data[: len(data) // 2]}.get(damage, b"")
        )
        if damage == "no_meta":
            np.savez(path, x=np.ones(3))
        logged = []
        cache = RenderCache(tmp_path, log=logged.append)
        data, meta = cache.get_or_make(key, lambda: ({"x": np.zeros(3)}, {"ms": 2.0}))
        assert meta["ms"] == 2.0 and data["x"].sum() == 0
        assert cache.corrupt == [path.name] and len(logged) == 1 and path.name in logged[0]
        data, meta = RenderCache(tmp_path).get_or_make(key, lambda: pytest.fail("the rewritten entry is valid"))
        assert meta["ms"] == 2.0

    def test_cache_sweeps_dead_runs_temporaries(self, tmp_path):
        import subprocess
        import sys

        p = subprocess.Popen([sys.executable, "-c", "pass"])
        p.wait()
        (tmp_path / f".abc.npz.{p.pid}.0123abcd.tmp").write_bytes(b"half")
        cache = RenderCache(tmp_path)
        assert len(cache.swept) == 1 and list(tmp_path.iterdir()) == []

    def test_metric_hdr_vs_ldr(self, first_run, tmp_path):
        out, res = first_run
        assert res["metric"] == "ldr"
        hdr = run_experiment(ExperimentConfig(out=str(tmp_path), cache_dir=str(out / "cache"), metric="hdr", **SMALL))
        assert hdr["cache"]["misses"] == 0  # same renders, only the error metric differs
        assert hdr["per_frame"][0]["ladder_rmse"]["left"][0] > res["per_frame"][0]["ladder_rmse"]["left"][0]
        with pytest.raises(ValueError, match="metric"):
            run_experiment(ExperimentConfig(out=str(tmp_path), metric="srgb", **SMALL))

    def test_exr_output(self, first_run, tmp_path):
        from stereorepro.io.exr import read_exr

        out, _ = first_run
        run_experiment(
            ExperimentConfig(out=str(tmp_path), cache_dir=str(out / "cache"), exr=True, **dict(SMALL, frames=1))
        )
        ch = read_exr(tmp_path / "exr" / "0000_left.exr")
        assert {"R", "G", "B", "Z", "N.X", "N.Y", "N.Z"} <= set(ch) and ch["R"].shape == (27, 48)

    def test_exceptions(self, tmp_path):
        out = tmp_path / "never"
        for bad, match in (
            (dict(ladder_spp=1), "ladder_spp"),
            (dict(frames=10_000), "frames"),
            (dict(alphas=(float("nan"),)), "alphas"),
            (dict(workers=0), "workers"),
            (dict(perceptual_every=0), "perceptual_every"),
            (dict(scene=str(tmp_path / "missing.toml")), "not found"),
        ):
            with pytest.raises(ValueError, match=match):
                run_experiment(ExperimentConfig(out=str(out), **dict(SMALL, **bad)))
            assert not out.exists(), f"{bad}: a failed validation created --out"
        (tmp_path / "file").write_text("x")
        with pytest.raises(ValueError, match="exists and is not a directory"):
            run_experiment(ExperimentConfig(out=str(tmp_path / "file"), **SMALL))
        with pytest.raises(ValueError, match="ladder_spp"):
            run_experiment(ExperimentConfig(out=str(tmp_path), **dict(SMALL, ladder_spp=1)))
        with pytest.raises(ValueError, match="frames"):
            run_experiment(ExperimentConfig(out=str(tmp_path), **dict(SMALL, frames=10_000)))

    def test_cli_errors(self, tmp_path, capsys):
        assert main(["experiment", "--scene", "no_such_scene", "--out", str(tmp_path)]) == 2
        assert "no_such_scene" in capsys.readouterr().err
        assert main(["experiment", "--scene", "living_room", "--out", str(tmp_path), "--resolution", "big"]) == 2
        assert len(capsys.readouterr().err.strip().splitlines()) == 1


class TestExperimentMovingObjects:
    """``experiment --scene living_room_moving_objects``: the motion-vector variants and the discards on the
    moving objects' pixels against the static background."""

    @pytest.fixture(scope="class")
    def run(self, tmp_path_factory):
        out = tmp_path_factory.mktemp("exp_mo")
        cfg = dict(SMALL, scene="living_room_moving_objects", frames=4, width=96, height=54)
        return out, run_experiment(ExperimentConfig(out=str(out), **cfg), log=lambda *a: None)

    def test_variants_and_table(self, run):
        out, res = run
        assert {"temporal_mv", "stereo_temporal_mv"} <= set(res["table2_variants"])
        mo = res["moving_objects"]
        assert mo["moving_pixels_pct"]["avg"] > 3
        cam, mv = mo["temporal"], mo["temporal_mv"]
        assert mv["moving"]["avg"] < 0.5 * cam["moving"]["avg"], (mv, cam)
        assert mv["static"]["avg"] == pytest.approx(cam["static"]["avg"], abs=0.5)  # same warp off the objects
        assert "Moving objects" in (out / "tables.md").read_text()

    def test_static_scene_has_no_motion_variants(self, first_run):
        _, res = first_run
        assert "moving_objects" not in res and "temporal_mv" not in res["table2_variants"]

    def test_figure_1_has_the_motion_panel(self, run, first_run):
        import matplotlib.image as mpimg

        def aspect(path):
            h, w = mpimg.imread(path).shape[:2]
            return w / h

        # three panels (stereo, temporal with cameras, temporal with motion vectors) instead of two
        assert aspect(run[0] / "fig1_discards.png") > 1.3 * aspect(first_run[0] / "fig1_discards.png")


class TestRenderTasks:
    """The render tasks behind the experiment (:mod:`stereorepro.workflows.experiment.inputs`): the lean ladder, the
    chunked reference and the cache footprint."""

    @staticmethod
    def ctx(tmp_path, **kw):
        from stereorepro.workflows.experiment.inputs import RenderContext, RenderSpec

        spec = dict(
            scene="living_room",
            width=40,
            height=24,
            seed=3,
            ladder_spp=5,
            reference_spp=8,
            reference_chunk_spp=8,
            base_key=json.dumps({"t": 1}),
            cache_dir=str(tmp_path),
        )
        spec.update(kw)
        return RenderContext(RenderSpec(**spec))

    def test_lean_ladder_equals_the_rungs(self, tmp_path):
        """The lean entry holds exactly what the analysis used to compute from every cached 1-spp rung."""
        import torch

        from stereorepro.workflows.experiment.config import METRICS, metric_image
        from stereorepro.workflows.experiment.inputs import ladder_task, reference
        from stereorepro.measure.metrics import ladder_rmse

        ctx = self.ctx(tmp_path)
        lad, meta = ladder_task(ctx, 1, 0)
        cam, _ = ctx.camera(1, 0)
        total, rungs = None, []
        for s in range(5):  # the old layout: one 1-spp render per rung, prefix means in float64
            x = ctx.tracer.render(cam, 1, 1, sample_offset=s, eye=0, gbuffers=False).radiance.double()
            total = x if total is None else total + x
            rungs.append((total / (s + 1)).float())
        ref = reference(ctx, 1, 0)[0]
        for m in METRICS:
            old = ladder_rmse([metric_image(r, m) for r in rungs], metric_image(ref, m))[0].tolist()
            assert lad[f"rmse_{m}"][-1].tolist() == old  # bit for bit
        assert torch.equal(torch.from_numpy(lad["first"]), rungs[0])
        assert torch.equal(torch.from_numpy(lad["top"]), rungs[-1])
        assert meta["ms_per_spp"] > 0

    def test_chunked_reference(self, tmp_path):
        """The reference is the mean of its chunk means in chunk order; its prefixes score the ladder too."""
        import torch

        from stereorepro.workflows.experiment.config import REFERENCE_OFFSET
        from stereorepro.workflows.experiment.inputs import ladder_task, reference, reference_prefixes

        ctx = self.ctx(tmp_path, reference_spp=8, reference_chunk_spp=2)
        assert reference_prefixes(ctx.spec) == [2, 4, 8]
        cam, _ = ctx.camera(0, 1)
        chunks = [
            ctx.tracer.render(cam, 0, 2, sample_offset=REFERENCE_OFFSET + 2 * i, eye=1, gbuffers=False).radiance
            for i in range(4)
        ]
        want = ((chunks[0].double() + chunks[1].double() + chunks[2].double() + chunks[3].double()) / 4).float()
        got, _ = reference(ctx, 0, 1)
        assert torch.equal(got, want)
        assert torch.equal(reference(ctx, 0, 1, 4)[0], ((chunks[0].double() + chunks[1].double()) / 2).float())
        # one chunk is the renderer's own reference render, under the same value
        one = self.ctx(tmp_path / "one")
        full = one.tracer.render(cam, 0, 8, sample_offset=REFERENCE_OFFSET, eye=1, gbuffers=False).radiance
        assert torch.equal(reference(one, 0, 1)[0], full)
        assert not torch.equal(full, got)  # chunking changes the value at rounding level: it is in the key
        assert (full - got).abs().max() < 1e-5
        lad, _ = ladder_task(ctx, 0, 1)
        assert lad["prefix_spp"].tolist() == [2, 4, 8] and lad["rmse_ldr"].shape == (3, 5)

    def test_reference_halves(self, tmp_path):
        """The resampling bias's two independent halves: the mean of the first half of the chunks, and of the rest."""
        from stereorepro.workflows.experiment.inputs import reference, reference_chunk_task
        from stereorepro.workflows.experiment.run import _reference_halves

        ctx = self.ctx(tmp_path, reference_spp=8, reference_chunk_spp=2)
        halves, spp = _reference_halves(ctx, 0)
        assert spp == (4, 4) and len(halves) == 2  # both eyes
        for eye, (a, b) in halves.items():
            assert torch.equal(a, reference(ctx, 0, eye, 4)[0])  # the 4-spp prefix
            c = [torch.from_numpy(reference_chunk_task(ctx, 0, eye, i)[0]["radiance"]).double() for i in (2, 3)]
            assert torch.equal(b, ((c[0] + c[1]) / 2).float())
        assert _reference_halves(self.ctx(tmp_path / "one"), 0) == (None, ())

    def test_bias_needs_two_chunks(self, first_run):
        out, res = first_run  # a reference in one chunk: no independent halves
        for k in ("stereo", "temporal", "stereo_temporal"):
            b = res["bias"][k]
            assert b["bias_mse"]["n"] == 0 and b["bias_share"]["avg"] is None
            assert b["anatomy"]["edge"]["pixels_pct"]["n"] > 0  # the footprint split needs no halves
            assert b["anatomy"]["edge"]["bias_share_pct"]["n"] == 0
        report = (out / "report.md").read_text()
        assert "Not measured: it needs the reference in two chunks or more" in report
        assert "### Where the error lives" in report

    def test_reference_study_and_footprint(self, tmp_path):
        res = run_experiment(ExperimentConfig(out=str(tmp_path), **dict(SMALL, reference_chunk_spp=4, frames=2)))
        study = res["reference_study"]
        assert list(study) == ["4", "8", "16"]
        assert set(study["4"]) == {"stereo", "temporal", "stereo_temporal"}
        assert study["16"]["temporal"] == res["table2"]["temporal"]
        for p in ("4", "8"):
            assert all(v["avg"] > 0 for v in study[p].values())
        # the same run without chunking: another reference value (another key), the same kind of tables
        plain = run_experiment(
            ExperimentConfig(out=str(tmp_path / "plain"), cache_dir=str(tmp_path / "cache"), **dict(SMALL, frames=2))
        )
        assert plain["reference_study"] is None and plain["cache"]["misses"] > 0
        fp = res["cache"]
        H, W = SMALL["height"], SMALL["width"]
        images = 1 + 3 + 4 * 3 + 2 * 3  # depth, normal, 4 reference chunks, first + top rungs (float32 planes)
        assert images * 4 * H * W < fp["bytes_per_eye_frame"] < images * 4 * H * W + 12_000

    def test_disk_space_warning(self, tmp_path, monkeypatch):
        import shutil
        from collections import namedtuple

        usage = namedtuple("usage", "total used free")
        monkeypatch.setattr(shutil, "disk_usage", lambda p: usage(10, 10, 1000))
        logged = []
        run_experiment(ExperimentConfig(out=str(tmp_path), **dict(SMALL, frames=1)), log=logged.append)
        warn = [m for m in logged if m.startswith("warning: the render cache needs")]
        assert len(warn) == 1 and "MiB per eye and frame" in warn[0]

    def test_chunk_and_scheduler_exceptions(self, tmp_path):
        for bad, match in (
            (dict(reference_chunk_spp=3), "reference_chunk_spp"),
            (dict(reference_chunk_spp=0), "reference_chunk_spp"),
            (dict(scheduler="local:0"), "scheduler"),
            (dict(scheduler="udp://x:1"), "scheduler"),
            (dict(scheduler="tcp://host"), "scheduler"),
        ):
            with pytest.raises(ValueError, match=match):
                run_experiment(ExperimentConfig(out=str(tmp_path / "x"), **dict(SMALL, **bad)))
            assert not (tmp_path / "x").exists()

    def test_jitter(self, first_run, tmp_path):
        """With jitter the schemes read the jittered cameras' G-buffers and centre samples; ladders and references
        are the unjittered run's (shared cache entries)."""
        out, res = first_run
        jit = run_experiment(ExperimentConfig(out=str(tmp_path), cache_dir=str(out / "cache"), jitter=True, **SMALL))
        n = SMALL["frames"] * 2
        assert jit["cache"]["misses"] == 2 * n  # only the jittered G-buffer and sample of each eye-frame are new
        assert jit["jitter"] and not res["jitter"]
        f0, j0 = res["per_frame"][0], jit["per_frame"][0]
        assert j0["ladder_rmse"] == f0["ladder_rmse"]
        assert j0["rmse"]["stereo"] != f0["rmse"]["stereo"]
        mid = [r for r in jit["per_frame"] if "masked_trace_matches" in r]
        assert mid and all(r["masked_trace_matches"] for r in mid)  # the left fill traces the jittered centres
        from stereorepro.workflows.experiment.inputs import RenderSpec, eye_tasks

        spec = RenderSpec(
            scene="x",
            width=8,
            height=8,
            seed=0,
            ladder_spp=2,
            reference_spp=4,
            reference_chunk_spp=2,
            base_key="{}",
            cache_dir=str(tmp_path),
            jitter=True,
        )
        assert [t[0] for t in eye_tasks(spec, 3, 1)] == [
            "gbuffer_task",
            "reference_chunk_task",
            "reference_chunk_task",
            "ladder_task",
            "jitter_gbuffer_task",
            "jitter_sample_task",
        ]
        assert eye_tasks(spec, 3, 1)[-1][2]["jitter"] != eye_tasks(spec, 4, 1)[-1][2]["jitter"]

    def test_beyond_ladder_is_bounded_not_extrapolated(self, first_run):
        """Frames whose error lies below the ladder's top rung (flagged ``extrapolated_high`` or ``beyond_floor``)
        are counted at the top rung in ``avg_lower_bound``, and the tables print that bound as ``≥ x``."""
        from stereorepro.workflows.experiment.report import cost_markdown
        from stereorepro.workflows.experiment.run import _spp_stats

        rows = [
            {"effective_spp": {"s": x}, "flags": {"s": f}}
            for x, f in [(10.0, "interpolated")] * 10 + [(50.0, "extrapolated_high"), (float("inf"), "beyond_floor")]
        ]
        st = _spp_stats(rows, "s", 32)
        assert st["beyond_ladder"] == 2 and st["n"] == 11  # the infinite frame drops out of the plain average
        assert st["avg"] == pytest.approx(150.0 / 11) and st["avg_lower_bound"] == pytest.approx(164.0 / 12)
        assert st["avg_after_warmup"] == 50.0 and st["avg_after_warmup_lower_bound"] == 32.0
        inside = _spp_stats(rows[:10], "s", 32)
        assert inside["beyond_ladder"] == 0 and inside["avg_lower_bound"] == inside["avg"] == 10.0

        _, res = first_run
        for k, v in {**res["table2"], **res["table2_variants"]}.items():
            beyond = sum(r["flags"][k] in ("extrapolated_high", "beyond_floor") for r in res["per_frame"])
            assert v["beyond_ladder"] == beyond, k
        t2 = {k: dict(v, beyond_ladder=0) for k, v in res["table2"].items()}
        t2["stereo_temporal"].update(beyond_ladder=2, avg_lower_bound=3.25)
        md = tables_markdown(dict(res, table2=t2))
        assert "| ≥ 3.25 |" in md and "stereo_temporal 2" in md
        assert "≥" not in tables_markdown(dict(res, table2={k: dict(v, beyond_ladder=0) for k, v in t2.items()}))
        cost = [{"scheme": "s", "ms": 8.0, "effective_spp": 32.0, "ms_per_effective_spp": 0.25, "beyond_ladder": 3}]
        assert cost_markdown({"cost": cost}).splitlines()[-1] == "| s | 8.0 | ≥ 32.00 | ≤ 0.2 |"

    def test_blend_and_alternate_schemes(self, first_run):
        """The follow-up's schemes run on the same renders: on frame 0 the alternating scheme traces the right eye
        like stereo+temporal (same images), from frame 1 on it traces the left eye every other frame."""
        _, res = first_run
        var = res["table2_variants"]
        assert {"stereo_temporal_blend", "alternate", "alternate_blend"} <= set(var)
        f0, f1 = res["per_frame"][0], res["per_frame"][1]
        assert f0["rmse"]["alternate"] == f0["rmse"]["stereo_temporal"]
        assert f1["rmse"]["alternate"] != f1["rmse"]["stereo_temporal"]
        assert all(v["avg"] > 0 for v in var.values())


class TestCostPlotStyles:
    def test_every_scheme_distinct(self):
        """The cost plot tells every scheme apart, the option variants included: no two share marker and colour;
        the marker is the family's, the colour the variant's (the same option reads alike in every family)."""
        from matplotlib import colormaps

        from stereorepro.workflows.experiment.config import schemes
        from stereorepro.workflows.experiment.report import _cost_styles

        cfg = ExperimentConfig(scene="cornell", out="unused", alphas=(0.1, 0.5), option_variants=True)
        names = [s.name for s in schemes(cfg, moving_objects=True)]
        styles = _cost_styles(names, colormaps["tab20"].colors)
        assert len(names) > 25 and len(set(styles.values())) == len(names)
        assert styles["temporal_clamp"][1] == styles["stereo_temporal_clamp"][1]
        assert styles["temporal"][1] == styles["stereo"][1] == styles["stereo_temporal"][1]
        assert [styles[n][0] for n in ("stereo", "temporal", "stereo_temporal_clamp", "alternate_blend")] == [
            "o",
            "s",
            "^",
            "D",
        ]
