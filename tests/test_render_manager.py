"""The pattern manager: state machine, stability windows, hysteresis, event-driven output, frame
interpolation, and numerical stability on bad or extreme input."""

from __future__ import annotations

import math

import numpy as np
import pytest

from tactdeform_hw.errors import LimitError
from tactdeform_hw.render import geometry
from tactdeform_hw.render.contexts import ApproachState, FrameAccumulator, contact_angle_deg
from tactdeform_hw.render.geometry import SurfaceQuery
from tactdeform_hw.render.manager import (
    APPROACHING,
    IDLE,
    INTERACTING,
    ManagerConfig,
    PatternManager,
    quat_axes,
)
from tactdeform_hw.render.patterns import DIRECTIONS, EDGE_ORIENTATIONS

from .render_fakes import PAD_DOWN, FakeFloor, hold_poses, line_poses, pad_down


def run(m: PatternManager, scene: FakeFloor, poses: list) -> list:
    return [m.update(t, p, q, scene.query(p)) for t, p, q in poses]


def ring_of(
    m: PatternManager, pattern: tuple[int, ...], feature: str = "face", orientation: str | None = None
) -> int:
    return m.patterns.frames(feature, orientation).index(pattern)


def press(
    start_z: float,
    end_z: float,
    speed: float,
    rate: float,
    t0: float = 0.0,
    xy: tuple[float, float] = (0.0, 0.0),
    q=PAD_DOWN,
) -> list:
    return line_poses(t0, (xy[0], xy[1], start_z), (xy[0], xy[1], end_z), speed, rate, q)


# --- approaching -------------------------------------------------------------------------------------------


@pytest.mark.parametrize("speed", [20.0, 100.0, 400.0])
@pytest.mark.parametrize("rate", [30.0, 72.0, 120.0])
def test_approach_frame_is_one_per_2mm_of_travel_and_none_is_skipped(speed: float, rate: float) -> None:
    m = PatternManager()
    scene = FakeFloor()
    poses = press(5.0, -13.0, speed, rate)
    shown: list[int] = []
    last_count = -1
    confirming = 0
    for t, p, q in poses:
        out = m.update(t, p, q, scene.query(p))
        depth = -float(p[2])
        if depth < 0:
            assert out.state == IDLE
            continue
        if out.state == IDLE:
            # Onset is confirmed by the next sample in contact (or at once 3 mm deep): one sample late.
            confirming += 1
            assert confirming == 1 and depth < 3.0
            continue
        assert out.state == APPROACHING
        assert m.frame == math.floor(depth / 2.0 + 1e-9)
        rings = [ring_of(m, pat) for _, pat in out.frames]
        jump = m.frame - last_count
        if jump <= 3:
            # Every count passed since the last sample is shown, in order.
            assert rings == [c % 3 for c in range(last_count + 1, m.frame + 1)]
        else:
            # Faster than a whole cycle per sample: every ring at least once, in expansion order,
            # continuing from the last ring shown and ending on n.
            assert set(rings) == {0, 1, 2} and 3 <= len(rings) <= 5 and rings[-1] == m.frame % 3
            assert rings[0] == (last_count + 1) % 3
            assert all(b == (a + 1) % 3 for a, b in zip(rings, rings[1:]))
        shown += rings
        last_count = m.frame
    assert shown[0] == 0 and shown[-1] == math.floor(13.0 / 2.0) % 3


def test_ten_metres_per_second_approach_interpolates_every_frame() -> None:
    m = PatternManager()
    scene = FakeFloor()
    m.update(0.0, (0, 0, 70.0), PAD_DOWN, scene.query(np.array([0, 0, 70.0])))
    dt = 1 / 72
    z = 70.0 - 10000.0 * dt  # 10 m/s: 139 mm in one sample, 69 mm deep
    out = m.update(dt, (0, 0, z), PAD_DOWN, scene.query(np.array([0, 0, z])))
    assert out.state == APPROACHING and m.stats.teleports == 0
    assert m.frame == math.floor(-z / 2.0)
    rings = [ring_of(m, pat) for _, pat in out.frames]
    # Every ring at least once in expansion order, starting at the centre, ending on n.
    assert set(rings) == {0, 1, 2} and rings[0] == 0 and len(rings) <= 5
    assert rings[-1] == m.frame % 3
    assert all(b == (a + 1) % 3 for a, b in zip(rings, rings[1:]))
    times = [tf for tf, _ in out.frames]
    assert times == sorted(times) and 0.0 < times[0] and times[-1] == dt
    # And on through the object at the same speed: still one of each frame per sample, no crash.
    for i in range(2, 6):
        last = m.frame
        z -= 10000.0 * dt
        o = m.update(i * dt, (0, 0, z), PAD_DOWN, scene.query(np.array([0, 0, z])))
        rings = [ring_of(m, pat) for _, pat in o.frames]
        # Every ring at least once, continuing from the last one shown, ending on n.
        assert set(rings) == {0, 1, 2} and len(rings) <= 5
        assert rings[0] == (last + 1) % 3 and rings[-1] == m.frame % 3


