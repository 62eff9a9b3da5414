"""Poses, their validation and CSV replay; the synthetic study trajectories."""

from __future__ import annotations

import io
import math
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from tactdeform_hw.errors import ConfigurationError, LimitError
from tactdeform_hw.render.geometry import contact_theta_deg, edge_angle_in_finger_deg
from tactdeform_hw.render.scene import load_scene
from tactdeform_hw.render.tracking import (
    POSE_CSV_COLUMNS,
    Pose,
    PoseValidator,
    matrix_to_quat,
    quat_from_axis_angle,
    quat_multiply,
    quat_to_matrix,
    read_pose_csv,
    rotation_from_euler_deg,
    write_pose_csv,
)
from tactdeform_hw.render.trajectories import (
    CONTACT_THETA_DEG,
    TRAJECTORIES,
    make_trajectory,
    scene_for_trajectory,
)

unit = st.floats(min_value=-1.0, max_value=1.0, allow_nan=False)


# --- rotations --------------------------------------------------------------------------------------------


@settings(max_examples=200, deadline=None)
@given(unit, unit, unit, unit)
def test_quaternion_matrix_round_trip(w: float, x: float, y: float, z: float) -> None:
    q = np.array([w, x, y, z])
    if np.linalg.norm(q) < 1e-3:
        return
    q /= np.linalg.norm(q)
    r = quat_to_matrix(q)
    np.testing.assert_allclose(r.T @ r, np.eye(3), atol=1e-12)
    assert np.linalg.det(r) == pytest.approx(1.0)
    back = matrix_to_quat(r)
    assert abs(float(np.dot(back, q))) == pytest.approx(1.0, abs=1e-9)  # q and -q are the same rotation
    assert back[0] >= 0


def test_quaternion_composition_matches_matrices() -> None:
    a = quat_from_axis_angle([1, 2, 3], 40.0)
    b = quat_from_axis_angle([0, 1, 0], -75.0)
    np.testing.assert_allclose(
        quat_to_matrix(quat_multiply(a, b)), quat_to_matrix(a) @ quat_to_matrix(b), atol=1e-12
    )
    np.testing.assert_allclose(rotation_from_euler_deg(0, 0, 90) @ [1, 0, 0], [0, 1, 0], atol=1e-12)


# --- poses ----------------------------------------------------------------------------------------------


def test_identity_finger_frame_points_up_with_the_pad_forward() -> None:
    pose = Pose(0.0, np.array([1.0, 2.0, 3.0]))
    np.testing.assert_allclose(pose.x_axis, [1, 0, 0])
    np.testing.assert_allclose(pose.y_axis, [0, 1, 0])
    np.testing.assert_allclose(pose.z_axis, [0, 0, 1])
    np.testing.assert_allclose(pose.to_world(np.array([2.0, 0.0, 0.0])), [3, 2, 3])


def test_to_world_and_back() -> None:
    q = quat_from_axis_angle([0.3, -1, 0.2], 123.0)
    pose = Pose(1.5, np.array([10.0, -5.0, 400.0]), q)
    pts = np.random.default_rng(0).normal(size=(10, 3)) * 5
    np.testing.assert_allclose(pose.to_finger(pose.to_world(pts)), pts, atol=1e-12)
    np.testing.assert_allclose(pose.rotation[:, 2], pose.z_axis)
    np.testing.assert_allclose(pose.direction_to_finger(pose.x_axis), [1, 0, 0], atol=1e-12)


def test_near_unit_quaternions_are_normalised_far_off_ones_refused() -> None:
    pose = Pose(0.0, np.zeros(3), np.array([1.004, 0.0, 0.0, 0.0]))
    assert np.linalg.norm(pose.orientation) == pytest.approx(1.0)
    with pytest.raises(LimitError, match="norm"):
        Pose(0.0, np.zeros(3), np.array([2.0, 0.0, 0.0, 0.0]))
    with pytest.raises(LimitError, match="norm"):
        Pose(0.0, np.zeros(3), np.zeros(4))


