"""Moving objects in the tracer: per-frame geometry only where declared, the static faces' BVH built once and queried
with the moving faces' (renders equal to one BVH of every face), and motion vectors against analytic motion (a plane
translating, a cube rotating) and against finite differences of rendered positions."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from conftest_render import camera_looking, write_scene
from stereorepro import camera_motion, load_scene
from stereorepro.errors import SceneError
from stereorepro.render import PathTracer
from stereorepro.render._embree import SplitBVH, TriangleBVH
from stereorepro.render.tracer import _face_normals, _Geometry
from stereorepro.scenes import scenes_dir, shared_scenes_dir
from stereorepro.scenes.animation import quat_to_matrix, slerp, quat_from_axis_angle

W, H = 48, 32


def moving_scene(tmp_path, animation: str, boxes: str, name="moving"):
    return write_scene(
        tmp_path,
        f"""
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
        """,
        name,
    )


ROOM = '{min = [-4.0, -2.0, -4.0], max = [4.0, 4.0, 6.0], material = "wall"}'


@pytest.fixture(scope="module")
def plane(tmp_path_factory):
    """A thin slab facing the camera at z = 1, translating +x by 0.1 per frame."""
    p = moving_scene(
        tmp_path_factory.mktemp("plane"),
        "frames = [0, 10]\ntranslate = [[0.0, 0.0, 0.0], [1.0, 0.0, 0.0]]",
        ROOM + ', {min = [-1.0, -1.0, 1.0], max = [1.0, 1.0, 1.05], material = "mover"}',
    )
    scene = load_scene(p)
    return scene, PathTracer(scene, workers=1)


@pytest.fixture(scope="module")
def cube(tmp_path_factory):
    """A cube spinning about y (pivot at its centre), 30 degrees per keyframe."""
    p = moving_scene(
        tmp_path_factory.mktemp("cube"),
        "frames = [0, 11]\nrotate = [[0.0, 1.0, 0.0, 0.0], [0.0, 1.0, 0.0, 66.0]]",
        ROOM + ', {min = [-0.6, -0.6, 0.4], max = [0.6, 0.6, 1.6], material = "mover"}',
    )
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


class OneBVH(PathTracer):
    """The tracer with the geometry stage it had before the split: every face's normal and one BVH of every face,
    computed per frame. What the split geometry stage must equal."""

    def geometry(self, frame):
        frame = int(frame)
        if self._geom_cache is None or self._geom_cache.frame != frame:
            v = self.object_vertices(frame)
            self._geom_cache = _Geometry(frame, v, _face_normals(v, self.faces), TriangleBVH(v, self.faces))
        return self._geom_cache


RESULT_FIELDS = (
    "radiance",
    "depth",
    "normal",
    "position",
    "albedo",
    "material_id",
    "motion",
    "motion_world",
    "object_id",
)


def assert_same_renders(scene, frames, width, height, spp):
    """Both eyes of ``frames``, with motion vectors: the tracer and :class:`OneBVH` equal byte for byte."""
    split, one = PathTracer(scene), OneBVH(scene)
    for f in frames:
        prev = scene.stereo_cameras(max(f - 1, 0), width, height)
        for eye, cam in enumerate(scene.stereo_cameras(f, width, height)):
            a, b = (tr.render(cam, f, spp, eye=eye, prev_camera=prev[eye]) for tr in (split, one))
            for k in RESULT_FIELDS:
                x, y = getattr(a, k), getattr(b, k)
                assert x.numpy().tobytes() == y.numpy().tobytes(), (f, eye, k)
            assert a.ray_counts == b.ray_counts, (f, eye)
        assert isinstance(split.geometry(f).bvh, SplitBVH)


def assert_same_hits(geom, one, faces, o, d):
    """Closest hits of ``geom.bvh`` and the BVH ``one`` of every face: the same ``t``, and the same triangle but at
    ties (where the other triangle is hit at the same ``t`` too: which one a BVH keeps depends on its tree).
    Returns both prims."""
    t, prim = geom.bvh.intersect(o, d)
    t1, prim1 = one.intersect(o, d)
    assert np.array_equal(t, t1) and np.array_equal(prim >= 0, prim1 >= 0)
    for i in np.flatnonzero(prim != prim1):
        for p in (prim[i], prim1[i]):
            assert TriangleBVH(geom.vertices, faces[[p]]).intersect(o[i : i + 1], d[i : i + 1])[0][0] == t[i]
    return prim, prim1


SLAB = '{min = [-1.0, -1.0, 1.0], max = [1.0, 1.0, 1.05], material = "%s"}'


class TestSplitBVH:
    def test_static_bvh_built_once(self):
        scene = load_scene("living_room_moving_objects")
        tr = PathTracer(scene, workers=1)
        assert tr.stats["bvh_builds"] == 1
        g0, g1 = tr.geometry(0), tr.geometry(1)
        assert g0.bvh.static is g1.bvh.static is tr._bvh and g0.bvh.moving is not g1.bvh.moving
        assert g0.bvh.moving.num_triangles == int((tr.face_object >= 0).sum()) == 24
        assert g0.bvh.num_triangles == len(tr.faces) and tr.stats["bvh_builds"] == 3
        assert np.array_equal(g1.face_normal, _face_normals(tr.object_vertices(1), tr.faces))

    def test_renders_equal_one_bvh(self):
        """Radiance, G-buffers, motion vectors, object ids and ray counts of the built-in moving scene equal those of
        one BVH of every face rebuilt per frame, byte for byte."""
        assert_same_renders(load_scene("living_room_moving_objects"), (0, 17, 30, 46), 64, 36, 2)

    def test_queries_equal_one_bvh(self):
        """Closest hits and occlusion of rays from all over the room, half of them aimed inside the moving faces,
        and rays aimed at the moving faces' corners (each hits several triangles at the same ``t``)."""
        scene = load_scene("living_room_moving_objects")
        tr = PathTracer(scene, workers=1)
        g = tr.geometry(23)
        one = TriangleBVH(g.vertices, tr.faces)
        rng = np.random.default_rng(0)
        n = 20000
        o = rng.uniform([-3.0, 0.05, -3.0], [3.0, 2.5, 3.0], (n, 3)).astype(np.float32)
        tri = g.vertices[tr.faces[tr.face_object >= 0]].astype(np.float64)[rng.integers(0, 24, n)]  # (n, 3, 3)
        inside = (rng.dirichlet([2.0, 2.0, 2.0], n)[:, :, None] * tri).sum(1)
        d = np.where(rng.random((n, 1)) < 0.5, inside - o, rng.normal(size=(n, 3))).astype(np.float32)
        prim = assert_same_hits(g, one, tr.faces, o, d)
        assert (prim[0] != prim[1]).sum() <= 2  # ties are rare
        assert np.isin(prim[0], np.flatnonzero(tr.face_object >= 0)).sum() > 5000  # many hit the moving faces
        tmax = rng.uniform(0.0, 4.0, n).astype(np.float32)
        assert np.array_equal(g.bvh.occluded(o, d, tmax), one.occluded(o, d, tmax))
        o, d = o[:2000], (tri[:2000, 0] - o[:2000]).astype(np.float32)
        prim = assert_same_hits(g, one, tr.faces, o, d)
        assert (prim[0] != prim[1]).sum() > 100  # at the corners the trees order their ties differently

    @pytest.mark.parametrize("moving_first", [False, True])
    def test_tie_keeps_lower_index(self, tmp_path, moving_first):
        """A moving slab exactly on a static one (frame 0): every hit on them is a tie, kept by the lower index."""
        slabs = [SLAB % "wall", SLAB % "mover"]
        boxes = ", ".join([ROOM] + (slabs[::-1] if moving_first else slabs))
        scene = load_scene(
            moving_scene(tmp_path, "frames = [0, 10]\ntranslate = [[0.0, 0.0, 0.0], [1.0, 0.0, 0.0]]", boxes)
        )
        tr = PathTracer(scene, workers=1)
        obj = tr.gbuffer(camera_looking((0.0, 0.0, -3.0), (0.0, 0.0, 0.0), width=W, height=H), 0).object_id
        assert (int((obj == 0).sum()) > 100) == moving_first  # the slab of the lower index
        assert int((obj == -1).sum()) > 100  # and the room

    def test_every_face_moving(self, tmp_path):
        """No static faces: one BVH of the frame, as before the split."""
        scene = load_scene(
            moving_scene(tmp_path, "frames = [0, 10]\ntranslate = [[0.0, 0.0, 0.0], [1.0, 0.0, 0.0]]", SLAB % "mover")
        )
        tr = PathTracer(scene, workers=1)
        assert tr._bvh is None and tr.stats["bvh_builds"] == 0
        g = tr.gbuffer(camera_looking((0.0, 0.0, -3.0), (0.0, 0.0, 0.0), width=W, height=H), 4)
        assert isinstance(tr.geometry(4).bvh, TriangleBVH) and int((g.object_id == 0).sum()) > 100

    @pytest.mark.slow
    @pytest.mark.skipif(
        not (shared_scenes_dir() / "living_room" / "living_room.ply").is_file(),
        reason="shared scene meshes not available (set STEREOREPRO_SHARED_SCENES)",
    )
    def test_shared_living_room_equals_one_bvh(self, tmp_path):
        """shared_living_room (about 400k triangles) with its sofa cushion moving: a few frames, byte for byte."""
        p = tmp_path / "moving_cushion.toml"
        p.write_text(
            f'extends = "{(scenes_dir() / "shared_living_room.toml").resolve()}"\n'
            'effects = ["moving_objects"]\n[[animations]]\nmaterials = ["Cushion1"]\nframes = [0, 59]\n'
            "translate = [[0.0, 0.0, 0.0], [0.8, 0.1, 0.6]]\n"
            "rotate = [[0.0, 1.0, 0.0, 0.0], [0.0, 1.0, 0.0, 45.0]]\n"
        )
        assert_same_renders(load_scene(p), (5, 40), 64, 36, 1)


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
        np.testing.assert_allclose(
            quat_to_matrix(slerp(q0, q1, 0.5)), quat_to_matrix(quat_from_axis_angle([0, 0, 1], 45.0)), atol=1e-12
        )

    def test_transforms_hold_outside_keyframes(self, plane):
        scene, _ = plane
        np.testing.assert_allclose(scene.object_transforms(0)[0], np.eye(4), atol=1e-12)
        np.testing.assert_allclose(scene.object_transforms(11)[0][:3, 3], [1.0, 0.0, 0.0], atol=1e-12)
        np.testing.assert_allclose(scene.object_transforms(2.5)[0][:3, 3], [0.25, 0.0, 0.0], atol=1e-12)

    @pytest.mark.parametrize(
        "anim, effects, msg",
        [
            ("frames = [0, 5]\ntranslate = [[0.0, 0.0, 0.0]]", '["moving_objects"]', "expected 2 entries"),
            ("frames = [5, 0]", '["moving_objects"]', "increasing"),
            ("frames = [0]\nscale = [0.0]", '["moving_objects"]', "positive"),
            ("frames = [0]\nrotate = [[0.0, 0.0, 0.0, 10.0]]", '["moving_objects"]', "zero vector"),
            ("frames = [0]", "[]", "moving_objects"),
        ],
    )
    def test_exceptions(self, tmp_path, anim, effects, msg):
        p = moving_scene(tmp_path, anim, ROOM + ', {min = [0.0, 0.0, 0.0], max = [1.0, 1.0, 1.0], material = "mover"}')
        p.write_text(p.read_text().replace('effects = ["moving_objects"]', f"effects = {effects}"))
        with pytest.raises(SceneError, match=msg):
            load_scene(p)

    def test_unknown_and_emissive_materials(self, tmp_path):
        p = moving_scene(tmp_path, "frames = [0]", ROOM)
        p.write_text(p.read_text().replace('materials = ["mover"]', 'materials = ["nope"]'))
        with pytest.raises(SceneError, match="unknown material 'nope'"):
            load_scene(p)
        p.write_text(
            p.read_text()
            .replace('materials = ["nope"]', 'materials = ["wall"]')
            .replace("albedo = [0.5, 0.5, 0.5]", "albedo = [0.5, 0.5, 0.5]\nemission = [1.0, 1.0, 1.0]")
        )
        with pytest.raises(SceneError, match="emissive"):
            load_scene(p)
        p2 = write_scene(
            tmp_path,
            'effects = ["moving_objects"]\nnum_frames = 2\n[geometry]\nboxes = ['
            + ROOM
            + "]\n[materials.wall]\nalbedo = [0.5, 0.5, 0.5]\n",
            "no_anim",
        )
        with pytest.raises(SceneError, match="no \\[\\[animations\\]\\]"):
            load_scene(p2)

    def test_builtin_moving_share(self):
        """The built-in moving-object scene: >= 5 % of the pixels show moving objects (averaged over its path)."""
        scene = load_scene("living_room_moving_objects")
        tr = PathTracer(scene)
        share = [
            float((tr.gbuffer(scene.stereo_cameras(f, 80, 45)[0], f).object_id >= 0).float().mean())
            for f in range(0, 60, 10)
        ]
        assert np.mean(share) >= 0.05, share
        assert math.isclose(scene.num_frames, 60)