def test_hold_overflow_stops_at_the_outer_ring() -> None:
    m = PatternManager(config=ManagerConfig(approach_overflow="hold"))
    outs = run(m, FakeFloor(), press(2.0, -15.0, 50.0, 72.0))
    assert outs[-1].pattern == m.patterns.frames("face")[-1]


def test_reversing_direction_contracts_the_pattern_then_loses_contact() -> None:
    m = PatternManager()
    scene = FakeFloor()
    down = press(3.0, -9.0, 20.0, 72.0)
    up = press(-9.0, 10.0, 20.0, 72.0, t0=down[-1][0] + 1 / 72)[1:]
    outs = run(m, scene, down + up)
    frames = [m_ for m_ in outs]
    states = [o.state for o in frames]
    assert INTERACTING not in states  # a press-and-withdraw is not a rest
    rings = [ring_of(m, pat) for o in outs if o.state == APPROACHING for _, pat in o.frames]
    # Up 0,1,2,0,1 (travel 9 mm = frame 4), then back down frame by frame to 0.
    assert rings[:5] == [0, 1, 2, 0, 1]
    assert rings[5:] == [0, 2, 1, 0]
    assert states[-1] == IDLE and outs[-1].pattern == m.patterns.off


# --- state machine ----------------------------------------------------------------------------------------


def test_idle_approaching_interacting_and_contact_loss_from_each_state() -> None:
    m = PatternManager()
    scene = FakeFloor()
    down = press(4.0, -3.0, 20.0, 72.0)
    rest = hold_poses(down[-1][0], (0, 0, -3.0), 1.0, 72.0)
    outs = run(m, scene, down + rest)
    seen = []
    for o in outs:
        if not seen or seen[-1] != o.state:
            seen.append(o.state)
    assert seen == [IDLE, APPROACHING, INTERACTING]
    assert outs[-1].context == "contact"
    # Interacting → Idle on lift-off.
    lift = press(-3.0, 20.0, 50.0, 72.0, t0=rest[-1][0] + 1 / 72)
    o = run(m, scene, lift)
    assert o[-1].state == IDLE and o[-1].pattern == m.patterns.off
    # Approaching → Idle.
    m2 = PatternManager()
    o2 = run(m2, scene, press(3.0, -2.0, 50.0, 72.0) + press(-2.0, 30.0, 200.0, 72.0, t0=1.0))
    assert APPROACHING in [x.state for x in o2] and o2[-1].state == IDLE


def test_event_driven_output_sends_nothing_while_nothing_changes() -> None:
    m = PatternManager()
    scene = FakeFloor()
    down = press(3.0, -3.0, 20.0, 72.0)
    rest = hold_poses(down[-1][0], (0, 0, -3.0), 5.0, 72.0)
    outs = run(m, scene, down + rest)
    first_interacting = next(i for i, o in enumerate(outs) if o.state == INTERACTING)
    assert outs[first_interacting].frames  # the contact pattern replaces the expansion frame once
    assert sum(len(o.frames) for o in outs[first_interacting + 1 :]) == 0
    assert m.stats.frames_out == sum(len(o.frames) for o in outs)


# --- contact (eq. 4) ----------------------------------------------------------------------------------------


