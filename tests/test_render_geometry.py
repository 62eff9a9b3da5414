"""Analytic solids, scene descriptions, what a scene builds, and the Utah teapot."""

from __future__ import annotations

import json
import math
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest
from hypothesis import assume, given, settings
from hypothesis import strategies as st

from tactdeform_hw.errors import ConfigurationError
from tactdeform_hw.render.geometry import (
    SceneObject,
    SurfaceQuery,
    TextureRegion,
    contact_theta_deg,
    edge_angle_in_finger_deg,
)
from tactdeform_hw.render.primitives import Box, Sphere
from tactdeform_hw.render.scene import (
    BUILTIN_SCENES,
    RenderOptions,
    Scene,
    load_scene,
)
from tactdeform_hw.render.tracking import quat_from_axis_angle, quat_to_matrix, rotation_from_euler_deg

REPO = Path(__file__).resolve().parents[1]

coord = st.floats(min_value=-150.0, max_value=150.0, allow_nan=False)


# --- sphere ------------------------------------------------------------------------------------------


def test_sphere_distance_normal_and_closest_point() -> None:
    s = Sphere("s", 50.0, (10.0, 0.0, 0.0))
    q = s.query(np.array([10.0, 80.0, 0.0]))
    assert q.signed_distance_mm == pytest.approx(30.0)
    np.testing.assert_allclose(q.normal, [0, 1, 0])
    np.testing.assert_allclose(q.closest_point_mm, [10, 50, 0])
    assert q.feature == "face" and q.edge_direction is None
    inside = s.query(np.array([10.0, 0.0, 45.0]))
    assert inside.signed_distance_mm == pytest.approx(-5.0)
    assert inside.depth_mm == pytest.approx(5.0) and inside.in_contact
    np.testing.assert_allclose(inside.normal, [0, 0, 1])


def test_sphere_centre_is_defined() -> None:
    q = Sphere("s", 20.0).query(np.zeros(3))
    assert q.signed_distance_mm == -20.0
    assert np.linalg.norm(q.normal) == pytest.approx(1.0)
    assert np.all(np.isfinite(q.closest_point_mm))


@pytest.mark.parametrize("bad", [[np.nan, 0, 0], [0, np.inf, 0], [1.0, 2.0]])
def test_queries_refuse_bad_points(bad: list[float]) -> None:
    for obj in (Sphere("s", 1.0), Box("b", 1.0)):
        with pytest.raises(ConfigurationError):
            obj.query(np.array(bad, dtype=float))


# --- box ---------------------------------------------------------------------------------------------


@pytest.fixture
def cube() -> Box:
    return Box("cube", 100.0, (0.0, 0.0, 0.0), feature_band_mm=3.0)


def test_box_face_region(cube: Box) -> None:
    q = cube.query(np.array([10.0, -20.0, 70.0]))
    assert q.signed_distance_mm == pytest.approx(20.0)
    np.testing.assert_allclose(q.closest_point_mm, [10, -20, 50])
    np.testing.assert_allclose(q.normal, [0, 0, 1])
    assert q.feature == "face"


def test_box_edge_region_outside_reads_as_edge(cube: Box) -> None:
    q = cube.query(np.array([53.0, 20.0, 54.0]))
    assert q.signed_distance_mm == pytest.approx(5.0)
    np.testing.assert_allclose(q.closest_point_mm, [50, 20, 50])
    np.testing.assert_allclose(q.normal, [0.6, 0, 0.8])
    assert q.feature == "edge"
    np.testing.assert_allclose(np.abs(q.edge_direction), [0, 1, 0])


def test_box_corner_region(cube: Box) -> None:
    q = cube.query(np.array([60.0, 60.0, 60.0]))
    assert q.signed_distance_mm == pytest.approx(math.sqrt(300.0))
    assert q.feature == "corner" and q.edge_direction is None
    np.testing.assert_allclose(q.normal, np.ones(3) / math.sqrt(3.0))


