"""Scene files and loader."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

import stereorepro
from stereorepro.scenes import SceneError, list_scenes, load_scene, shared_scenes_dir

from conftest_render import write_scene

SEVEN = [
    "atrium",
    "atrium_glossy",
    "atrium_moving_light",
    "living_room",
    "living_room_glossy",
    "living_room_moving_light",
    "classroom",
]


class TestListScenes:
    def test_smoke(self):
        assert stereorepro.list_scenes() == SEVEN
        ext = list_scenes(include_external=True)
        assert ext[:7] == SEVEN and {"shared_sponza", "shared_living_room", "shared_classroom"} <= set(ext)


class TestLoadScene:
    @pytest.mark.parametrize("name", SEVEN)
    def test_smoke(self, name):
        s = stereorepro.load_scene(name)
        assert s.name == name and s.num_frames == 60
        expected = {"glossy"} if "glossy" in name else {"moving_light"} if "moving" in name else set()
        assert s.effects == frozenset(expected)
        g = s.geometry()
        assert 1000 < len(g.faces) < 20000
        assert g.material_ids.max() < len(s.material_table()["names"])
        assert 0 < s.position_threshold < 1 and 0 < s.normal_threshold < 1

    def test_shapes(self):
        s = load_scene("classroom")
        left, right = s.stereo_cameras(10, 64, 36)
        assert left.batch_size == 1 and left.height == 36 and left.width == 64
        assert left.cam_from_world.dtype == torch.float64
        assert s.head_pose(10).shape == (1, 4, 4)
        sep = (left.center_world - right.center_world).norm().item()
        assert math.isclose(sep, 0.065, rel_tol=1e-9)
        assert s.rig.eye_separation == 0.065

    def test_load_by_path(self):
        s = load_scene(stereorepro.scenes.scenes_dir() / "atrium.toml")
        assert s.name == "atrium"

    def test_camera_paths(self):
        """Atrium: moves backward (against its view direction); living room / classroom: curved pans."""
        for name, backward in [("atrium", True), ("living_room", False), ("classroom", False)]:
            s = load_scene(name)
            centers = torch.cat([s.camera(f, 8, 8).center_world for f in range(60)]).numpy()
            fwd = np.stack([s.head_pose(f)[0, 2, :3].numpy() for f in range(60)])
            vel = np.diff(centers, axis=0)
            steps = np.linalg.norm(vel, axis=1)
            assert steps.max() < 3 * np.median(steps) + 1e-9  # smooth, no jumps
            along = (vel * fwd[:-1]).sum(1) / steps
            if backward:
                assert (along < -0.8).all()
            if not backward:
                turn = np.degrees(np.arccos(np.clip((fwd[0] * fwd[-1]).sum(), -1, 1)))
                assert turn > 15, turn  # panning
            acc = np.diff(vel, axis=0)
            assert np.linalg.norm(acc, axis=1).max() < 0.5 * steps.mean() + 1e-9  # curved but smooth

    def test_exceptions(self, tmp_path):
        with pytest.raises(SceneError, match="unknown scene"):
            load_scene("no_such_scene")
        with pytest.raises(SceneError, match="not found"):
            load_scene(tmp_path / "missing.toml")
        base = """
            effects = []
            num_frames = 2
            [geometry]
            boxes = [{min = [0.0, 0.0, 0.0], max = [1.0, 1.0, 1.0], material = "m"}]
            [materials.m]
            albedo = [0.5, 0.5, 0.5]
            """
        cases = [
            ("colour = 3\n" + base, "unknown key 'colour'"),
            (base.replace("num_frames = 2", 'num_frames = "two"'), "num_frames.*integer"),
            (base.replace("albedo = [0.5, 0.5, 0.5]", "albedo = [0.5, 0.5]"), "materials.m.albedo.*3 numbers"),
            (base.replace("effects = []", 'effects = ["fog"]'), "unknown effect"),
            (
                base.replace("albedo = [0.5, 0.5, 0.5]", "albedo = [0.5, 0.5, 0.5]\nspecular = [0.1, 0.1, 0.1]"),
                "glossy",
            ),
            (base.replace("effects = []", 'effects = ["glossy"]'), "no material has a specular"),
            (
                base.replace(
                    "albedo = [0.5, 0.5, 0.5]", "albedo = [0.9, 0.9, 0.9]\nspecular = [0.3, 0.3, 0.3]"
                ).replace("effects = []", 'effects = ["glossy"]'),
                "energy",
            ),
            (
                base + "[[lights]]\nintensity = [1.0, 1.0, 1.0]\nkeyframes = [[0.0, 0.0, 0.0], [1.0, 1.0, 1.0]]\n",
                "moving_light",
            ),
            (base.replace("effects = []", 'effects = ["moving_light"]'), "no light has keyframes"),
            (base.replace('material = "m"', 'material = "nope"'), "nope"),
            (base + "[rig]\neye_separation = -1.0\n", "eye_separation"),
            ("effects = [\n", "invalid TOML"),
            (
                base + "[camera]\nvfov_deg = 60.0\nup = [0.0, 0.0, 0.0]\npositions = [[0.0, 0.0, -3.0]]\n"
                "targets = [[0.0, 0.0, 0.0]]\n",
                r"camera .* at frame 0: .*zero vector",
            ),
            (
                base + "[camera]\nvfov_deg = 60.0\npositions = [[1.0, 2.0, 3.0]]\ntargets = [[1.0, 2.0, 3.0]]\n",
                r"camera .* at frame 0: .*target equals eye",
            ),
            # the keyframes are fine, but the interpolated path meets its target at frame 1 of 3
            (
                base.replace("num_frames = 2", "num_frames = 3")
                + "[camera]\nvfov_deg = 60.0\npositions = [[0.0, 0.0, -1.0], [0.0, 0.0, 1.0]]\n"
                "targets = [[0.0, 0.0, 1.0], [0.0, 0.0, -1.0]]\n",
                "at frame 1: .*target equals eye",
            ),
        ]
        binary = tmp_path / "binary.toml"
        binary.write_bytes(bytes(range(256)) * 4)
        with pytest.raises(SceneError, match=r"binary\.toml: not a text \(UTF-8\) TOML file"):
            load_scene(binary)
        with pytest.raises(SceneError, match="is a directory"):
            (tmp_path / "dir.toml").mkdir()
            load_scene(tmp_path / "dir.toml")
        for i, (text, msg) in enumerate(cases):
            p = write_scene(tmp_path, text, name=f"bad{i}")
            with pytest.raises(SceneError, match=msg) as e:
                load_scene(p).geometry()
            assert str(p) in str(e.value), (i, str(e.value))

    def test_frame_out_of_range(self):
        s = load_scene("atrium")
        with pytest.raises(ValueError, match="frame"):
            s.head_pose(60)

    def test_extends(self):
        g = load_scene("living_room_glossy")
        base = load_scene("living_room")
        assert g.material_table()["names"] == base.material_table()["names"]
        assert g.material_table()["specular"].max() > 0 and base.material_table()["specular"].max() == 0


class TestTextures:
    """The ``textures`` effect: world-space patterns cut into the declared materials' faces only."""

    BASE = """
        effects = ["textures"]
        num_frames = 2
        [geometry]
        quads = [{corner = [0.0, 0.0, 0.0], edge_u = [1.0, 0.0, 0.0], edge_v = [0.0, 0.0, 1.0], material = "m"},
                 {corner = [0.0, 1.0, 0.0], edge_u = [1.0, 0.0, 0.0], edge_v = [0.0, 0.0, 1.0], material = "plain"}]
        [materials.m]
        albedo = [0.6, 0.4, 0.2]
        [materials.plain]
        albedo = [0.5, 0.5, 0.5]
        [textures.m]
        pattern = "checker"
        scale = 0.25
        contrast = 0.5
        """

    def test_checker_cells(self, tmp_path):
        """A unit quad with a 0.25 checker: 16 cells, each a square of two triangles with the material of its
        parity (the second colour = albedo × 0.5); the untextured quad keeps its two faces."""
        s = load_scene(write_scene(tmp_path, self.BASE, name="checker"))
        names = s.material_table()["names"]
        assert names == ["m", "plain", "m~texture"]
        np.testing.assert_allclose(s.material_table()["albedo"][2], [0.3, 0.2, 0.1], rtol=1e-6)
        g = s.geometry()
        plain = g.material_ids == 1
        assert int(plain.sum()) == 2
        tex = ~plain
        assert int(tex.sum()) == 32  # 16 cells of two triangles
        centroid = g.vertices[g.faces[tex]].mean(1)
        parity = (np.floor(centroid[:, 0] / 0.25) + np.floor(centroid[:, 2] / 0.25)) % 2
        assert np.array_equal(g.material_ids[tex], np.where(parity == 1, 2, 0))
        area = 0.5 * np.linalg.norm(
            np.cross(*(g.vertices[g.faces[tex]][:, 1:] - g.vertices[g.faces[tex]][:, :1]).transpose(1, 0, 2)), axis=1
        )
        assert math.isclose(float(area.sum()), 1.0, rel_tol=1e-6)

    def test_exceptions(self, tmp_path):
        cases = [
            (self.BASE.replace('effects = ["textures"]', "effects = []"), "declare effects"),
            (self.BASE.split("[textures.m]")[0], "no \\[textures.NAME\\] table"),
            (self.BASE.replace("[textures.m]", "[textures.nope]"), "no material named 'nope'"),
            (self.BASE.replace('"checker"', '"dots"'), "pattern"),
            (self.BASE.replace("scale = 0.25", "scale = 0.0"), "scale"),
            (self.BASE.replace("contrast = 0.5", "contrast = 1.5"), "contrast"),
            (self.BASE.replace('pattern = "checker"', 'pattern = "stripes"\naxis = "w"'), "axis"),
        ]
        for i, (text, msg) in enumerate(cases):
            with pytest.raises(SceneError, match=msg):
                load_scene(write_scene(tmp_path, text, name=f"bad{i}")).geometry()

    def test_living_room_textured(self):
        """The built-in textured variant: the living room's geometry and materials, the declared materials cut
        into patterns (more faces, the same surface), every other face as in the living room."""
        base, tex = load_scene("living_room"), load_scene("living_room_textured")
        assert tex.effects == frozenset({"textures"}) and "living_room_textured" in list_scenes(beyond_paper=True)
        names = tex.material_table()["names"]
        assert names[: len(base.material_table()["names"])] == base.material_table()["names"]
        declared = {"floor", "wall", "rug", "fabric"}
        assert set(names[len(base.material_table()["names"]) :]) == {n + "~texture" for n in declared}
        gb, gt = base.geometry(), tex.geometry()
        ids = [names.index(n) for n in names if n.split("~")[0] in declared]
        untouched_b = ~np.isin(gb.material_ids, ids)
        untouched_t = ~np.isin(gt.material_ids, ids)
        assert np.array_equal(gb.vertices[gb.faces[untouched_b]], gt.vertices[gt.faces[untouched_t]])
        assert np.array_equal(gb.material_ids[untouched_b], gt.material_ids[untouched_t])
        assert len(gt.faces) > 10 * len(gb.faces)

        def area(g, sel):
            tri = g.vertices[g.faces[sel]].astype(np.float64)
            return 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1).sum()

        assert math.isclose(area(gt, ~untouched_t), area(gb, ~untouched_b), rel_tol=1e-5)

    def test_albedo_changes_only_where_declared(self):
        """G-buffer albedo of the textured living room against the plain one (same camera): different on a
        large part of the textured materials' pixels, identical on every other pixel."""
        from stereorepro.render import PathTracer

        base, tex = load_scene("living_room"), load_scene("living_room_textured")
        cam = base.camera(10, 96, 54)
        a = PathTracer(base).render(cam, 10, 1)
        b = PathTracer(tex).render(cam, 10, 1)
        names = tex.material_table()["names"]
        textured = torch.from_numpy(
            np.isin(
                b.material_id.numpy(),
                [i for i, n in enumerate(names) if n.split("~")[0] in ("floor", "wall", "rug", "fabric")],
            )
        ).reshape(b.albedo.shape[0], 1, *b.albedo.shape[2:])
        differs = (a.albedo != b.albedo).any(1, keepdim=True)
        assert not bool(differs[~textured].any())
        assert float(differs[textured].float().mean()) > 0.3