@pytest.mark.parametrize(("roll", "level"), [(-60.0, 0), (-15.0, 1), (15.0, 2), (60.0, 3)])
def test_contact_theta_levels_shift_the_pattern(roll: float, level: int) -> None:
    q = pad_down(roll_deg=roll)
    scene = FakeFloor()
    m = PatternManager()
    poses = press(3.0, -2.0, 20.0, 72.0, q=q)
    poses += hold_poses(poses[-1][0], (0, 0, -2.0), 1.0, 72.0, q)
    outs = run(m, scene, poses)
    assert outs[-1].state == INTERACTING and outs[-1].context == "contact"
    assert m.theta.value == level
    assert m.theta_deg == pytest.approx(roll)
    assert outs[-1].pattern == m.patterns.contact("face", None, level)
    uni = PatternManager(config=ManagerConfig(contact_mode="uniform"))
    assert run(uni, scene, poses)[-1].pattern == uni.patterns.static("face")


def test_theta_near_a_boundary_does_not_flicker() -> None:
    scene = FakeFloor()
    m = PatternManager()
    rng = np.random.default_rng(1)
    poses = press(3.0, -2.0, 20.0, 72.0, q=pad_down(roll_deg=31.0))
    t = poses[-1][0]
    for _ in range(360):
        t += 1 / 72
        poses.append(
            (
                t,
                np.array([0, 0, -2.0]),
                pad_down(roll_deg=30.0 + 3.0 * math.sin(2 * math.pi * 10 * t) + rng.normal(0, 0.5)),
            )
        )
    outs = run(m, scene, poses)
    levels = [m_ for m_ in outs if m_.state == INTERACTING]
    assert levels and m.theta.value in (2, 3)
    assert sum(len(o.frames) for o in levels[1:]) == 0  # one level, kept through ±3.5° of jitter


def test_contact_angle_matches_the_geometry_module() -> None:
    rng = np.random.default_rng(7)
    for _ in range(300):
        q = rng.normal(size=4)
        q /= np.linalg.norm(q)
        n = rng.normal(size=3)
        n /= np.linalg.norm(n)
        X, Y, Z = quat_axes(*q)
        R = np.column_stack([X, Y, Z])
        assert contact_angle_deg(n, X, Z) == pytest.approx(geometry.contact_theta_deg(R, n), abs=1e-9)


# --- edges --------------------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("edge_world", "orientation"),
    [
        ((1.0, 0.0, 0.0), "h"),
        ((0.0, -1.0, 0.0), "v"),
        ((1.0, -1.0, 0.0), "d1"),
        ((-1.0, -1.0, 0.0), "d2"),
        ((1.0, 0.2, 0.0), "h"),
    ],
)
def test_edge_orientation_picks_the_line(edge_world: tuple[float, float, float], orientation: str) -> None:
    e = np.array(edge_world) / np.linalg.norm(edge_world)
    scene = FakeFloor(feature="edge", edge_direction=tuple(e))
    m = PatternManager()
    outs = run(m, scene, press(2.0, -5.0, 20.0, 72.0))
    assert outs[-1].feature == "edge" and outs[-1].orientation == orientation
    assert outs[-1].pattern in m.patterns.frames("edge", orientation)
    X, Y, Z = quat_axes(*PAD_DOWN)
    ang = geometry.edge_angle_in_finger_deg(np.column_stack([X, Y, Z]), e)
    assert EDGE_ORIENTATIONS[int(math.floor(ang / 45.0 + 0.5)) % 4] == orientation


def test_feature_flicker_shorter_than_the_window_is_ignored() -> None:
    flip = {"n": 0}

    def feature(p: np.ndarray) -> str:
        flip["n"] += 1
        return "edge" if flip["n"] % 3 == 0 else "face"  # an edge for one sample in three

    scene = FakeFloor(feature=feature, edge_direction=(1.0, 0.0, 0.0))
    m = PatternManager()
    poses = press(2.0, -1.0, 20.0, 72.0)
    poses += hold_poses(poses[-1][0], (0, 0, -1.0), 2.0, 72.0)
    flip["n"] = 1  # the onset sample reads "face"
    outs = run(m, scene, poses)
    assert {o.feature for o in outs if o.state != IDLE} == {"face"}
    # A real change (held longer than the window) does switch.
    steady = FakeFloor(feature=lambda p: "corner" if p[0] > 5 else "face")
    m2 = PatternManager()
    poses2 = press(2.0, -1.0, 20.0, 72.0) + [
        (1.0 + i / 72, np.array([10.0, 0, -1.0]), PAD_DOWN) for i in range(30)
    ]
    outs2 = run(m2, steady, poses2)
    assert outs2[-1].feature == "corner"


