import math

import pytest
import torch

from stereorepro import PinholeCamera, StereoRig, has_surface, intrinsics_from_fov, invert_rigid, look_at
from stereorepro.camera import inverse_intrinsics, pixel_centers, project, unproject


def _head(dtype=torch.float64):
    eye = torch.tensor([[1.0, 2.0, 3.0]], dtype=dtype)
    return look_at(eye, torch.tensor([[0.0, 1.0, -2.0]], dtype=dtype), torch.tensor([[0.0, 1.0, 0.0]], dtype=dtype))


class TestConventions:
    def test_has_surface(self):
        d = torch.tensor([1.0, 0.0, -1.0, float("nan"), float("inf"), -float("inf"), 1e-30])
        assert has_surface(d).tolist() == [True, False, False, False, False, False, True]

    def test_pixel_centers(self):
        uv = pixel_centers(2, 3)
        assert uv.shape == (2, 2, 3)
        assert uv[0, 0].tolist() == [0.5, 1.5, 2.5] and uv[1, :, 0].tolist() == [0.5, 1.5]

    def test_look_at_opencv_axes(self):
        T = look_at(torch.zeros(1, 3), torch.tensor([[0.0, 0.0, -1.0]]), torch.tensor([[0.0, 1.0, 0.0]]))
        # world -z is camera +z (forward), world +x is camera +x (right), world +y is camera -y (up = -down)
        assert torch.allclose(T[0, :3, :3], torch.tensor([[1.0, 0, 0], [0, -1, 0], [0, 0, -1]]))

    def test_look_at_parallel_up_raises(self):
        with pytest.raises(ValueError, match="parallel"):
            look_at(torch.zeros(1, 3), torch.tensor([[0.0, 1.0, 0.0]]), torch.tensor([[0.0, 1.0, 0.0]]))

    def test_invert_rigid(self):
        T = _head()
        assert torch.allclose(invert_rigid(T) @ T, torch.eye(4, dtype=T.dtype)[None], atol=1e-12)

    def test_inverse_intrinsics(self):
        K = torch.tensor([[[500.0, 2.0, 320.5], [0.0, 480.0, 240.25], [0.0, 0.0, 1.0]]], dtype=torch.float64)
        assert torch.allclose(inverse_intrinsics(K), torch.linalg.inv(K), atol=1e-15)

    def test_project_unproject_roundtrip(self):
        K = intrinsics_from_fov(50.0, 7, 5, dtype=torch.float64)
        depth = torch.rand(1, 1, 5, 7, dtype=torch.float64) + 0.5
        uv, z = project(unproject(depth, K), K)
        assert torch.allclose(uv, pixel_centers(5, 7, dtype=torch.float64)[None], atol=1e-12)
        assert torch.allclose(z, depth)

    def test_depth_is_camera_z_not_ray_length(self):
        cam = PinholeCamera(intrinsics_from_fov(90.0, 4, 4, dtype=torch.float64), _head(), 4, 4)
        depth = torch.full((1, 1, 4, 4), 2.0, dtype=torch.float64)
        pts = cam.unproject(depth)
        _, z = cam.project(pts)
        assert torch.allclose(z, depth)
        # ray_directions are scaled to camera z = 1
        d = cam.ray_directions()
        p = cam.center_world.view(1, 3, 1, 1) + 2.0 * d
        assert torch.allclose(p, pts, atol=1e-12)

    def test_intrinsics_fov(self):
        K = intrinsics_from_fov(90.0, 200, 100)
        assert math.isclose(K[0, 0, 0].item(), 50.0, rel_tol=1e-6) and K[0, 0, 2] == 100 and K[0, 1, 2] == 50
        with pytest.raises(ValueError):
            intrinsics_from_fov(0.0, 10, 10)


