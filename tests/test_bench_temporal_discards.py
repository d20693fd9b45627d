"""bench/temporal_discards.py (why a scene's temporal discards are what they are): the slowed camera path and the
reason split that its table rests on."""

from __future__ import annotations

import pytest
import torch

from conftest import load_script
from stereorepro import load_scene

td = load_script("bench", "temporal_discards")


class TestTemporalDiscards:
    def test_slowed_path_samples_the_same_path_more_densely(self):
        scene = load_scene("living_room")
        for k in (2, 4):
            slow = td.slowed(scene, k)
            assert slow.num_frames == (scene.num_frames - 1) * k + 1 and scene.num_frames == 60
            for f in (0, 7, scene.num_frames - 1):
                assert torch.allclose(slow.head_pose(k * f), scene.head_pose(f), atol=1e-12)
            # frames between the original ones lie between their poses (the camera moves 1/k as far per frame)
            step = torch.linalg.norm(slow.head_pose(k * 7 + 1) - slow.head_pose(k * 7))
            assert 0 < step < torch.linalg.norm(scene.head_pose(8) - scene.head_pose(7))

    def test_reasons_add_up_and_a_slower_camera_discards_less_out_of_frame(self):
        # the built-in atrium's camera moves backward, as the paper's Sponza does: its discards are mostly out of frame
        fast = td.measure("atrium", 64, 36, 4, 1)
        slow = td.measure("atrium", 64, 36, 4, 4)
        for r in (fast, slow):
            assert r["pairs"] == 3 and len(r["discard_pct_per_frame"]) == 3
            assert sum(r["by_reason_pct"].values()) == pytest.approx(r["discard_pct"], abs=1e-9)
            assert 0 < r["discard_pct"] < 100
        assert slow["translation_per_frame"] == pytest.approx(fast["translation_per_frame"] / 4, rel=0.05)
        assert slow["flow_px720_mean"] < fast["flow_px720_mean"] / 2
        assert fast["by_reason_pct"]["out_of_frame"] > fast["discard_pct"] / 2
        assert slow["by_reason_pct"].get("out_of_frame", 0.0) < fast["by_reason_pct"]["out_of_frame"] / 2

    def test_moving_objects_are_refused(self):
        with pytest.raises(SystemExit, match="moving objects"):
            td.measure("living_room_moving_objects", 16, 9, 2, 1)
