"""Moving objects in the tracer: per-frame geometry only where declared, and motion vectors against analytic
motion (a plane translating, a cube rotating) and against finite differences of rendered positions."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from conftest_render import camera_looking, write_scene
from stereorepro import camera_motion, load_scene
from stereorepro.errors import SceneError
from stereorepro.render import PathTracer
from stereorepro.scenes.animation import quat_to_matrix, slerp, quat_from_axis_angle

W, H = 48, 32


def moving_scene(tmp_path, animation: str, boxes: str, name="moving"):
    return write_scene(tmp_path, f"""
        effects = ["moving_objects"]
        num_frames = 12
        [geometry]
        boxes = [{boxes}]
        [materials.wall]
        albedo = [0.5, 0.5, 0.5]
        [materials.mover]
        albedo = [0.8, 0.4, 0.2]
        [[lights]]
        intensity = [3.0, 3.0, 3.0]
        position = [0.0, 1.5, -2.0]
        [[animations]]
        materials = ["mover"]
        {animation}
        """, name)


ROOM = '{min = [-4.0, -2.0, -4.0], max = [4.0, 4.0, 6.0], material = "wall"}'


@pytest.fixture(scope="module")
def plane(tmp_path_factory):
    """A thin slab facing the camera at z = 1, translating +x by 0.1 per frame."""
    p = moving_scene(tmp_path_factory.mktemp("plane"), 'frames = [0, 10]\ntranslate = [[0.0, 0.0, 0.0], [1.0, 0.0, 0.0]]',
                     ROOM + ', {min = [-1.0, -1.0, 1.0], max = [1.0, 1.0, 1.05], material = "mover"}')
    scene = load_scene(p)
    return scene, PathTracer(scene, workers=1)


@pytest.fixture(scope="module")
def cube(tmp_path_factory):
    """A cube spinning about y (pivot at its centre), 30 degrees per keyframe."""
    p = moving_scene(tmp_path_factory.mktemp("cube"),
                     'frames = [0, 11]\nrotate = [[0.0, 1.0, 0.0, 0.0], [0.0, 1.0, 0.0, 66.0]]',
                     ROOM + ', {min = [-0.6, -0.6, 0.4], max = [0.6, 0.6, 1.6], material = "mover"}')
    scene = load_scene(p)
    return scene, PathTracer(scene, workers=1)


def project(cam, P):
    """(N, 3) world points -> (N, 2) pixel coordinates, float64."""
    T = cam.cam_from_world[0].double().numpy()
    K = cam.K[0].double().numpy()
    q = P @ T[:3, :3].T + T[:3, 3]
    return np.stack([K[0, 0] * q[:, 0] / q[:, 2] + K[0, 2], K[1, 1] * q[:, 1] / q[:, 2] + K[1, 2]], 1)


def pixel_centres(mask):
    ys, xs = np.nonzero(mask)
    return np.stack([xs + 0.5, ys + 0.5], 1)


class TestMovingGeometry:
    def test_costs_nothing_when_absent(self):
        scene = load_scene("living_room")
        tr = PathTracer(scene, workers=1)
        for f in range(3):
            tr.gbuffer(scene.camera(f, 16, 9), f)
        assert tr.stats["bvh_builds"] == 1 and not tr.moving_objects
        assert scene.object_transforms(5).shape == (0, 4, 4) and (scene.face_objects() == -1).all()

    def test_one_bvh_per_frame_when_declared(self, plane):
        scene, tr = plane
        builds = tr.stats["bvh_builds"]
        cam = camera_looking((0.0, 0.0, -3.0), (0.0, 0.0, 0.0), width=W, height=H)
        tr.gbuffer(cam, 3)
        tr.render(cam, 3, 1)  # the same frame again: the geometry is kept
        tr.gbuffer(cam, 4)
        assert tr.stats["bvh_builds"] == builds + 2

    def test_object_really_moves(self, plane):
        scene, tr = plane
        cam = camera_looking((0.0, 0.0, -3.0), (0.0, 0.0, 0.0), width=W, height=H)
        a, b = tr.gbuffer(cam, 0), tr.gbuffer(cam, 10)
        assert a.object_id.shape == (1, 1, H, W) and int((a.object_id == 0).sum()) > 100
        xa = a.position[0, 0][a.object_id[0, 0] == 0]
        xb = b.position[0, 0][b.object_id[0, 0] == 0]
        assert float(xb.mean() - xa.mean()) > 0.5  # moved +1 in x (partly out of view)

    def test_radiance_static_scene_unchanged(self):
        """The restructured geometry stage gives the same renders for scenes without moving objects."""
        scene = load_scene("atrium")
        cam = scene.camera(2, 24, 16)
        a = PathTracer(scene, workers=1).render(cam, 2, 2)
        b = PathTracer(scene, workers=2, backend="numpy").render(cam, 2, 2)
        assert torch.equal(a.radiance, b.radiance) and torch.equal(a.depth, b.depth)


class TestMotionVectors:
    def test_shapes_and_no_surface(self, plane):
        scene, tr = plane
        cam = camera_looking((0.0, 0.0, -3.0), (0.0, 0.0, 0.0), width=W, height=H)
        r = tr.render(cam, 5, 1, prev_camera=cam)
        assert r.motion.shape == (1, 2, H, W) and r.motion_world.shape == (1, 3, H, W)
        assert r.motion.dtype == r.motion_world.dtype == torch.float32
        assert tr.render(cam, 5, 1).motion is None

    @pytest.mark.parametrize("frame", [1, 5, 10])
    def test_translating_plane_analytic(self, plane, frame):
        scene, tr = plane
        cam = camera_looking((0.0, 0.0, -3.0), (0.0, 0.0, 0.0), width=W, height=H)
        r = tr.gbuffer(cam, frame, prev_camera=cam)
        on = (r.object_id[0, 0] == 0).numpy()
        assert on.sum() > 50
        mw = r.motion_world[0].numpy()[:, on].T
        np.testing.assert_allclose(mw, np.tile([-0.1, 0.0, 0.0], (len(mw), 1)), atol=1e-6)
        # analytic screen motion: the surface point at the pixel centre, 0.1 units back along -x
        P = r.position[0].double().numpy()[:, on].T
        uv = pixel_centres(on)
        expected = project(cam, P + np.array([-0.1, 0.0, 0.0])) - uv
        got = r.motion[0].double().numpy()[:, on].T
        assert np.abs(got - expected).max() < 1e-3
        # and the static background moves with the camera only (here: not at all)
        off = (r.object_id[0, 0] < 0).numpy() & np.isfinite(r.depth[0, 0].numpy())
        assert np.abs(r.motion[0].numpy()[:, off]).max() < 1e-3 and (r.motion_world[0].numpy()[:, off] == 0).all()

    @pytest.mark.parametrize("frame", [1, 6, 11])
    def test_rotating_cube_analytic(self, cube, frame):
        scene, tr = cube
        cam = camera_looking((0.5, 1.2, -2.5), (0.0, 0.0, 1.0), width=W, height=H)
        prev = camera_looking((0.45, 1.2, -2.5), (0.0, 0.0, 1.0), width=W, height=H)  # the camera moves too
        r = tr.gbuffer(cam, frame, prev_camera=prev)
        on = (r.object_id[0, 0] == 0).numpy()
        assert on.sum() > 50
        d_theta = -6.0  # degrees per frame (66 over 11 frames), previous minus current
        R = quat_to_matrix(quat_from_axis_angle([0.0, 1.0, 0.0], d_theta))
        pivot = np.array([0.0, 0.0, 1.0])
        P = r.position[0].double().numpy()[:, on].T
        P_prev = (P - pivot) @ R.T + pivot
        np.testing.assert_allclose(r.motion_world[0].double().numpy()[:, on].T, P_prev - P, atol=2e-6)
        got = r.motion[0].double().numpy()[:, on].T
        assert np.abs(got - (project(prev, P_prev) - pixel_centres(on))).max() < 1e-3

    def test_static_geometry_matches_camera_motion(self):
        scene = load_scene("living_room")
        tr = PathTracer(scene, workers=1)
        cam, prev = scene.camera(10, 40, 24), scene.camera(9, 40, 24)
        r = tr.gbuffer(cam, 10, prev_camera=prev)
        cm = camera_motion(r.depth, cam.K, cam.cam_from_world, prev.K, prev.cam_from_world)
        ok = torch.isfinite(cm)
        assert torch.equal(ok, torch.isfinite(r.motion)) and float((r.motion - cm)[ok].abs().max()) < 1e-3
        assert float(r.motion_world[torch.isfinite(r.motion_world)].abs().max()) == 0.0
        assert bool(torch.isnan(r.motion[:, :, ~torch.isfinite(r.depth[0, 0])]).all())

    def test_finite_differences_of_positions(self):
        """P + motion_world lands on the previous frame's rendered surface at pixel + motion (both eyes)."""
        scene = load_scene("living_room_moving_objects")
        tr = PathTracer(scene)
        Wd, Hd = 160, 90
        for eye in (0, 1):
            cam, prev = scene.stereo_cameras(21, Wd, Hd)[eye], scene.stereo_cameras(20, Wd, Hd)[eye]
            r = tr.gbuffer(cam, 21, prev_camera=prev)
            p = tr.gbuffer(prev, 20)
            on = (r.object_id[0, 0] >= 0) & torch.isfinite(r.motion).all(1)[0]
            assert int(on.sum()) > 200
            ys, xs = torch.nonzero(on, as_tuple=True)
            u = xs.double() + 0.5 + r.motion[0, 0, ys, xs].double()
            v = ys.double() + 0.5 + r.motion[0, 1, ys, xs].double()
            xi, yi = torch.floor(u).long(), torch.floor(v).long()  # the previous pixel containing the point
            inside = (xi >= 0) & (xi < Wd) & (yi >= 0) & (yi < Hd)
            xi, yi, ys, xs = xi[inside], yi[inside], ys[inside], xs[inside]
            same = p.object_id[0, 0, yi, xi] == r.object_id[0, 0, ys, xs]
            moved = (r.position[0, :, ys, xs] + r.motion_world[0, :, ys, xs])[:, same]
            there = p.position[0, :, yi[same], xi[same]]
            # the previous pixel's surface point lies within a pixel footprint (~2 cm here) of the moved point
            err = (moved - there).norm(dim=0)
            assert float(err.median()) < 0.02 and float(same.float().mean()) > 0.9