class TestStereoRig:
    def test_parallel_rig_baseline_and_rows(self):
        K = intrinsics_from_fov(60.0, 64, 48, dtype=torch.float64)
        left, right = StereoRig(0.065).cameras(_head(), K, 48, 64)
        assert torch.allclose((left.center_world - right.center_world).norm(), torch.tensor(0.065, dtype=torch.float64))
        # parallel: same rotation, so a point maps to the same row in both eyes
        assert torch.allclose(left.cam_from_world[:, :3, :3], right.cam_from_world[:, :3, :3])
        pts = left.unproject(torch.full((1, 1, 48, 64), 3.0, dtype=torch.float64))
        uv_r, _ = right.project(pts)
        uv_l, _ = left.project(pts)
        assert torch.allclose(uv_r[:, 1], uv_l[:, 1], atol=1e-9)
        assert (uv_r[:, 0] < uv_l[:, 0]).all()  # right eye sees points further left

    def test_convergence_by_sensor_shift(self):
        K = intrinsics_from_fov(60.0, 64, 48, dtype=torch.float64)
        head = _head()
        left, right = StereoRig(0.065, convergence_distance=2.0).cameras(head, K, 48, 64)
        head_cam = PinholeCamera(K, head, 48, 64)
        p = head_cam.unproject(torch.full((1, 1, 48, 64), 2.0, dtype=torch.float64))[:, :, 24:25, 32:33]
        ul, _ = left.project(p)
        ur, _ = right.project(p)
        assert torch.allclose(ul, ur, atol=1e-9)  # zero disparity at the convergence distance

    def test_default_baseline(self):
        from stereorepro.camera import DEFAULT_BASELINE

        assert StereoRig().eye_separation == DEFAULT_BASELINE == 0.065

    def test_exceptions(self):
        with pytest.raises(ValueError):
            StereoRig(-1.0)
        with pytest.raises(ValueError, match="K"):
            StereoRig().cameras(_head(), torch.eye(3), 4, 4)
        with pytest.raises(ValueError, match="cam_from_world"):
            PinholeCamera(torch.eye(3)[None], torch.eye(3)[None], 4, 4)


class TestEye:
    """One eye type: a string enum whose names are the file/JSON/CLI names and whose int is the index."""

    def test_names_and_indices(self):
        import json

        from stereorepro.camera import Eye

        assert list(Eye) == ["left", "right"] and [int(e) for e in Eye] == [0, 1]
        assert {"left": 0, "right": 1}[Eye.RIGHT] == 1 and Eye.LEFT in ("left",)  # equal and same hash as names
        assert f"{7:04d}_{Eye.LEFT}.exr" == "0007_left.exr" and str(Eye.RIGHT) == "right"
        assert json.dumps({Eye.LEFT: Eye.RIGHT}) == '{"left": "right"}'
        assert Eye.LEFT.other is Eye.RIGHT and Eye.RIGHT.other is Eye.LEFT

    def test_constructor(self):
        import numpy as np

        from stereorepro.camera import Eye

        for e in Eye:
            assert Eye(e) is e and Eye(e.value) is e and Eye(int(e)) is e and Eye(np.int64(int(e))) is e
        for bad in ("LEFT", "centre", 2, -1, 1.0, True, None):
            with pytest.raises(ValueError, match="not a valid Eye"):
                Eye(bad)

    def test_index_is_the_rig_order_and_the_rng_field(self):
        from stereorepro.camera import Eye
        from stereorepro.render.rng import stream_key

        K = intrinsics_from_fov(60.0, 64, 48, dtype=torch.float64)
        cams = StereoRig().cameras(_head(), K, 48, 64)
        head_x_axis = invert_rigid(_head())[0, :3, 0]  # the head's x axis in world coordinates
        assert ((cams[int(Eye.RIGHT)].center_world - cams[int(Eye.LEFT)].center_world) @ head_x_axis).item() > 0
        assert [stream_key(7, 3, e) for e in Eye] == [stream_key(7, 3, 0), stream_key(7, 3, 1)]


