"""Tests for stereorepro.measure.temporal: the reference-relative warping error.

Sequences are the analytic scene of stereorepro._testing seen by a camera that moves between two frames (every
pixel has a surface there), or a fronto-parallel plane seen by a static camera. Independent Gaussian noise of
standard deviation SIGMA per frame over a static camera gives SIGMA·√2 in expectation; the mean of d² over
P = 3·H·W values has a relative standard deviation of sqrt(2 / P), the RMSE half of it, and tolerances are stated
as multiples of that.
"""

from __future__ import annotations

import math

import pytest
import torch

from stereorepro import PinholeCamera, View, backward_reproject, intrinsics_from_fov, look_at
from stereorepro._testing import default_scene, raycast
from stereorepro.errors import ParameterError, ParameterTypeError, ShapeError
from stereorepro.measure import temporal_error

F64 = torch.float64
SIGMA = 0.05
#: Accept tests of the moving-camera sequence: loose enough that all but the disoccluded pixels pass.
THR = (0.2, 0.5)


def _static_view(h=64, w=64, batch=1, dtype=torch.float32) -> View:
    """A camera looking at a fronto-parallel plane 2 units away: the warp between two frames is the identity."""
    depth = torch.full((batch, 1, h, w), 2.0, dtype=dtype)
    normal = torch.zeros(batch, 3, h, w, dtype=dtype)
    normal[:, 2] = -1
    K = intrinsics_from_fov(60.0, w, h, batch, dtype=dtype)
    return View(depth, normal, K, torch.eye(4, dtype=dtype).expand(batch, 4, 4))


def _camera(x: float, h: int, w: int) -> PinholeCamera:
    eye = torch.tensor([[x, 1.4, 1.5]], dtype=F64)
    cam_from_world = look_at(
        eye, torch.tensor([[0.0, 0.8, -3.0]], dtype=F64), torch.tensor([[0.0, 1.0, 0.0]], dtype=F64)
    )
    return PinholeCamera(intrinsics_from_fov(60.0, w, h, dtype=F64), cam_from_world, h, w)


def _moving(h=48, w=64, dtype=torch.float32):
    """Two frames of the analytic scene, the camera moved 10 cm sideways: (view, prev_view, colour, prev_colour),
    the colours noise-free (a converged render of each frame)."""
    cur, prev = _camera(0.3, h, w), _camera(0.2, h, w)
    scene = default_scene()
    g, gp = raycast(cur, scene), raycast(prev, scene)

    def view(gb, cam):
        return View(gb.depth.to(dtype), gb.normal.to(dtype), cam.K.to(dtype), cam.cam_from_world.to(dtype))

    return view(g, cur), view(gp, prev), g.color.to(dtype), gp.color.to(dtype)


def _noise(like: torch.Tensor, gen: torch.Generator) -> torch.Tensor:
    return SIGMA * torch.randn(like.shape, generator=gen, dtype=like.dtype)