@pytest.mark.parametrize(
    ("t", "pos", "quat", "field"),
    [
        (math.nan, [0, 0, 0], [1, 0, 0, 0], "t_s"),
        (0.0, [0, math.inf, 0], [1, 0, 0, 0], "position_mm"),
        (0.0, [0, 0, 0], [math.nan, 0, 0, 0], "orientation"),
    ],
)
def test_non_finite_poses_are_refused_naming_the_field(t: float, pos: list, quat: list, field: str) -> None:
    with pytest.raises(LimitError, match=field):
        Pose(t, np.array(pos, dtype=float), np.array(quat, dtype=float))


def test_pose_arrays_are_read_only() -> None:
    pose = Pose(0.0, np.zeros(3))
    with pytest.raises(ValueError):
        pose.position_mm[0] = 1.0


def test_validator_counts_drops_by_reason() -> None:
    v = PoseValidator()
    assert v.check(0.0, [0, 0, 0], [1, 0, 0, 0]) is not None
    assert v.check(0.01, [math.nan, 0, 0], [1, 0, 0, 0]) is None
    assert v.check(0.02, [0, 0, 0], [0.5, 0, 0, 0]) is None
    assert v.check(0.0, [0, 0, 0], [1, 0, 0, 0]) is None  # back in time
    assert v.check(0.03, [0, 0], [1, 0, 0, 0]) is None
    ok = v.check(0.04, [0, 0, 0], [0.9999, 0.0, 0.0, 0.0])
    assert ok is not None and np.linalg.norm(ok.orientation) == pytest.approx(1.0)
    assert dict(v.drops) == {"non_finite": 1, "quaternion_norm": 1, "time_not_increasing": 1, "malformed": 1}
    assert v.accepted == 2 and v.dropped == 4
    strict = PoseValidator(on_invalid="error")
    with pytest.raises(ConfigurationError, match="NaN"):
        strict.check(0.0, [math.nan, 0, 0], [1, 0, 0, 0])


# --- CSV replay -----------------------------------------------------------------------------------------


def test_csv_round_trip_is_exact(tmp_path: Path) -> None:
    rng = np.random.default_rng(1)
    poses = []
    for i in range(20):
        q = rng.normal(size=4)
        poses.append(Pose(i / 72.0, rng.normal(size=3) * 100, q / np.linalg.norm(q)))
    path = tmp_path / "poses.csv"
    assert write_pose_csv(path, poses) == 20
    assert path.read_text().splitlines()[0] == ",".join(POSE_CSV_COLUMNS)
    back = read_pose_csv(path)
    assert len(back) == 20
    for a, b in zip(poses, back):
        assert a.t_s == b.t_s
        np.testing.assert_array_equal(a.position_mm, b.position_mm)
        np.testing.assert_array_equal(a.orientation, b.orientation)


HEADER = "t_s,x_mm,y_mm,z_mm,qw,qx,qy,qz\n"


@pytest.mark.parametrize(
    ("body", "message"),
    [
        ("0,0,0,0,1,0,0,0\n0.1,0,zero,0,1,0,0,0\n", r"row 2, column 'y_mm': 'zero' is not a number"),
        ("0,0,0,0,1,0,0,0\n0.1,0,0,0,1,0,0\n", r"row 2, column 'qz': missing value"),
        ("0,0,0,0,1,0,0,0\n0.1,0,0,nan,1,0,0,0\n", r"row 2, column 'z_mm'.*not finite"),
        ("0,0,0,0,2,0,0,0\n", r"row 1, columns 'qw'..'qz': quaternion norm 2"),
        ("0.5,0,0,0,1,0,0,0\n0.4,0,0,0,1,0,0,0\n", r"row 2, column 't_s'"),
    ],
)
def test_csv_errors_name_row_and_column(body: str, message: str) -> None:
    with pytest.raises(ConfigurationError, match=message):
        read_pose_csv(io.StringIO(HEADER + body))