class TestJitter:
    """Halton (2, 3) sub-pixel jitter and the jittered camera's sign convention (stereorepro.camera)."""

    def test_halton_known_values(self):
        from fractions import Fraction

        from stereorepro.camera import halton

        assert [halton(i, 2) for i in range(8)] == [0.0, 0.5, 0.25, 0.75, 0.125, 0.625, 0.375, 0.875]
        third = [Fraction(k, 3) for k in (0, 1, 2)] + [Fraction(k, 9) for k in (1, 4, 7, 2, 5, 8)]
        assert [halton(i, 3) for i in range(9)] == [float(f) for f in third]  # the nearest floats, exactly
        assert halton(5, 10) == 0.5 and halton(123, 10) == float(Fraction(321, 1000))
        assert halton(2**60 - 1, 2) < 1.0 and halton(3**40 - 1, 3) < 1.0  # never 1.0, however large the index
        assert halton(2**60, 2) == 2.0**-61

    def test_jitter_offset_range_period_and_values(self):
        from stereorepro.camera import halton, jitter_offset

        assert jitter_offset(0) == (0.0, float(1 / 3) - 0.5)
        assert jitter_offset(1) == (-0.25, 2 / 3 - 0.5) and jitter_offset(2) == (0.25, halton(3, 3) - 0.5)
        for length in (1, 2, 8, 16, 17):
            offs = [jitter_offset(f, length) for f in range(-length, 3 * length)]
            assert all(-0.5 <= v < 0.5 for o in offs for v in o)
            assert offs[:length] == offs[length : 2 * length] == offs[2 * length : 3 * length]  # period, negative too
            assert len(set(offs[:length])) == length
        seq = torch.tensor([jitter_offset(f) for f in range(16)], dtype=torch.float64)
        assert seq.mean(0).abs().max() < 0.05  # well spread about the pixel centre
        assert jitter_offset(torch.tensor(3)) == jitter_offset(3)  # integer tensors and numpy ints are integers

    @pytest.mark.parametrize("dx, dy", [(0.25, -1 / 6), (-0.49, 0.3), (0.0, 0.0), (2.0, -3.5)])
    def test_jittered_projection_convention(self, dx, dy):
        """A world point at uv in the camera is at uv - (dx, dy) in the jittered one (skew included), and the
        jittered pixel centres look along the camera's rays through centres + (dx, dy)."""
        K = torch.tensor([[[300.0, 1.5, 33.0], [0.0, 280.0, 21.0], [0.0, 0.0, 1.0]]], dtype=torch.float64)
        cam = PinholeCamera(K, _head(), 40, 64)
        jit = cam.jittered(dx, dy)
        pts = cam.unproject(
            torch.rand(1, 1, 40, 64, dtype=torch.float64, generator=torch.Generator().manual_seed(0)) * 5 + 0.5
        )
        uv, z = cam.project(pts)
        uv_j, z_j = jit.project(pts)
        shift = torch.tensor([dx, dy], dtype=torch.float64).view(1, 2, 1, 1)
        assert torch.allclose(uv_j, uv - shift, atol=1e-9, rtol=0) and torch.equal(z_j, z)
        want = cam.ray_directions(jitter=shift.expand(1, 2, 40, 64))
        assert torch.allclose(jit.ray_directions(), want, atol=1e-12, rtol=0)
        assert torch.equal(jit.cam_from_world, cam.cam_from_world)
        keep = torch.ones(3, 3, dtype=torch.bool)
        keep[0, 2] = keep[1, 2] = False
        assert torch.equal(jit.K[0][keep], K[0][keep])  # only the principal point moves
        assert jit.K[0, 0, 2] == 33.0 - dx and jit.K[0, 1, 2] == 21.0 - dy and K[0, 0, 2] == 33.0  # K not modified

    def test_jittered_stereo_pair_stays_rectified(self):
        from stereorepro.camera import compose_warp, jitter_offset, rectify_warp

        K = intrinsics_from_fov(60.0, 64, 48, dtype=torch.float64)
        left, right = StereoRig(0.065).cameras(_head(), K, 48, 64)
        d = jitter_offset(5)
        jl, jr = left.jittered(*d), right.jittered(*d)  # both eyes alike
        warp = compose_warp(jr.K, jr.cam_from_world, jl.K, jl.cam_from_world, torch.float64)
        rectify_warp(warp, 48, 64)  # raises CameraError for a pair that is not rectified
        assert torch.equal(warp.pixel_src_from_pixel_dst[0, 1:], torch.eye(3, dtype=torch.float64)[1:])

    def test_jitter_gradients_reach_K(self):
        from stereorepro.camera import jitter_intrinsics

        K = intrinsics_from_fov(60.0, 8, 6, dtype=torch.float64).requires_grad_()
        jitter_intrinsics(K, 0.25, -0.125).sum().backward()
        assert torch.equal(K.grad, torch.ones_like(K))

    def test_jitter_exceptions(self):
        from stereorepro.camera import halton, jitter_intrinsics, jitter_offset

        cam = PinholeCamera(intrinsics_from_fov(60.0, 8, 6), _head(torch.float32), 6, 8)
        for bad in (float("nan"), float("inf"), -float("inf"), torch.tensor(float("nan"))):
            with pytest.raises(ValueError, match=r"jitter: dx \(pixels\): expected a finite number"):
                cam.jittered(bad, 0.0)
            with pytest.raises(ValueError, match=r"jitter: dy \(pixels\): expected a finite number"):
                jitter_intrinsics(cam.K, 0.0, bad)
        for bad in ("0.5", None, [0.5], True):
            with pytest.raises(TypeError, match="dx"):
                cam.jittered(bad, 0.0)
        with pytest.raises(ValueError, match="dx"):
            cam.jittered(torch.tensor([0.1, 0.2]), 0.0)
        with pytest.raises(ValueError, match="K"):
            jitter_intrinsics(torch.eye(3), 0.1, 0.1)
        with pytest.raises(ValueError, match="index must be >= 0"):
            halton(-1, 2)
        with pytest.raises(ValueError, match="base must be >= 2"):
            halton(1, 1)
        for bad in (1.0, True, "1", None):
            with pytest.raises(TypeError, match="halton: index"):
                halton(bad, 2)
            with pytest.raises(TypeError, match="jitter_offset: frame"):
                jitter_offset(bad)
        with pytest.raises(TypeError, match="halton: base"):
            halton(1, 2.0)
        with pytest.raises(ValueError, match="length must be >= 1"):
            jitter_offset(0, 0)
        with pytest.raises(TypeError, match="jitter_offset: length"):
            jitter_offset(0, 16.0)