def test_box_feature_band_on_the_face(cube: Box) -> None:
    # 2 mm from the x edge of the top face: an edge; 4 mm: a face; near two edges: a corner.
    assert cube.query(np.array([48.0, 0.0, 51.0])).feature == "edge"
    assert cube.query(np.array([46.0, 0.0, 51.0])).feature == "face"
    assert cube.query(np.array([48.5, 48.5, 51.0])).feature == "corner"
    # 2.5 mm from two edges is 3.5 mm from the corner: the nearer edge, not the corner.
    q = cube.query(np.array([47.5, 47.5, 51.0]))
    assert q.feature == "edge"
    wide = Box("wide", 100.0, feature_band_mm=5.0)
    assert wide.query(np.array([46.0, 0.0, 51.0])).feature == "edge"


def test_box_inside_takes_nearest_face(cube: Box) -> None:
    q = cube.query(np.array([45.0, 0.0, 10.0]))
    assert q.signed_distance_mm == pytest.approx(-5.0)
    np.testing.assert_allclose(q.closest_point_mm, [50, 0, 10])
    np.testing.assert_allclose(q.normal, [1, 0, 0])


def test_features_off_reads_everything_as_face() -> None:
    box = Box("b", 100.0, classify_features=False)
    q = box.query(np.array([60.0, 60.0, 60.0]))
    assert q.feature == "face" and q.edge_direction is None


@settings(max_examples=200, deadline=None)
@given(coord, coord, coord)
def test_box_distance_matches_brute_force_and_contains(x: float, y: float, z: float) -> None:
    box = Box("b", (80.0, 40.0, 120.0), (5.0, -3.0, 2.0))
    p = np.array([x, y, z])
    q = box.query(p)
    lo, hi = box.bounds_mm
    outside = np.linalg.norm(np.maximum(np.maximum(lo - p, p - hi), 0.0))
    inside_depth = np.min(np.minimum(p - lo, hi - p))
    expected = outside if outside > 0 else -inside_depth
    assert q.signed_distance_mm == pytest.approx(expected, abs=1e-9)
    assert np.linalg.norm(p - q.closest_point_mm) == pytest.approx(abs(expected), abs=1e-9)
    assert bool(box.contains(p[None, :])[0]) == (q.signed_distance_mm <= 0)
    assert np.linalg.norm(q.normal) == pytest.approx(1.0)


@settings(max_examples=100, deadline=None)
@given(coord, coord, coord, st.floats(-180, 180), st.floats(-90, 90), st.floats(-180, 180))
def test_rotated_box_is_the_box_seen_rotated(
    x: float, y: float, z: float, rx: float, ry: float, rz: float
) -> None:
    r = rotation_from_euler_deg(rx, ry, rz)
    centre = np.array([10.0, 20.0, 30.0])
    plain = Box("b", (60.0, 30.0, 90.0), (0.0, 0.0, 0.0))
    turned = Box("b", (60.0, 30.0, 90.0), centre, rotation=r)
    local = np.array([x, y, z])
    # Inside, equidistant faces (two axes, or both sides of one) are a tie either answer may take;
    # rounding in the turned frame decides it.
    depth = np.abs(local) - np.array([30.0, 15.0, 45.0])
    if not np.any(depth > 0):
        nearest = int(np.argmax(depth))
        assume(np.sort(depth)[-1] - np.sort(depth)[-2] > 1e-6 and abs(local[nearest]) > 1e-6)
    q0 = plain.query(local)
    q1 = turned.query(centre + r @ local)
    assert q1.signed_distance_mm == pytest.approx(q0.signed_distance_mm, abs=1e-9)
    np.testing.assert_allclose(q1.normal, r @ q0.normal, atol=1e-9)
    np.testing.assert_allclose(q1.closest_point_mm, centre + r @ q0.closest_point_mm, atol=1e-9)
    assert q1.feature == q0.feature
    if q0.edge_direction is not None:
        np.testing.assert_allclose(q1.edge_direction, r @ q0.edge_direction, atol=1e-9)