def test_csv_header_and_drop_mode() -> None:
    with pytest.raises(ConfigurationError, match="lacks column"):
        read_pose_csv(io.StringIO("t_s,x_mm\n0,0\n"))
    text = (
        HEADER + "# comment\n0,0,0,0,1,0,0,0\n\n0.1,nan,0,0,1,0,0,0\n0.2,0,0,0,3,0,0,0\n0.3,1,2,3,1,0,0,0\n"
    )
    validator = PoseValidator()
    poses = read_pose_csv(io.StringIO(text), invalid="drop", validator=validator)
    assert [p.t_s for p in poses] == [0.0, 0.3]
    assert dict(validator.drops) == {"non_finite": 1, "quaternion_norm": 1}


def test_csv_with_extra_columns_in_any_order() -> None:
    text = "note,qz,qy,qx,qw,z_mm,y_mm,x_mm,t_s\nhello,0,0,0,1,3,2,1,0.5\n"
    (pose,) = read_pose_csv(io.StringIO(text))
    assert pose.t_s == 0.5
    np.testing.assert_array_equal(pose.position_mm, [1, 2, 3])


# --- trajectories --------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def cube():
    return load_scene("cube")


def _contact_queries(scene, poses):
    return [(p, scene.query(p.position_mm)) for p in poses]


def test_every_trajectory_builds_on_the_cube_and_task3(cube) -> None:
    task3 = load_scene("task3")
    for name in TRAJECTORIES:
        scene = scene_for_trajectory(name, task3 if name.startswith("slide-") else cube)
        poses = make_trajectory(name, scene)
        assert len(poses) > 50, name
        ts = np.array([p.t_s for p in poses])
        np.testing.assert_allclose(np.diff(ts), 1 / 72.0, atol=1e-12)
        sd = np.array([scene.query(p.position_mm).signed_distance_mm for p in poses])
        assert sd[0] >= 80.0 - 1e-9, name  # every task starts at least 8 cm away
        assert sd.min() < 0, name  # and comes into contact
        assert sd.min() > -3.0 - 1e-6, name  # a few mm of penetration, never more


@pytest.mark.parametrize("orientation, angle", [("h", 0.0), ("v", 90.0), ("d1", 45.0), ("d2", 135.0)])
def test_edge_approaches_show_the_edge_in_the_asked_orientation(cube, orientation: str, angle: float) -> None:
    poses = make_trajectory(f"approach-edge-{orientation}", cube)
    contact = [(p, q) for p, q in _contact_queries(cube, poses) if q.signed_distance_mm <= 0]
    assert contact
    for p, q in contact:
        assert q.feature == "edge"
        measured = edge_angle_in_finger_deg(p.rotation, q.edge_direction)
        assert min(abs(measured - angle), 180 - abs(measured - angle)) < 1e-6


def test_approach_moves_along_the_normal_at_the_asked_speed(cube) -> None:
    poses = make_trajectory("approach-face", cube, speed_mm_s=150.0, rate_hz=90.0, approach_speed_mm_s=100.0)
    pos = np.array([p.position_mm for p in poses])
    sd = np.array([cube.query(p).signed_distance_mm for p in pos])
    normal = cube.query(pos[0]).normal
    moves = np.diff(pos, axis=0)
    toward = np.diff(sd) < -1e-9
    away = np.diff(sd) > 1e-9
    # Whole frames inside each phase move at that phase's speed, straight along the normal.
    inner = toward[1:-1] & toward[:-2] & toward[2:]
    speeds_in = np.linalg.norm(moves[1:-1][inner], axis=1) * 90.0
    np.testing.assert_allclose(speeds_in, 150.0, rtol=1e-9)
    inner_out = away[1:-1] & away[:-2] & away[2:]
    np.testing.assert_allclose(np.linalg.norm(moves[1:-1][inner_out], axis=1) * 90.0, 100.0, rtol=1e-9)
    for m in moves[toward]:
        assert float(np.dot(m / np.linalg.norm(m), normal)) == pytest.approx(-1.0)
    for p in poses:  # the pad faces the surface throughout
        assert float(np.dot(p.z_axis, normal)) == pytest.approx(-1.0)