# --- sliding (eq. 5–7) --------------------------------------------------------------------------------------


def slide_run(
    texture: int,
    direction_deg: float = 0.0,
    speed: float = 20.0,
    duration: float = 3.0,
    rate: float = 72.0,
    config: ManagerConfig | None = None,
    tremor_mm: float = 0.0,
):
    scene = FakeFloor(texture_level=texture)
    m = PatternManager(config=config)
    poses = press(2.0, -1.0, 20.0, rate)
    poses += hold_poses(poses[-1][0], (0, 0, -1.0), 0.6, rate)
    t0 = poses[-1][0]
    a = math.radians(direction_deg)
    # Finger x is world +x and finger y is world -y (PAD_DOWN).
    u = np.array([math.cos(a), -math.sin(a), 0.0])
    n = int(duration * rate)
    for i in range(1, n + 1):
        t = t0 + i / rate
        p = np.array([0.0, 0.0, -1.0]) + u * speed * (t - t0)
        if tremor_mm:
            p = p + tremor_mm * np.array(
                [
                    math.sin(2 * math.pi * 9.0 * t),
                    math.sin(2 * math.pi * 11.0 * t + 1.0),
                    0.3 * math.sin(2 * math.pi * 10.0 * t),
                ]
            )
        poses.append((t, p, PAD_DOWN))
    outs = run(m, scene, poses)
    return m, outs, t0


def test_smooth_slide_is_static_k0() -> None:
    m, outs, t0 = slide_run(0)
    sliding = [o for o in outs if o.context == "sliding"]
    assert sliding and {o.pattern for o in sliding} == {m.patterns.static("face")}
    assert m.shift_count == 0


@pytest.mark.parametrize(("k", "hz"), [(1, 10.0), (2, 5.0)])
def test_textured_slide_shifts_at_v_over_d_k(k: int, hz: float) -> None:
    m, outs, t0 = slide_run(k, duration=3.0)
    changes = [tf for o in outs if o.context == "sliding" for tf, _ in o.frames]
    window = [tf for tf in changes if t0 + 1.0 <= tf < t0 + 3.0]
    assert len(window) == pytest.approx(2.0 * hz, abs=1.5)
    ps = m.patterns
    pats = {o.pattern for o in outs if o.context == "sliding"}
    assert pats <= {ps.sliding("face", None, 0, k, ph) for ph in range(ps.mask_period(k))}


@pytest.mark.parametrize("k", [1, 2])
def test_tremor_while_sliding_does_not_rock_the_texture(k: int) -> None:
    m0, calm, t0 = slide_run(k, duration=3.0)
    m1, shaky, _ = slide_run(k, duration=3.0, tremor_mm=1.0)
    n_calm = sum(len(o.frames) for o in calm if o.context == "sliding")
    n_shaky = sum(len(o.frames) for o in shaky if o.context == "sliding")
    assert n_calm > 0 and abs(n_shaky - n_calm) <= 2
    # The texture travel is the smoothed displacement: it telescopes to the stroke length.
    assert m1.slide.travel_mm == pytest.approx(m0.slide.travel_mm, rel=0.1)


@pytest.mark.parametrize("d", range(8))
def test_slide_direction_is_quantised_to_8(d: int) -> None:
    m, outs, _ = slide_run(1, direction_deg=45.0 * d + 12.0)
    assert m.direction.value == d
    assert outs[-1].context == "sliding"
    assert outs[-1].pattern in {
        m.patterns.sliding("face", None, d, 1, ph) for ph in range(m.patterns.mask_period(1))
    }


def test_direction_on_a_bin_boundary_with_tremor_does_not_flicker() -> None:
    scene = FakeFloor(texture_level=1)
    m = PatternManager()
    rate = 72.0
    poses = press(2.0, -1.0, 20.0, rate)
    poses += hold_poses(poses[-1][0], (0, 0, -1.0), 0.6, rate)
    t0 = poses[-1][0]
    a = math.radians(22.5)  # exactly between E and NE
    u = np.array([math.cos(a), -math.sin(a), 0.0])
    for i in range(1, int(3.0 * rate)):
        t = t0 + i / rate
        tremor = np.array(
            [
                math.sin(2 * math.pi * 9.0 * t),
                math.sin(2 * math.pi * 11.0 * t + 1.0),
                0.3 * math.sin(2 * math.pi * 10.0 * t),
            ]
        )
        poses.append((t, np.array([0.0, 0.0, -1.0]) + u * 20.0 * (t - t0) + tremor, PAD_DOWN))
    dirs, ctx = [], []
    for t, p, q in poses:
        o = m.update(t, p, q, scene.query(p))
        if o.context == "sliding":
            dirs.append(m.direction.value)
        if o.state == INTERACTING:
            ctx.append(o.context)
    assert dirs and len(set(dirs)) == 1 and dirs[0] in (0, 1)
    assert ctx[ctx.index("sliding") :].count("contact") == 0  # never drops out of sliding


