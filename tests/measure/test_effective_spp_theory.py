"""End-to-end check of reprojection + effective spp against theory (how high stereo-only effective spp can go):
bilinear reuse of one 1-spp image with independent pixel noise has variance σ²·Σw². A parallel rig maps
rows onto rows, so the two taps lie on one row: E[Σw²] = E[(1−f)² + f²] = 2/3 for uniform sub-pixel offsets f,
and the effective spp is 1.5 (no blur bias on a constant-colour surface)."""

import math

import torch

from stereorepro import PinholeCamera, StereoRig, View, effective_spp_many, look_at, rmse, stereo_reproject


def _tilted_wall(H, W, K, head):
    """Depth and normal of the plane x·0.6 + z·0.8 = 4 (world), seen by ``head``-relative cameras."""
    cam = PinholeCamera(K, head, H, W)
    d = cam.ray_directions()
    o = cam.center_world.view(1, 3, 1, 1)
    n = torch.tensor([0.6, 0.0, 0.8], dtype=d.dtype).view(1, 3, 1, 1)
    t = (4.0 - (n * o).sum(1, keepdim=True)) / (n * d).sum(1, keepdim=True)
    return t, (-n).expand(1, 3, H, W).clone()


def test_stereo_effective_spp_is_one_and_a_half():
    H, W = 120, 160
    g = torch.Generator().manual_seed(0)
    K = torch.tensor([[[100.0, 0, 80], [0, 100.0, 60], [0, 0, 1]]], dtype=torch.float64)
    head = look_at(
        torch.zeros(1, 3, dtype=torch.float64),
        torch.tensor([[0.0, 0.0, 5.0]], dtype=torch.float64),
        torch.tensor([[0.0, -1.0, 0.0]], dtype=torch.float64),
    )
    left, right = StereoRig(0.3).cameras(head, K, H, W)  # wide baseline: disparities of many pixels
    depth_l, normal_l = _tilted_wall(H, W, K, left.cam_from_world)
    depth_r, normal_r = _tilted_wall(H, W, K, right.cam_from_world)
    sigma, truth = 0.1, 0.5
    right_1spp = truth + sigma * torch.randn(1, 3, H, W, generator=g, dtype=torch.float64)
    left_1spp = truth + sigma * torch.randn(1, 3, H, W, generator=g, dtype=torch.float64)
    src, dst = View(depth_r, normal_r, K, right.cam_from_world), View(depth_l, normal_l, K, left.cam_from_world)
    out, valid, *_ = stereo_reproject(right_1spp, src, dst, (1.0, 0.1))
    out = torch.where(valid, out, left_1spp)  # discarded pixels are traced
    assert valid.float().mean() > 0.9
    reference = torch.full_like(out, truth)
    ladder_spp = torch.arange(1, 9, dtype=torch.float64)
    ladder_rmse = torch.tensor([sigma / math.sqrt(n) for n in range(1, 9)], dtype=torch.float64)
    spp, flags = effective_spp_many(rmse(out, reference), ladder_spp, ladder_rmse)
    # 3·H·W = 57600 samples: the MSE estimate has ~0.6 % relative spread; discards (traced at 1 spp) pull it down
    assert 1.40 < float(spp[0]) < 1.56, float(spp[0])
    # nearest sampling reuses one sample: no variance reduction
    near, valid_n, *_ = stereo_reproject(right_1spp, src, dst, (1.0, 0.1), sampling="nearest")
    near = torch.where(valid_n, near, left_1spp)
    spp_n, _ = effective_spp_many(rmse(near, reference), ladder_spp, ladder_rmse)
    assert 0.95 < float(spp_n[0]) < 1.05
