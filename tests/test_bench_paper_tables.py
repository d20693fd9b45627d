"""bench/paper_tables.py (the 720p tables from finished runs): the resampling-bias and FLIP/SSIM sections."""

from __future__ import annotations

from conftest import load_script

pt = load_script("bench", "paper_tables")


def _stat(x: float) -> dict:
    return {"avg": x, "min": x, "max": x, "n": 15, "avg_after_warmup": x}


def _bias(share: float, without_noise: float, edge_pixels: float, edge_bias: float) -> dict:
    return {
        "bias_share": _stat(share),
        "bias_share_without_reference_noise": _stat(without_noise),
        "anatomy": {"edge": {"pixels_pct": _stat(edge_pixels), "bias_share_pct": _stat(edge_bias)}},
    }


class TestPaperTables:
    def test_bias_rows(self):
        run = {
            "bias": {"stereo_temporal": _bias(0.028, 0.040, 17.8, 88.4), "temporal": _bias(0.019, 0.027, 17.2, 92.6)}
        }
        lines = pt._bias_lines({"lr": run})
        assert "| lr | temporal | 1.9 % | 2.7 % | 17.2 % | 92.6 % |" in lines
        assert "| lr | stereo_temporal | 2.8 % | 4.0 % | 17.8 % | 88.4 % |" in lines
        assert not any("| stereo |" in x for x in lines)  # a scheme without a bias measurement has no row
        assert pt._bias_lines({"lr": {"bias": {}}}) == []

    def test_flip_and_ssim(self):
        a = {
            "flip": {"stereo": _stat(0.25), "stereo_temporal_clamp": _stat(0.125)},
            "ssim": {"stereo": _stat(0.5)},
            "perceptual_every": 4,
        }
        b = {"flip": {"stereo": _stat(0.375)}, "ssim": None, "perceptual_every": 1}
        lines = pt._perceptual_lines({"a": a, "b": b})
        assert "K = a: 4, b: 1" in lines[1]
        assert "| stereo | 0.2500 | 0.5000 | 0.3750 | – |" in lines
        assert "| stereo_temporal_clamp | 0.1250 | – | – | – |" in lines
        assert pt._perceptual_lines({"a": {"flip": None, "ssim": None}}) == []

    def test_collect_fills_a_scene_from_another_run(self, tmp_path):
        import json

        import pytest

        def write(name: str, **fields) -> str:
            (tmp_path / name).mkdir()
            (tmp_path / name / "results.json").write_text(json.dumps(fields))
            return str(tmp_path / name)

        a = write("options", scene="lr", table1={"t": 1}, flip=None, ssim=None, perceptual_every=None)
        b = write("flip", scene="lr", table1={"t": 2}, flip={"stereo": _stat(0.25)}, ssim={}, perceptual_every=4)
        c = write("other", scene="cr", table1={"t": 3})
        runs = pt.collect([a, c], fill=[b])
        assert list(runs) == ["lr", "cr"]  # rows are named by scene, in the order given
        assert runs["lr"]["table1"] == {"t": 1}  # the row's own fields stay
        assert runs["lr"]["flip"] == {"stereo": _stat(0.25)} and runs["lr"]["perceptual_every"] == 4
        assert runs["lr"]["filled_from"] == {"flip": b, "perceptual_every": b}  # empty ssim is not filled
        assert runs["lr"]["path"] == a and "filled_from" not in runs["cr"]
        assert pt._sources("lr", runs["lr"]) == f"lr `{a}` (flip, perceptual_every from `{b}`)"
        both = pt.collect([a, b, c])  # two runs of a scene: two rows, named by their folders, nothing filled
        assert list(both) == ["options", "flip", "cr"] and both["options"]["flip"] is None
        with pytest.raises(SystemExit, match="2 runs of scene lr"):
            pt.collect([a, b], fill=[b])
        with pytest.raises(SystemExit, match="0 runs of scene lr"):
            pt.collect([c], fill=[b])

    def test_frames_beyond_the_ladder_are_bounded(self):
        rows = [{"effective_spp": {"s": 8.0}, "flags": {"s": "interpolated"}}] * 10 + [
            {"effective_spp": {"s": 40.0}, "flags": {"s": "extrapolated_high"}}
        ]
        old = {"avg": 10.9, "min": 8.0, "max": 40.0, "n": 11, "avg_after_warmup": 40.0}
        got = {"table2": {}, "table2_variants": {"s": dict(old)}}
        pt._bound_old_results(got, {"per_frame": rows, "ladder_spp": 16})
        st = got["table2_variants"]["s"]
        assert {k: st[k] for k in old} == old  # what the run wrote stays
        assert st["beyond_ladder"] == 1 and st["avg_lower_bound"] == 96.0 / 11
        assert pt._cell(st) == "≥ 8.73 / ≥ 16.00 [8.00, 40.00]"
        assert pt._pair(dict(old, beyond_ladder=0)) == "10.90 / 40.00"