def test_box_sites_read_as_their_feature(cube: Box) -> None:
    for feature in ("face", "edge", "corner"):
        sites = cube.sites(feature)
        assert sites, feature
        for site in sites:
            q = cube.query(site.point_mm + 1.0 * site.normal)
            assert q.feature == feature
            assert q.signed_distance_mm == pytest.approx(1.0)
    assert len(cube.sites("edge")) == 12 and len(cube.sites("corner")) == 8


def test_bad_sizes_and_rotations_are_refused() -> None:
    with pytest.raises(ConfigurationError, match="size_mm"):
        Box("b", (1.0, -2.0, 3.0))
    with pytest.raises(ConfigurationError, match="rotation"):
        Box("b", 1.0, rotation=np.diag([1.0, 1.0, -1.0]))
    with pytest.raises(ConfigurationError, match="radius_mm"):
        Sphere("s", 0.0)
    with pytest.raises(ConfigurationError, match="texture_level"):
        Sphere("s", 1.0, texture_level=3)


def test_objects_satisfy_the_protocol() -> None:
    assert isinstance(Box("b", 1.0), SceneObject)
    assert isinstance(Sphere("s", 1.0), SceneObject)


# --- texture --------------------------------------------------------------------------------------------


def test_texture_regions_pick_the_level_of_the_closest_point() -> None:
    top = TextureRegion((-60, 49, -60), (60, 51, 0), 2, "top-front")
    box = Box("b", 100.0, texture_level=1, texture_regions=[top])
    assert box.has_texture_lookup
    q = box.query(np.array([0.0, 60.0, -20.0]))
    assert q.texture_level == 2 and q.region == "top-front"
    q = box.query(np.array([0.0, 60.0, 20.0]))
    assert q.texture_level == 1 and q.region is None
    smooth = Box("b", 100.0, texture_regions=[TextureRegion((0, 0, 0), (1, 1, 1), 0)])
    assert not smooth.has_texture_lookup


def test_texture_region_validation() -> None:
    with pytest.raises(ConfigurationError, match="lo_mm"):
        TextureRegion((1, 0, 0), (0, 1, 1), 1)
    with pytest.raises(ConfigurationError, match="texture level"):
        TextureRegion((0, 0, 0), (1, 1, 1), 5)


# --- finger-frame angles ----------------------------------------------------------------------------------


def test_contact_theta_is_the_roll_between_pad_and_surface() -> None:
    normal = np.array([0.0, 0.0, -1.0])  # a wall ahead, facing the participant
    assert contact_theta_deg(np.eye(3), normal) == pytest.approx(0.0)
    for roll in (-60.0, -15.0, 15.0, 60.0):
        # Rolling the finger about its own axis (y) by -roll tips its right side toward the wall for roll > 0.
        r = quat_to_matrix(quat_from_axis_angle([0, 1, 0], -roll))
        assert contact_theta_deg(r, normal) == pytest.approx(roll)
    assert contact_theta_deg(np.eye(3), np.array([0.0, 0.0, 1.0])) in (-90.0, 90.0)


def test_edge_angle_in_finger_frame() -> None:
    eye = np.eye(3)
    assert edge_angle_in_finger_deg(eye, np.array([1.0, 0.0, 0.0])) == pytest.approx(0.0)
    assert edge_angle_in_finger_deg(eye, np.array([-1.0, 0.0, 0.0])) == pytest.approx(0.0)
    assert edge_angle_in_finger_deg(eye, np.array([0.0, 1.0, 0.0])) == pytest.approx(90.0)
    assert edge_angle_in_finger_deg(eye, np.array([1.0, 1.0, 0.0]) / math.sqrt(2)) == pytest.approx(45.0)
    assert edge_angle_in_finger_deg(eye, np.array([-1.0, 1.0, 0.0]) / math.sqrt(2)) == pytest.approx(135.0)
    assert edge_angle_in_finger_deg(eye, np.array([0.0, 0.0, 1.0])) == 0.0