def test_rightward_only_renders_nothing_on_other_strokes() -> None:
    cfg = ManagerConfig(slide_directions=frozenset({"E"}))
    m, outs, _ = slide_run(1, direction_deg=180.0, config=cfg)
    assert outs[-1].context == "sliding" and outs[-1].pattern == m.patterns.off
    m2, outs2, _ = slide_run(1, direction_deg=0.0, config=cfg)
    assert outs2[-1].pattern != m2.patterns.off


def test_texture_disabled_renders_every_surface_smooth() -> None:
    m, outs, _ = slide_run(2, config=ManagerConfig(use_texture=False))
    assert {o.pattern for o in outs if o.context == "sliding"} == {m.patterns.static("face")}


# --- numerical stability ------------------------------------------------------------------------------------


def test_zero_velocity_zero_dt_and_infinite_gap() -> None:
    m = PatternManager()
    scene = FakeFloor()
    p = np.array([0.0, 0.0, -1.0])
    outs = run(m, scene, press(2.0, -1.0, 20.0, 72.0) + hold_poses(0.15, (0, 0, -1.0), 2.0, 72.0))
    assert outs[-1].state == INTERACTING
    t = outs[-1].t_s
    # Repeated timestamps with (jitter) motion: no division, travel still from displacement.
    for dz in (0.1, -0.2, 0.05):
        o = m.update(t, p + (0, 0, dz), PAD_DOWN, scene.query(p + (0, 0, dz)))
        assert o.dropped is None and o.state == INTERACTING
    # Hours without a sample (Δt → ∞): speed reads 0, contact holds.
    o = m.update(t + 1e7, p, PAD_DOWN, scene.query(p))
    assert o.state == INTERACTING and o.context == "contact" and o.dropped is None
    assert not m.sliding
    # A first sample with nothing before it, and an absurd first time, are fine too.
    fresh = PatternManager()
    assert fresh.update(1e12, p, PAD_DOWN, scene.query(p)).state == IDLE  # onset needs a second sample
    assert fresh.update(1e12 + 1 / 72, p, PAD_DOWN, scene.query(p)).state == APPROACHING


@pytest.mark.parametrize(
    ("t", "pos", "quat", "reason"),
    [
        (math.nan, (0, 0, -1), PAD_DOWN, "time"),
        (math.inf, (0, 0, -1), PAD_DOWN, "time"),
        (1.0, (0, math.nan, -1), PAD_DOWN, "position"),
        (1.0, (0, 0, math.inf), PAD_DOWN, "position"),
        (1.0, (0, 0), PAD_DOWN, "position"),
        (1.0, (0, 0, -1), (math.nan, 0, 0, 1), "orientation"),
        (1.0, (0, 0, -1), (0.0, 0.0, 0.0, 0.0), "orientation-norm"),
        (1.0, (0, 0, -1), (2.0, 0.0, 0.0, 0.0), "orientation-norm"),
        (1.0, (0, 0, -1), "wxyz", "orientation"),
        (0.1, (0, 0, -1), PAD_DOWN, "time-backwards"),
    ],
)
def test_bad_samples_are_counted_drops_that_keep_the_pattern(t, pos, quat, reason) -> None:
    m = PatternManager()
    scene = FakeFloor()
    outs = run(m, scene, press(2.0, -3.0, 20.0, 72.0))
    before = m.pattern
    state = m.state
    q = scene.query(np.array([0.0, 0.0, -3.0]))
    o = m.update(t, pos, quat, q)
    assert o.dropped == reason and o.frames == [] and o.pattern == before and o.state == state
    assert m.stats.dropped[reason] == 1
    # The stream carries on as if the bad sample never came.
    o2 = m.update(outs[-1].t_s + 1 / 72, (0, 0, -3.0), PAD_DOWN, q)
    assert o2.dropped is None and o2.state == state


