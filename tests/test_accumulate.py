"""SpatiotemporalReprojection: the paper's combined scheme, driven over analytic frames."""

import pytest
import torch

from stereorepro import PinholeCamera, SpatiotemporalReprojection, stereo_reproject, temporal_reproject
from stereorepro.synthetic import camera_pair, default_scene, raycast

H, W = 36, 48
THR = (0.2, 0.3)  # ~1.5 pixel footprints at these sizes


def _left_of(right_cam):
    """The left eye of the same head: 0.065 units to the left along the camera's x axis."""
    T = right_cam.cam_from_world.clone()
    T[:, 0, 3] += 0.065
    return PinholeCamera(right_cam.K, T, right_cam.height, right_cam.width)


def frame(i):
    """Left/right G-buffers and noisy 1-spp-like colours of frame i (the head moves forward and turns)."""
    _, right = camera_pair(H, W, baseline=0.065, forward=0.03 * i, yaw_deg=0.3 * i)
    scene = default_scene()
    g = torch.Generator().manual_seed(1000 * i)
    out = {}
    for eye, cam in (("left", _left_of(right)), ("right", right)):
        gb = raycast(cam, scene)
        noisy = gb["color"] * (2 * torch.rand(gb["color"].shape, generator=g, dtype=torch.float64))
        out[eye] = dict(color=noisy.float(), clean=gb["color"].float(), depth=gb["depth"].float(),
                        normal=gb["normal"].float(), K=cam.K, cam_from_world=cam.cam_from_world)
    return out


def run_sequence(st, n=4):
    outs = []
    for i in range(n):
        f = frame(i)
        r, lf = f["right"], f["left"]
        right = st.right(r["color"], r["depth"], r["normal"], r["K"], r["cam_from_world"])
        mask = st.left_trace_mask(lf["depth"], lf["normal"], lf["K"], lf["cam_from_world"])
        left = st.left(torch.where(mask, lf["color"], torch.full_like(lf["color"], float("nan"))))
        outs.append((f, right, mask, left))
    return outs


class TestSpatiotemporalReprojection:
    def test_smoke(self):
        outs = run_sequence(SpatiotemporalReprojection(*THR), n=2)
        f, right, mask, left = outs[-1]
        assert right.shape == left.shape == (1, 3, H, W) and mask.dtype == torch.bool

    def test_trace_mask_is_stereo_discard(self):
        st = SpatiotemporalReprojection(*THR, temporal=False)
        f, right, mask, left = run_sequence(st, n=1)[0]
        r, lf = f["right"], f["left"]
        ref, valid, _ = stereo_reproject(r["color"], r["depth"], r["normal"], r["K"], r["cam_from_world"],
                                         lf["depth"], lf["normal"], lf["K"], lf["cam_from_world"], *THR)
        assert torch.equal(mask, ~valid) and 0 < mask.float().mean() < 0.3
        # stereo only: kept pixels are the reprojection, discarded ones the traced samples (only those are read)
        assert torch.equal(left, torch.where(valid, ref, lf["color"]))
        assert torch.isfinite(left).all()

    def test_stereo_off_traces_everything(self):
        st = SpatiotemporalReprojection(*THR, stereo=False, temporal=False)
        f, right, mask, left = run_sequence(st, n=1)[0]
        assert mask.all() and torch.equal(left, f["left"]["color"])

    def test_temporal_right_matches_module(self):
        st = SpatiotemporalReprojection(*THR)
        outs = run_sequence(st, n=2)
        f0, right0, *_ = outs[0]
        f1, right1, *_ = outs[1]
        r0, r1 = f0["right"], f1["right"]
        ref, n, valid = temporal_reproject(r1["color"], r1["depth"], r1["normal"], r1["K"], r1["cam_from_world"],
                                           right0, torch.ones_like(r0["depth"]), r0["depth"], r0["normal"],
                                           r0["K"], r0["cam_from_world"], *THR)
        assert torch.equal(right1, ref) and torch.equal(st.right_valid, valid)

    def test_accumulation_reduces_error(self):
        st = SpatiotemporalReprojection(*THR)
        outs = run_sequence(st, n=6)
        f, right, mask, left = outs[-1]
        for eye, img in (("right", right), ("left", left)):
            clean, noisy = f[eye]["clean"], f[eye]["color"]
            err_acc = ((img - clean) ** 2).mean()
            err_1spp = ((noisy - clean) ** 2).mean()
            assert err_acc < 0.5 * err_1spp, eye

    def test_order_errors(self):
        st = SpatiotemporalReprojection(*THR)
        with pytest.raises(RuntimeError, match="right"):
            st.left_trace_mask(torch.ones(1, 1, 2, 2), torch.ones(1, 3, 2, 2), torch.eye(3)[None], torch.eye(4)[None])
        with pytest.raises(RuntimeError, match="left_trace_mask"):
            st.left(torch.zeros(1, 3, 2, 2))

    def test_misordered_calls_raise_instead_of_black_left_eye(self):
        st = SpatiotemporalReprojection(*THR)
        f = frame(0)
        r, lf = f["right"], f["left"]
        st.right(r["color"], r["depth"], r["normal"], r["K"], r["cam_from_world"])
        st.left_trace_mask(lf["depth"], lf["normal"], lf["K"], lf["cam_from_world"])
        st.right(r["color"], r["depth"], r["normal"], r["K"], r["cam_from_world"])  # a new frame began
        with pytest.raises(RuntimeError, match="left_trace_mask"):
            st.left(lf["color"])
        st.left_trace_mask(lf["depth"], lf["normal"], lf["K"], lf["cam_from_world"])
        with pytest.raises(ValueError, match="traced_color"):
            st.left(torch.cat([lf["color"], lf["color"]]))  # batch of 2 against a batch of 1
        with pytest.raises(ValueError, match="depth"):
            st.right(r["color"], r["depth"][..., :-1], r["normal"], r["K"], r["cam_from_world"])

    def test_reset(self):
        st = SpatiotemporalReprojection(*THR)
        run_sequence(st, n=2)
        st.reset()
        assert st.right_state is None and st.left_state is None