def test_corner_and_face_approaches_hit_their_feature(cube) -> None:
    for name, feature in (("approach-face", "face"), ("approach-corner", "corner")):
        poses = make_trajectory(name, cube)
        feats = {q.feature for _, q in _contact_queries(cube, poses) if q.signed_distance_mm <= 0}
        assert feats == {feature}


@pytest.mark.parametrize("level", list(CONTACT_THETA_DEG))
def test_contact_tasks_land_theta_in_each_level(cube, level: str) -> None:
    bounds = {
        "steep-left": (-90, -30),
        "shallow-left": (-30, 0),
        "shallow-right": (0, 30),
        "steep-right": (30, 90),
    }
    poses = make_trajectory(f"contact-{level}", cube)
    contact = [(p, q) for p, q in _contact_queries(cube, poses) if q.signed_distance_mm <= 0]
    lo, hi = bounds[level]
    for p, q in contact:
        assert lo <= contact_theta_deg(p.rotation, q.normal) < hi
    # Stationary while in full contact.
    deepest = [p for p, q in contact if q.signed_distance_mm <= -3.0 + 1e-9]
    assert len(deepest) > 72  # at least a second of stationary contact
    assert np.ptp([p.position_mm for p in deepest], axis=0).max() < 1e-9


@pytest.mark.parametrize("texture, level", [("smooth", 0), ("rough", 1), ("rougher", 2)])
def test_slides_stroke_rightward_over_their_texture(texture: str, level: int) -> None:
    scene = scene_for_trajectory(f"slide-{texture}", load_scene("task3"))
    poses = make_trajectory(f"slide-{texture}", scene, speed_mm_s=20.0)
    contact = [(p, q) for p, q in _contact_queries(scene, poses) if q.signed_distance_mm <= 0]
    assert {q.texture_level for _, q in contact} == {level}
    pos = np.array([p.position_mm for p, _ in contact])
    moves = np.diff(pos, axis=0)
    # The stroke: moves along the surface (the lead-in press is along the normal).
    along = np.array([abs(float(np.dot(m, q.normal))) < 1e-9 for m, (_, q) in zip(moves, contact[:-1])])
    sliding = (np.linalg.norm(moves, axis=1) > 1e-9) & along
    assert sliding.sum() > 100
    for (p, _), m, s in zip(contact[:-1], moves, sliding):
        if s:
            assert float(np.dot(m, p.x_axis)) > 0.99 * np.linalg.norm(m)  # rightward in the finger frame
    assert np.median(np.linalg.norm(moves[sliding], axis=1)) * 72.0 == pytest.approx(20.0, rel=1e-6)
    assert float(np.dot(contact[0][0].z_axis, [0.0, -1.0, 0.0])) == pytest.approx(1.0)  # palm down


def test_slide_over_a_texture_the_scene_lacks(cube) -> None:
    assert scene_for_trajectory("slide-smooth", cube) is cube
    rough = scene_for_trajectory("slide-rough", cube)
    assert rough is not cube and rough.needs.needs_texture
    poses = make_trajectory("slide-rough", rough)
    assert {rough.query(p.position_mm).texture_level for p in poses} == {1}
    with pytest.raises(ConfigurationError, match="rough"):
        make_trajectory("slide-rough", cube)


def test_explore_touches_and_stays_shallow(cube) -> None:
    poses = make_trajectory("explore", cube)
    sd = np.array([cube.query(p.position_mm).signed_distance_mm for p in poses])
    touching = sd <= 0
    starts = np.flatnonzero(touching[1:] & ~touching[:-1])
    assert len(starts) >= 3  # several touches
    assert sd.min() > -3.0 - 1e-6