def test_bad_surface_queries_are_drops() -> None:
    m = PatternManager()
    nan_q = SurfaceQuery("x", math.nan, np.zeros(3), np.array([0, 0, 1.0]), "face", None, 0)
    zero_n = SurfaceQuery("x", -1.0, np.zeros(3), np.zeros(3), "face", None, 0)
    odd = SurfaceQuery("x", -1.0, np.zeros(3), np.array([0, 0, 1.0]), "vertex", None, 0)
    for i, q in enumerate((nan_q, zero_n, odd)):
        assert m.update(float(i), (0, 0, -1), PAD_DOWN, q).dropped == "query"
    assert m.state == IDLE and m.stats.dropped_total == 3


def test_nearly_unit_quaternions_are_normalised_not_dropped() -> None:
    m = PatternManager()
    scene = FakeFloor()
    q = tuple(1.005 * c for c in pad_down(roll_deg=60.0))
    poses = [(t, p, q) for t, p, _ in press(2.0, -2.0, 20.0, 72.0)]
    poses += [(t, p, q) for t, p, _ in hold_poses(poses[-1][0], (0, 0, -2.0), 1.0, 72.0)]
    outs = run(m, scene, poses)
    assert m.stats.dropped_total == 0 and m.stats.normalised_quaternions == len(poses)
    assert m.theta_deg == pytest.approx(60.0) and outs[-1].state == INTERACTING


def test_teleporting_pose_is_not_travel() -> None:
    m = PatternManager()
    scene = FakeFloor()
    run(m, scene, press(2.0, -3.0, 20.0, 72.0))
    assert m.frame == 1
    t = m._t + 1 / 72  # 900 mm in one 72 Hz sample: 65 m/s
    o = m.update(t, (0.0, 0.0, 900.0), PAD_DOWN, scene.query(np.array([0, 0, 900.0])))  # glitch
    assert m.stats.teleports == 1 and o.state == IDLE and o.pattern == m.patterns.off
    o = m.update(t + 1 / 72, (0.0, 0.0, -5.0), PAD_DOWN, scene.query(np.array([0, 0, -5.0])))
    assert m.stats.teleports == 2
    # A fresh contact 5 mm deep: frame 2, nothing of the 905 mm jump counted.
    assert o.state == APPROACHING and m.frame == 2 and m.approach.travel_mm == pytest.approx(5.0)
    # A teleport between two places inside the object does the same (1 mm deep: confirmed by the next sample).
    o = m.update(t + 2 / 72, (400.0, 0.0, -1.0), PAD_DOWN, scene.query(np.array([400.0, 0, -1.0])))
    assert m.stats.teleports == 3 and o.state == IDLE
    o = m.update(t + 3 / 72, (400.0, 0.0, -1.0), PAD_DOWN, scene.query(np.array([400.0, 0, -1.0])))
    assert o.state == APPROACHING and m.frame == 0 and m.approach.travel_mm == pytest.approx(1.0)


@pytest.mark.parametrize("freq", [8.0, 10.0, 12.0])
@pytest.mark.parametrize("rate", [72.0, 90.0, 120.0])
@pytest.mark.parametrize("rest_z", [-0.5, 0.4])
def test_tremor_does_not_flicker_the_state(freq: float, rate: float, rest_z: float) -> None:
    m = PatternManager()
    scene = FakeFloor()
    poses = press(3.0, rest_z, 20.0, rate)
    t0 = poses[-1][0]
    amp = 1.0
    for i in range(1, int(4.0 * rate)):
        t = t0 + i / rate
        w = 2 * math.pi * freq * t
        jitter = amp * np.array([math.sin(w + 0.3), math.sin(1.1 * w + 1.0), math.sin(w)])
        poses.append((t, np.array([0.0, 0.0, rest_z]) + jitter, PAD_DOWN))
    outs = run(m, scene, poses)
    states = [o.state for o in outs]
    first = states.index(APPROACHING)
    changes = [(a, b) for a, b in zip(states[first:], states[first + 1 :]) if a != b]
    assert changes == [(APPROACHING, INTERACTING)]
    ctx = [o.context for o in outs if o.state == INTERACTING]
    assert set(ctx) == {"contact"}
    # Once interacting, tremor changes nothing on the pad.
    k = states.index(INTERACTING)
    assert sum(len(o.frames) for o in outs[k + 1 :]) == 0