_SHARED = shared_scenes_dir()


@pytest.mark.skipif(
    not (_SHARED / "sponza_dabrovic" / "sponza_dabrovic.ply").is_file(),
    reason="shared scene meshes not available (set STEREOREPRO_SHARED_SCENES)",
)
class TestSharedScenes:
    def test_smoke(self):
        from stereorepro.render import PathTracer

        s = load_scene("shared_sponza")
        r = PathTracer(s).render(s.stereo_cameras(0, 32, 18)[0], 0, 1)
        assert r.radiance.mean() > 0 and stereorepro.has_surface(r.depth).float().mean() > 0.9

    @pytest.mark.slow
    @pytest.mark.parametrize("name", ["shared_living_room", "shared_classroom"])
    def test_large(self, name):
        from stereorepro.render import PathTracer

        s = load_scene(name)
        r = PathTracer(s).render(s.stereo_cameras(0, 32, 18)[0], 0, 1)
        assert r.radiance.mean() > 0

    def test_missing_mesh_dir(self, monkeypatch, tmp_path):
        monkeypatch.setenv("STEREOREPRO_SHARED_SCENES", str(tmp_path))
        with pytest.raises(SceneError, match="STEREOREPRO_SHARED_SCENES"):
            load_scene("shared_sponza").geometry()