def test_tremor_and_noise_are_seeded(cube) -> None:
    a = make_trajectory("contact-steep-left", cube, seed=4, tremor_mm=1.0, noise_mm=0.05)
    b = make_trajectory("contact-steep-left", cube, seed=4, tremor_mm=1.0, noise_mm=0.05)
    c = make_trajectory("contact-steep-left", cube, seed=5, tremor_mm=1.0, noise_mm=0.05)
    assert all(np.array_equal(p.position_mm, q.position_mm) for p, q in zip(a, b))
    assert not all(np.array_equal(p.position_mm, q.position_mm) for p, q in zip(a, c))


def test_tremor_has_its_amplitude_and_frequency(cube) -> None:
    clean = make_trajectory("contact-shallow-right", cube, rate_hz=240.0)
    shaky = make_trajectory(
        "contact-shallow-right", cube, rate_hz=240.0, tremor_mm=1.0, tremor_hz=10.0, seed=2
    )
    delta = np.array([s.position_mm - c.position_mm for s, c in zip(shaky, clean)])
    amplitude = np.linalg.norm(delta, axis=1)
    assert amplitude.max() == pytest.approx(1.0, abs=0.01)
    axis = delta[np.argmax(amplitude)] / amplitude.max()
    signal = delta @ axis
    spectrum = np.abs(np.fft.rfft(signal))
    freqs = np.fft.rfftfreq(len(signal), 1 / 240.0)
    assert freqs[np.argmax(spectrum)] == pytest.approx(10.0, abs=0.5)
    drawn = make_trajectory("contact-shallow-right", cube, rate_hz=240.0, tremor_mm=1.0, seed=9)
    d = np.array([s.position_mm - c.position_mm for s, c in zip(drawn, clean)])
    sig = d @ (d[np.argmax(np.linalg.norm(d, axis=1))] / np.linalg.norm(d, axis=1).max())
    f = np.fft.rfftfreq(len(sig), 1 / 240.0)[np.argmax(np.abs(np.fft.rfft(sig)))]
    assert 7.5 <= f <= 12.5


def test_very_fast_approaches_and_other_rates(cube) -> None:
    fast = make_trajectory("approach-face", cube, speed_mm_s=10_000.0)
    assert len(fast) > 10 and min(cube.query(p.position_mm).signed_distance_mm for p in fast) < 0
    for rate in (30.0, 90.0, 120.0):
        poses = make_trajectory("approach-corner", cube, rate_hz=rate)
        np.testing.assert_allclose(np.diff([p.t_s for p in poses]), 1 / rate, atol=1e-12)


def test_bad_requests_are_refused(cube) -> None:
    with pytest.raises(ConfigurationError, match="unknown trajectory"):
        make_trajectory("approach-sideways", cube)
    with pytest.raises(ConfigurationError, match="no edge"):
        make_trajectory("approach-edge-h", load_scene("sphere"))
    with pytest.raises(LimitError, match="speed_mm_s"):
        make_trajectory("approach-face", cube, speed_mm_s=0.0)
    with pytest.raises(LimitError, match="rate_hz"):
        make_trajectory("approach-face", cube, rate_hz=math.nan)
    with pytest.raises(LimitError, match="start_distance_mm"):
        make_trajectory("approach-face", cube, start_distance_mm=50.0)


@pytest.mark.parametrize(
    ("field", "value"), [("penetration_mm", 1e300), ("penetration_mm", 101.0), ("start_distance_mm", 1e300)]
)
def test_a_trajectory_beyond_a_touch_is_refused_naming_the_field(cube, field: str, value: float) -> None:
    """Found by fuzzing: a penetration of 1e300 mm overflowed the trajectory's arithmetic."""
    with pytest.raises(LimitError, match=field):
        make_trajectory("approach-face", cube, **{field: value})
