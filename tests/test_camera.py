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

    def test_exceptions(self):
        with pytest.raises(ValueError):
            StereoRig(-1.0)
        with pytest.raises(ValueError, match="K"):
            StereoRig().cameras(_head(), torch.eye(3), 4, 4)
        with pytest.raises(ValueError, match="cam_from_world"):
            PinholeCamera(torch.eye(3)[None], torch.eye(3)[None], 4, 4)