# --- scenes --------------------------------------------------------------------------------------------


def test_builtin_primitive_scenes_load() -> None:
    for name in ("sphere", "cube", "task1", "task2", "task3"):
        scene = load_scene(name)
        assert scene.name == name
        q = scene.query(np.array([0.0, 0.0, 0.0]))
        assert isinstance(q, SurfaceQuery) and q.signed_distance_mm > 0


def test_phase2_objects_fit_the_20_cm_box() -> None:
    for name in ("sphere", "cube", "teapot"):
        lo, hi = load_scene(name).bounds_mm
        assert float(np.max(hi - lo)) == pytest.approx(200.0)


def test_nearest_object_wins_and_inside_beats_outside() -> None:
    scene = load_scene("task2")
    q = scene.query(np.array([-200.0, -200.0, 300.0]))
    assert q.object_name == "left" and q.signed_distance_mm == pytest.approx(75.0)
    q = scene.query(np.array([150.0, -200.0, 400.0]))
    assert q.object_name == "right" and q.signed_distance_mm < 0
    inside = scene.contains(np.array([[200.0, -200.0, 400.0], [0.0, -200.0, 400.0], [-250.0, -190.0, 410.0]]))
    assert inside.tolist() == [True, False, True]
    assert scene.contains(np.array([[200.0, -200.0, 400.0]]), objects=["left"]).tolist() == [False]


def test_needs_follow_objects_and_options() -> None:
    cube = load_scene("cube")
    assert cube.needs.as_dict() == {
        "needs_mesh_index": False,
        "needs_features": True,
        "needs_texture": False,
        "needs_orientation": True,
        "needs_contains": False,
    }
    uniform = load_scene("cube", options=RenderOptions(contact_mode="uniform"))
    assert not uniform.needs.needs_orientation
    ua = load_scene("task3", options=RenderOptions(approach="ua"))
    assert ua.needs.needs_contains and not ua.needs.needs_features and not ua.needs.needs_texture
    assert not any(o.classify_features for o in ua.objects)
    assert load_scene("task3").needs.needs_texture
    teapot = load_scene("teapot")
    assert teapot.needs.needs_mesh_index and not teapot.needs.needs_texture


def test_smooth_scene_builds_no_texture_machinery() -> None:
    scene = load_scene("cube")
    assert not scene.needs.needs_texture
    assert scene.built_parts()["texture_lookup"] == []
    textured = load_scene("task3").with_texture_level(0)
    assert not textured.needs.needs_texture
    rough = load_scene("cube").with_texture_level(2)
    assert rough.needs.needs_texture and rough.query(np.zeros(3)).texture_level == 2


def test_regions_are_compiled_only_when_texture_is_rendered(tmp_path: Path) -> None:
    desc = {
        "objects": [
            {
                "type": "box",
                "name": "slab",
                "size_mm": [300, 20, 150],
                "center_mm": [0, -110, 400],
                "texture_regions": [{"lo_mm": [0, -101, 325], "hi_mm": [150, -99, 475], "level": 2}],
            }
        ]
    }
    path = tmp_path / "slab.json"
    path.write_text(json.dumps(desc))
    scene = load_scene(path)
    assert scene.needs.needs_texture and scene.built_parts()["texture_lookup"] == ["slab"]
    assert scene.query(np.array([100.0, -90.0, 400.0])).texture_level == 2
    assert scene.query(np.array([-100.0, -90.0, 400.0])).texture_level == 0
    cam = load_scene(path, options=RenderOptions(approach="cam"))
    assert not cam.needs.needs_texture and cam.built_parts()["texture_lookup"] == []


