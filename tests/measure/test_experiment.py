"""The experiment command: schema of results.json, content cache, resume, atomic outputs, CLI errors."""

import json

import pytest

from stereorepro.cli import main
from stereorepro.measure.experiment import ExperimentConfig, RenderCache, run_experiment, tables_markdown

SMALL = dict(scene="living_room", frames=3, width=48, height=27, reference_spp=16, ladder_spp=4, progress=False,
             alphas=(0.5,))


@pytest.fixture(scope="module")
def first_run(tmp_path_factory):
    out = tmp_path_factory.mktemp("exp")
    return out, run_experiment(ExperimentConfig(out=str(out), **SMALL), log=lambda *a: None)


class TestExperiment:
    def test_smoke(self, first_run):
        out, res = first_run
        for f in ("results.json", "tables.md", "report.md", "fig1_discards.png", "fig3_rmse.png",
                  "fig4_comparison.png", "fig_cost.png"):
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
        off = run_experiment(ExperimentConfig(out=str(tmp_path), cache_dir=str(out / "cache"), flip=False,
                                              **dict(SMALL, frames=1)))
        assert off["flip"] is None and off["cache"]["misses"] == 0

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
        per_frame = (SMALL["ladder_spp"] + 2) * 2  # ladder rungs + gbuffer + reference, both eyes
        assert part["cache"]["misses"] == 2 * per_frame
        assert full["cache"]["misses"] == per_frame and full["cache"]["hits"] == 2 * per_frame

    def test_force_recomputes(self, tmp_path):
        cfg = dict(SMALL, frames=1)
        run_experiment(ExperimentConfig(out=str(tmp_path), **cfg))
        forced = run_experiment(ExperimentConfig(out=str(tmp_path), force=True, **cfg))
        assert forced["cache"]["hits"] == 0

    @pytest.mark.parametrize("damage", ["garbage", "zero_bytes", "truncated", "no_meta"])
    def test_corrupt_cache_entry_is_recomputed(self, tmp_path, damage):
        """A zero-byte or truncated entry (EOFError, BadZipFile) crashed the next run instead of being recomputed."""
        import numpy as np

        cache = RenderCache(tmp_path)
        key = {"a": 1}
        cache.get_or_make(key, lambda: ({"x": np.ones(1000)}, {"ms": 1.0}))
        path = next(tmp_path.glob("*.npz"))
        data = path.read_bytes()
        path.write_bytes({"garbage": b"not a zip", "zero_bytes": b"", "truncated": data[: len(data) // 2]}.get(damage, b""))
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
        from stereorepro.render import read_exr

        out, _ = first_run
        run_experiment(ExperimentConfig(out=str(tmp_path), cache_dir=str(out / "cache"), exr=True,
                                        **dict(SMALL, frames=1)))
        ch = read_exr(tmp_path / "exr" / "0000_left.exr")
        assert {"R", "G", "B", "Z", "N.X", "N.Y", "N.Z"} <= set(ch) and ch["R"].shape == (27, 48)

    def test_exceptions(self, tmp_path):
        out = tmp_path / "never"
        for bad, match in ((dict(ladder_spp=1), "ladder_spp"), (dict(frames=10_000), "frames"),
                           (dict(alphas=(float("nan"),)), "alphas"), (dict(workers=0), "workers"),
                           (dict(scene=str(tmp_path / "missing.toml")), "not found")):
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