def test_eight_hour_session_accumulates_travel_without_drift() -> None:
    rate = 72.0
    n = int(8 * 3600 * rate)
    t = np.arange(n + 1) / rate
    # Press-and-release motion along the normal, 0–14 mm deep, with tracker noise.
    rng = np.random.default_rng(3)
    depth = 7.0 - 7.0 * np.cos(2 * np.pi * 0.4 * t) + rng.normal(0.0, 0.05, t.size)
    steps = np.diff(depth).tolist()
    acc = FrameAccumulator(2.0)
    add = acc.add
    for d in steps:
        add(d)
    exact = float(depth[-1] - depth[0])
    assert abs(acc.travel_mm - exact) < 1e-9
    assert acc.whole == math.floor(exact / 2.0)
    # Frame counts at the end of the session are those of the net travel.
    st = ApproachState(2.0, release_mm=0.0)
    st.begin(float(depth[0]))
    adv = st.advance
    for d in steps[: int(3600 * rate)]:
        adv(d)
    assert st.frame == math.floor(float(depth[int(3600 * rate)]) / 2.0)


def test_late_session_timestamps_keep_windows_exact() -> None:
    """Eight hours in, t is ~28 800 s; windows of 70–300 ms must behave as at t = 0."""
    scene = FakeFloor()
    t_base = 8 * 3600.0
    early = PatternManager()
    late = PatternManager()
    poses = press(3.0, -3.0, 20.0, 72.0)
    poses += hold_poses(poses[-1][0], (0, 0, -3.0), 1.0, 72.0)
    a = [(o.state, o.pattern) for o in run(early, scene, poses)]
    b = [(o.state, o.pattern) for o in run(late, scene, [(t + t_base, p, q) for t, p, q in poses])]
    assert a == b


def test_config_is_checked() -> None:
    with pytest.raises(LimitError, match="contact_mode"):
        ManagerConfig(contact_mode="both")  # type: ignore[arg-type]
    with pytest.raises(LimitError, match="slide_on_mm_s"):
        ManagerConfig(slide_on_mm_s=5.0, slide_off_mm_s=8.0)
    with pytest.raises(LimitError, match="feature_window_s"):
        ManagerConfig(feature_window_s=-0.1)
    with pytest.raises(LimitError, match="slide_directions"):
        ManagerConfig(slide_directions=frozenset({"right"}))
    with pytest.raises(LimitError, match="alpha"):
        ManagerConfig(alpha=0.0)
    with pytest.raises(LimitError, match="frame_release_mm"):
        PatternManager(config=ManagerConfig(frame_release_mm=2.5))
    assert DIRECTIONS[0] == "E"


def test_frame_error_tool_shows_displacement_has_no_drift() -> None:
    import importlib.util
    from pathlib import Path

    path = Path(__file__).resolve().parents[1] / "tools" / "frame_error.py"
    spec = importlib.util.spec_from_file_location("frame_error", path)
    assert spec is not None and spec.loader is not None
    tool = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(tool)
    res = tool.frame_errors(120.0, 72.0, 0, ("displacement", "velocity-rect"))
    disp, vel = res["displacement"], res["velocity-rect"]
    # Sampling latency only: under a tenth of a frame on average, never more than 2 frames.
    assert max(disp["mean_abs"]) < 0.15 and max(disp["max_abs"]) <= 2
    assert vel["mean_abs"][-1] > disp["mean_abs"][-1]


def test_tactdeform_and_the_baselines_count_updates_drops_and_renormalised_quaternions_alike() -> None:
    from tactdeform_hw.render.baselines import UniformActivation

    q = tuple(1.005 * c for c in PAD_DOWN)
    samples = [(0.0, (0, 0, 5.0), q), (1.0, (0, 0, 5.0), PAD_DOWN), (0.5, (0, 0, 5.0), q), (2.0, (0, 0), q)]
    for manager in (PatternManager(), UniformActivation()):
        dropped = [manager.update(t, p, o, None).dropped for t, p, o in samples]
        assert dropped == [None, None, "time-backwards", "position"]
        assert manager.stats.updates == 4 and manager.stats.normalised_quaternions == 1
        assert manager.stats.dropped == {"time-backwards": 1, "position": 1}