class TestCameraMotion:
    """stereorepro.camera.camera_motion: the motion of static geometry from two cameras, and its checks."""

    @staticmethod
    def _inputs(batch=1):
        depth = torch.full((batch, 1, 6, 8), 2.0)
        K = intrinsics_from_fov(60.0, 8, 6).repeat(batch, 1, 1)
        T = torch.eye(4)[None].repeat(batch, 1, 1)
        return depth, K, T

    def test_smoke(self):
        from stereorepro import camera_motion

        depth, K, T = self._inputs()
        prev = T.clone()
        prev[:, 0, 3] = 0.1  # the previous camera 0.1 to the left: the points were further right in its image
        mv = camera_motion(depth, K, T, K, prev)
        assert mv.shape == (1, 2, 6, 8) and bool((mv[:, 0] > 0).all()) and float(mv[:, 1].abs().max()) < 1e-6

    def test_exceptions(self):
        """Singular intrinsics, a scaled extrinsic and a batch mismatch raise naming the argument (K*0 returned
        all-NaN motion, the scaled camera a wrong one, the batch mismatch torch's broadcasting error)."""
        from stereorepro import CameraError, ShapeError, camera_motion

        depth, K, T = self._inputs()
        with pytest.raises(CameraError, match=r"camera_motion: K\[0\]: focal lengths must be > 0"):
            camera_motion(depth, K * 0, T, K, T)
        with pytest.raises(CameraError, match=r"camera_motion: prev_K\[0\]"):
            camera_motion(depth, K, T, K * 0, T)
        scaled = T.clone()
        scaled[:, :3, :3] *= 2.0
        with pytest.raises(CameraError, match=r"camera_motion: cam_from_world\[0\]: .*scaled"):
            camera_motion(depth, K, scaled, K, T)
        with pytest.raises(CameraError, match=r"camera_motion: prev_cam_from_world\[0\]"):
            camera_motion(depth, K, T, K, scaled)
        _, K2, T2 = self._inputs(2)
        with pytest.raises(ShapeError, match=r"camera_motion: K: expected shape \(B, 3, 3\) with B=1"):
            camera_motion(depth, K2, T, K, T)
        with pytest.raises(ShapeError, match="camera_motion: prev_cam_from_world"):
            camera_motion(depth, K, T, K, T2)
        with pytest.raises(TypeError, match="camera_motion: depth: expected a floating"):
            camera_motion(depth.int(), K, T, K, T)