def test_primitive_scene_never_imports_scipy() -> None:
    code = textwrap.dedent(
        """
        import json, sys
        import numpy as np
        from tactdeform_hw.render.scene import load_scene
        from tactdeform_hw.render.trajectories import make_trajectory
        scene = load_scene("task2")
        scene.prepare()
        poses = make_trajectory("explore", scene)
        for p in poses[::10]:
            scene.query(p.position_mm)
        scene.contains(np.zeros((4, 3)))
        print(json.dumps({"parts": scene.built_parts(), "scipy": "scipy" in sys.modules,
                          "trimesh": "trimesh" in sys.modules, "needs": scene.needs.as_dict()}))
        """
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=REPO, check=True)
    report = json.loads(out.stdout.strip().splitlines()[-1])
    assert report["scipy"] is False and report["trimesh"] is False
    assert report["parts"]["mesh_index"] == [] and not report["needs"]["needs_mesh_index"]


def test_scene_description_toml_and_json_agree(tmp_path: Path) -> None:
    toml_text = textwrap.dedent(
        """
        name = "bars"
        [options]
        contact_mode = "uniform"
        approach = "tactdeform"
        [[objects]]
        type = "box"
        name = "left"
        size_mm = [200, 50, 50]
        center_mm = [-200, -200, 400]
        approach = "cam"
        [[objects]]
        type = "sphere"
        name = "ball"
        radius_mm = 30
        center_mm = [200, -200, 400]
        texture_level = 1
        """
    )
    (tmp_path / "bars.toml").write_text(toml_text)
    data = {
        "name": "bars",
        "options": {"contact_mode": "uniform", "approach": "tactdeform"},
        "objects": [
            {
                "type": "box",
                "name": "left",
                "size_mm": [200, 50, 50],
                "center_mm": [-200, -200, 400],
                "approach": "cam",
            },
            {
                "type": "sphere",
                "name": "ball",
                "radius_mm": 30,
                "center_mm": [200, -200, 400],
                "texture_level": 1,
            },
        ],
    }
    (tmp_path / "bars.json").write_text(json.dumps(data))
    a, b = load_scene(tmp_path / "bars.toml"), load_scene(tmp_path / "bars.json")
    for scene in (a, b):
        assert scene.name == "bars"
        assert scene.options == RenderOptions(contact_mode="uniform", approach="tactdeform")
        assert scene.approach_for("left") == "cam" and scene.approach_for("ball") == "tactdeform"
        assert scene.needs.needs_contains and scene.needs.needs_texture and not scene.needs.needs_orientation
        q = scene.query(np.array([200.0, -200.0, 300.0]))
        assert q.object_name == "ball" and q.signed_distance_mm == pytest.approx(70.0)
    # Command-line options replace the file's.
    assert load_scene(tmp_path / "bars.toml", options=RenderOptions()).options.contact_mode == "orientation"


@pytest.mark.parametrize(
    ("desc", "message"),
    [
        ({"objects": []}, "non-empty list"),
        ({"objects": [{"type": "cone"}]}, "type='cone'"),
        ({"objects": [{"type": "box", "colour": "red"}]}, "unknown key"),
        ({"objects": [{"type": "box", "texture_level": 7}]}, "texture level"),
        ({"objects": [{"type": "box", "approach": "magic"}]}, "approach"),
        ({"objects": [{"type": "box", "size_mm": [1, 2]}]}, "size_mm"),
        ({"objects": [{"type": "box"}], "options": {"contact_mode": "sideways"}}, "contact_mode"),
        ({"objects": [{"type": "mesh"}]}, "needs 'path'"),
        ({"objects": [{"type": "mesh", "path": "nowhere.obj"}]}, "does not exist"),
        ({"objects": [{"type": "box", "name": "a"}, {"type": "box", "name": "a"}]}, "unique"),
        ({"objects": [{"type": "box"}], "extra": 1}, "top-level"),
    ],
)
def test_bad_descriptions_say_what_is_wrong(tmp_path: Path, desc: dict, message: str) -> None:
    path = tmp_path / "bad.json"
    path.write_text(json.dumps(desc))
    with pytest.raises(ConfigurationError, match=message):
        load_scene(path)