class TestTemporalError:
    def test_smoke(self):
        view = _static_view()
        ref = torch.full((1, 3, 64, 64), 0.5)
        out = temporal_error(ref, ref, ref, ref, view, view, THR)
        assert out.shape == (1,) and out.dtype == F64
        assert out.tolist() == [0.0]

    def test_cardinality(self):
        view = _static_view(8, 10, batch=3)
        img = torch.rand(3, 3, 8, 10, generator=torch.Generator().manual_seed(0))
        assert temporal_error(img, img[:1], img, img[:1], view, view, THR).shape == (3,)  # references broadcast
        empty = _static_view(8, 10, batch=3)
        empty = View(empty.depth[:0], empty.normal[:0], empty.K[:0], empty.cam_from_world[:0])
        assert temporal_error(img[:0], img[:1], img[:0], img[:1], empty, empty, THR).shape == (0,)

    def test_static_noise_flickers(self):
        """Independent noise per frame over a static camera: SIGMA·√2, the difference of two independent samples."""
        h = w = 128
        view = _static_view(h, w)
        gen = torch.Generator().manual_seed(1)
        ref = torch.full((1, 3, h, w), 0.5, dtype=F64)
        frames = [ref + _noise(ref, gen) for _ in range(2)]  # 10 SIGMA from the clamp: clamping changes nothing
        err = float(temporal_error(frames[1], ref, frames[0], ref, view, view, THR)[0])
        expected = SIGMA * math.sqrt(2.0)
        assert err == pytest.approx(expected, rel=4 * math.sqrt(2.0 / (3 * h * w)) / 2)
        assert err == pytest.approx(0.07062, abs=5e-5)  # this seed's value

    def test_constant_sequence_is_steady(self):
        view = _static_view()
        gen = torch.Generator().manual_seed(2)
        ref = torch.rand(1, 3, 64, 64, generator=gen)
        assert float(temporal_error(ref, ref, ref, ref, view, view, THR)[0]) == 0.0
        noisy = ref + _noise(ref, gen)  # the same noise in both frames: a steady (if wrong) image
        assert float(temporal_error(noisy, ref, noisy, ref, view, view, THR, tonemap="none")[0]) == 0.0

    def test_camera_motion_alone_is_not_flicker(self):
        view, prev_view, color, prev_color = _moving()
        warped = backward_reproject(prev_color, prev_view, view, THR)
        assert warped.valid.float().mean() > 0.9
        # the motion is real: the plain warping error of the converged image alone is not 0
        naive = (color - warped.values)[warped.valid.expand(-1, 3, -1, -1)].pow(2).mean().sqrt()
        assert naive > 5e-3
        assert float(temporal_error(color, color, prev_color, prev_color, view, prev_view, THR)[0]) == 0.0
        # a steady bias (an image 0.1 brighter than the reference in every frame) is no flicker either
        err = temporal_error(color + 0.1, color, prev_color + 0.1, prev_color, view, prev_view, THR, tonemap="none")
        assert float(err[0]) < 1e-6

    def test_noise_under_camera_motion_flickers(self):
        view, prev_view, color, prev_color = _moving()
        gen = torch.Generator().manual_seed(3)
        err = float(temporal_error(color + _noise(color, gen), color, prev_color + _noise(color, gen), prev_color,
                                   view, prev_view, THR, tonemap="none")[0])  # fmt: skip
        # bilinear resampling averages the previous frame's noise: between SIGMA·√(5/4) and SIGMA·√2
        assert SIGMA * math.sqrt(1.25) * 0.97 < err < SIGMA * math.sqrt(2.0) * 1.03

    def test_disoccluded_and_background_pixels_are_excluded(self):
        view, prev_view, color, prev_color = _moving()
        sky = torch.zeros_like(view.depth, dtype=torch.bool)
        sky[..., :4, :] = True  # the top rows see no surface in the current frame
        view = View(view.depth.masked_fill(sky, math.inf), view.normal.masked_fill(sky, 0.0), view.K,
                    view.cam_from_world)  # fmt: skip
        valid = backward_reproject(prev_color, prev_view, view, THR).valid
        assert not bool(valid[sky].any()) and bool((~valid & ~sky).any())  # background and disocclusions
        gen = torch.Generator().manual_seed(4)
        image, prev_image = color + _noise(color, gen), prev_color + _noise(color, gen)
        err = temporal_error(image, color, prev_image, prev_color, view, prev_view, THR, tonemap="none")
        # anything at the excluded pixels leaves the value unchanged
        garbage = torch.where(valid, image, torch.full_like(image, 100.0))
        again = temporal_error(garbage, color, prev_image, prev_color, view, prev_view, THR, tonemap="none")
        assert torch.equal(err, again)
        # and the value is the mean over exactly the valid pixels
        w = backward_reproject(torch.cat([prev_image, prev_color], 1), prev_view, view, THR).values
        d = (image - w[:, :3]) - (color - w[:, 3:])
        manual = d.double().pow(2)[valid.expand(-1, 3, -1, -1)].mean().sqrt()
        assert float(err[0]) == pytest.approx(float(manual), rel=1e-6)

    def test_no_valid_pixel_gives_nan(self):
        view = _static_view(8, 8, batch=2)
        depth = view.depth.clone()
        depth[1] = math.inf  # the second item sees no surface at all
        view = View(depth, view.normal, view.K, view.cam_from_world)
        img = torch.full((2, 3, 8, 8), 0.5)
        out = temporal_error(img, img, img, img, view, view, THR)
        assert out[0] == 0.0 and math.isnan(out[1])

    def test_tonemap_clamp(self):
        """The default clamps to [0, 1] like the other LDR metrics: flicker above white is not seen."""
        view = _static_view(8, 8)
        ref = torch.full((1, 3, 8, 8), 0.5)
        bright = torch.full((1, 3, 8, 8), 3.0)
        assert float(temporal_error(bright, ref, bright + 1.0, ref, view, view, THR)[0]) == 0.0
        assert float(temporal_error(bright, ref, bright + 1.0, ref, view, view, THR, tonemap="none")[0]) == 1.0

    def test_exception(self):
        view = _static_view(8, 8)
        img = torch.rand(1, 3, 8, 8)
        with pytest.raises(ParameterError, match="tonemap must be one of"):
            temporal_error(img, img, img, img, view, view, THR, tonemap="reinhard")
        with pytest.raises(ShapeError, match="prev_image"):
            temporal_error(img, img, img[..., :7], img, view, view, THR)
        with pytest.raises(ShapeError, match=r"image \(sizes of view\)"):
            temporal_error(img[..., :7], img[..., :7], img, img, view, view, THR)
        with pytest.raises(ShapeError, match="prev_image"):
            temporal_error(img, img, img[:, :2], img[:, :2], view, view, THR)  # channels differ
        with pytest.raises(ShapeError, match="reference"):
            temporal_error(img, img.expand(2, -1, -1, -1), img, img, view, view, THR)
        with pytest.raises(ShapeError):
            temporal_error(img[0], img, img, img, view, view, THR)
        with pytest.raises(ParameterTypeError, match="prev_view"):
            temporal_error(img, img, img, img, view, (view.depth, view.normal), THR)
        with pytest.raises(ParameterTypeError, match="floating"):
            temporal_error((img * 255).to(torch.uint8), img, img, img, view, view, THR)
        bad = img.clone()
        bad[0, 1, 2, 3] = math.nan
        with pytest.raises(ParameterError, match="prev_reference has 1 non-finite"):
            temporal_error(img, img, img, bad, view, view, THR)
        with pytest.raises(ParameterError, match="thresholds|threshold"):
            temporal_error(img, img, img, img, view, view, (-1.0, 0.5))

    def test_gradcheck(self):
        view, prev_view, color, prev_color = _moving(6, 8, dtype=F64)
        gen = torch.Generator().manual_seed(5)
        image = (color + _noise(color, gen)).requires_grad_()
        prev_image = (prev_color + _noise(color, gen)).requires_grad_()

        def loss(image, prev_image):
            return temporal_error(image, color, prev_image, prev_color, view, prev_view, THR)

        assert torch.autograd.gradcheck(loss, (image, prev_image), eps=1e-6, atol=1e-8)
        loss(image, prev_image).sum().backward()
        assert torch.isfinite(image.grad).all() and image.grad.abs().sum() > 0