class TestAnimation:
    def test_interpolation(self):
        q0 = quat_from_axis_angle([0, 0, 1], 0.0)
        q1 = quat_from_axis_angle([0, 0, 1], 90.0)
        np.testing.assert_allclose(quat_to_matrix(slerp(q0, q1, 0.5)), quat_to_matrix(quat_from_axis_angle([0, 0, 1], 45.0)),
                                   atol=1e-12)

    def test_transforms_hold_outside_keyframes(self, plane):
        scene, _ = plane
        np.testing.assert_allclose(scene.object_transforms(0)[0], np.eye(4), atol=1e-12)
        np.testing.assert_allclose(scene.object_transforms(11)[0][:3, 3], [1.0, 0.0, 0.0], atol=1e-12)
        np.testing.assert_allclose(scene.object_transforms(2.5)[0][:3, 3], [0.25, 0.0, 0.0], atol=1e-12)

    @pytest.mark.parametrize("anim, effects, msg", [
        ('frames = [0, 5]\ntranslate = [[0.0, 0.0, 0.0]]', '["moving_objects"]', "expected 2 entries"),
        ('frames = [5, 0]', '["moving_objects"]', "increasing"),
        ('frames = [0]\nscale = [0.0]', '["moving_objects"]', "positive"),
        ('frames = [0]\nrotate = [[0.0, 0.0, 0.0, 10.0]]', '["moving_objects"]', "zero vector"),
        ('frames = [0]', '[]', "moving_objects"),
    ])
    def test_exceptions(self, tmp_path, anim, effects, msg):
        p = moving_scene(tmp_path, anim, ROOM + ', {min = [0.0, 0.0, 0.0], max = [1.0, 1.0, 1.0], material = "mover"}')
        p.write_text(p.read_text().replace('effects = ["moving_objects"]', f"effects = {effects}"))
        with pytest.raises(SceneError, match=msg):
            load_scene(p)

    def test_unknown_and_emissive_materials(self, tmp_path):
        p = moving_scene(tmp_path, 'frames = [0]', ROOM)
        p.write_text(p.read_text().replace('materials = ["mover"]', 'materials = ["nope"]'))
        with pytest.raises(SceneError, match="unknown material 'nope'"):
            load_scene(p)
        p.write_text(p.read_text().replace('materials = ["nope"]', 'materials = ["wall"]')
                     .replace("albedo = [0.5, 0.5, 0.5]", "albedo = [0.5, 0.5, 0.5]\nemission = [1.0, 1.0, 1.0]"))
        with pytest.raises(SceneError, match="emissive"):
            load_scene(p)
        p2 = write_scene(tmp_path, 'effects = ["moving_objects"]\nnum_frames = 2\n[geometry]\nboxes = [' + ROOM
                         + ']\n[materials.wall]\nalbedo = [0.5, 0.5, 0.5]\n', "no_anim")
        with pytest.raises(SceneError, match="no \\[\\[animations\\]\\]"):
            load_scene(p2)

    def test_builtin_moving_share(self):
        """The built-in moving-object scene: >= 5 % of the pixels show moving objects (averaged over its path)."""
        scene = load_scene("living_room_moving_objects")
        tr = PathTracer(scene)
        share = [float((tr.gbuffer(scene.stereo_cameras(f, 80, 45)[0], f).object_id >= 0).float().mean())
                 for f in range(0, 60, 10)]
        assert np.mean(share) >= 0.05, share
        assert math.isclose(scene.num_frames, 60)