def test_unknown_scene_name_lists_builtins() -> None:
    with pytest.raises(ConfigurationError, match="cube"):
        load_scene("dodecahedron")
    assert {"sphere", "cube", "teapot", "bunny"} <= set(BUILTIN_SCENES)


def test_broken_files_are_clear(tmp_path: Path) -> None:
    (tmp_path / "x.toml").write_text("objects = [")
    with pytest.raises(ConfigurationError, match="TOML"):
        load_scene(tmp_path / "x.toml")
    (tmp_path / "x.json").write_text("{")
    with pytest.raises(ConfigurationError, match="JSON"):
        load_scene(tmp_path / "x.json")


def test_scene_from_objects_computes_needs() -> None:
    scene = Scene([Box("a", 10.0), Sphere("b", 5.0, (50, 0, 0), texture_level=2)], approaches={"a": "ua"})
    assert scene.needs.needs_texture and scene.needs.needs_contains and not scene.needs.needs_mesh_index
    with pytest.raises(ConfigurationError, match="unknown object"):
        Scene([Box("a", 10.0)], approaches={"z": "ua"})
    with pytest.raises(ConfigurationError, match="no objects"):
        Scene([])


# --- the teapot -------------------------------------------------------------------------------------------


def test_teapot_data_has_the_published_shape() -> None:
    from tactdeform_hw.render.teapot import control_points, patches

    cp, idx = control_points(), patches()
    assert cp.shape == (306, 3) and idx.shape == (32, 4, 4)
    assert idx.min() == 0 and idx.max() == 305
    np.testing.assert_allclose(cp.min(axis=0), [-3.0, -2.0, 0.0])
    np.testing.assert_allclose(cp.max(axis=0), [3.525, 2.0, 3.15])
    # Neighbouring patches share their border control points (rim patch 0 and body patch 4).
    assert set(idx[0, 3].tolist()) == set(idx[4, 0].tolist())


def test_teapot_mesh_is_upright_and_inside_out_tests_work() -> None:
    from tactdeform_hw.render.teapot import teapot_mesh

    pot = teapot_mesh(center_mm=(0.0, 0.0, 0.0))
    lo, hi = pot.bounds_mm
    size = hi - lo
    assert size[0] == pytest.approx(200.0)  # spout to handle along x
    assert size[1] < size[0] and size[2] < size[0]  # y is up: lower than it is long
    assert not pot.is_watertight  # open spout and lid gap: the winding number decides inside
    body = np.array([0.0, lo[1] + 0.35 * size[1], 0.0])
    q = pot.query(body)
    assert q.signed_distance_mm < -20.0
    above = np.array([0.0, hi[1] + 20.0, 0.0])
    assert pot.query(above).signed_distance_mm == pytest.approx(20.0, abs=0.5)
    assert pot.contains(np.array([body, above])).tolist() == [True, False]
    assert pot.index.sign_method == "winding"


def test_rotated_box_on_the_feature_band_border_keeps_its_feature() -> None:
    """3 mm from the edge of a box whose band is 3 mm: the turned box's rounding must not flip it."""
    r = rotation_from_euler_deg(45.0, 0.0, 0.0)
    centre = np.array([10.0, 20.0, 30.0])
    plain = Box("b", (60.0, 30.0, 90.0), (0.0, 0.0, 0.0))
    turned = Box("b", (60.0, 30.0, 90.0), centre, rotation=r)
    local = np.array([28.0, 12.0, 0.0])
    assert plain.feature_band_mm == 3.0
    assert plain.query(local).feature == "edge"
    assert turned.query(centre + r @ local).feature == "edge"
