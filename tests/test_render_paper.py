"""The renderer against the paper's equations (renderer spec, eq. 1–7, the state machine, the baselines),
each test written from the equation or the spec's sentence, not from the renderer's output: a
directional texture, eq. 4 on the whole base pattern, parameters latched at contact, slow and fast
fingers, edges and corners expanding like faces, stability-filtered onset, θ on a bin boundary, and
lost tracking switching stimulation off."""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import pytest

from tactdeform_hw.render.array import ElectrodeArray
from tactdeform_hw.render.contexts import THETA_TOLERANCE_DEG, theta_level
from tactdeform_hw.render.geometry import PadPlane
from tactdeform_hw.render.manager import APPROACHING, IDLE, INTERACTING, ManagerConfig, PatternManager
from tactdeform_hw.render.patterns import DIRECTIONS, EDGE_ORIENTATIONS, PatternSet
from tactdeform_hw.render.pipeline import LOST_TRACKING_S, Renderer
from tactdeform_hw.render.primitives import Box
from tactdeform_hw.render.tracking import frame_from_z_y, matrix_to_quat

from .render_fakes import PAD_DOWN, FakeFloor, hold_poses, line_poses, pad_down

PAD = ElectrodeArray.tactdeform()
D_MM = 2.0  # d_electrode


def quat_facing(
    normal: np.ndarray, y_hint: tuple[float, float, float] = (0.0, 0.0, 1.0)
) -> tuple[float, ...]:
    """A pad pressing against a surface of outward normal ``normal``: its z axis (out of the pad) is -n."""
    r = frame_from_z_y(-np.asarray(normal, dtype=float), y_hint)
    return tuple(float(v) for v in matrix_to_quat(r))


def run(m: PatternManager, scene: Any, poses: list) -> list:
    return [m.update(t, p, q, scene.query(np.asarray(p, dtype=float))) for t, p, q in poses]


def sliding_stroke(
    k: int, speed: float, duration: float, *, beta: float = 1.0, rate: float = 72.0
) -> tuple[PatternManager, list, float]:
    """Press 1 mm into a floor of texture level k, rest, then slide rightward (finger +x) at ``speed``."""
    m = PatternManager(config=ManagerConfig(beta=beta))
    scene = FakeFloor(texture_level=k)
    poses = line_poses(0.0, (0, 0, 2.0), (0, 0, -1.0), 20.0, rate)
    poses += hold_poses(poses[-1][0], (0, 0, -1.0), 0.8, rate)
    t0 = poses[-1][0]
    n = int(duration * rate)
    poses += [(t0 + i / rate, np.array([speed * i / rate, 0.0, -1.0]), PAD_DOWN) for i in range(1, n + 1)]
    return m, run(m, scene, poses), t0


# --- finding 1: the texture travels against the finger ---------------------------------------------------


def stripe_columns(pattern: tuple[int, ...], y: float = 1.0) -> set[float]:
    pos = PAD.positions_mm
    return {float(x) for (x, yy), v in zip(pos, pattern) if v and yy == y}


@pytest.mark.parametrize("k", [1, 2])
def test_rightward_finger_sees_the_texture_move_left(k: int) -> None:
    m, outs, _ = sliding_stroke(k, 20.0, 2.0)
    seq = [pat for o in outs if o.context == "sliding" for _, pat in o.frames]
    assert len(seq) >= 6
    # Eq. 5 with β = +1: each shift moves the stripes k spacings (2k mm) to the left, opposite the finger.
    period_mm = m.patterns.mask_period(k) * D_MM
    for a, b in zip(seq, seq[1:]):
        moved = {(x - k * D_MM + 5.0) % period_mm for x in stripe_columns(a)}
        assert {(x + 5.0) % period_mm for x in stripe_columns(b)} == moved
    # β = -1 moves them with the finger: the two settings give different sequences.
    _, outs_b, _ = sliding_stroke(k, 20.0, 2.0, beta=-1.0)
    seq_b = [pat for o in outs_b if o.context == "sliding" for _, pat in o.frames]
    for a, b in zip(seq_b, seq_b[1:]):
        moved = {(x + k * D_MM + 5.0) % period_mm for x in stripe_columns(a)}
        assert {(x + 5.0) % period_mm for x in stripe_columns(b)} == moved
    assert seq_b[:4] != seq[:4]


def test_a_two_state_mask_is_refused() -> None:
    from tactdeform_hw.errors import LimitError
    from tactdeform_hw.render.patterns import PatternParams

    with pytest.raises(LimitError, match="mask_period_factor"):
        PatternParams(mask_period_factor=2)


# --- finding 2: eq. 4 shifts the feature's whole base pattern ----------------------------------------------


@pytest.mark.parametrize(
    ("feature", "orientation"), [("face", None), ("corner", None)] + [("edge", o) for o in EDGE_ORIENTATIONS]
)
def test_contact_pattern_is_the_whole_base_pattern_shifted(feature: str, orientation: str | None) -> None:
    ps = PatternSet(PAD)
    base = ps.static(feature, orientation)
    pos = PAD.positions_mm
    shapes = []
    for level, c in enumerate((-4.0, -2.0, 2.0, 4.0)):
        want = tuple(base[j] if (j := PAD.index_at(x - c, y)) >= 0 else 0 for x, y in pos)
        got = ps.contact(feature, orientation, level)
        assert got == want  # overlap 1.0 with P_base(x - Δx, y)
        shapes.append(got)
    assert len(set(shapes)) == 4  # four distinct levels for every feature
    # A horizontal edge stays a line: two rows, at least four columns wide at every level.
    if orientation == "h":
        for got in shapes:
            on = pos[np.array(got, dtype=bool)]
            assert set(on[:, 1]) == {-1.0, 1.0} and len(set(on[:, 0])) >= 4


# --- findings 3 and 5: latched features, one frame per 2 mm along the bisector, corners from frame 0 --------


CUBE = Box("cube", 50.0, (0.0, 0.0, 0.0))


def bisector_approach(
    corner: bool, depth_mm: float, speed: float = 20.0, rate: float = 72.0, yaw_turn_deg: float = 0.0
) -> tuple[PatternManager, list, np.ndarray, np.ndarray]:
    """Approach the cube's top-front edge (or top-front-right corner) along its bisector."""
    tip = np.array([25.0 if corner else 0.0, 25.0, 25.0])
    n = np.array([1.0 if corner else 0.0, 1.0, 1.0])
    n /= np.linalg.norm(n)
    start, end = tip + 6.0 * n, tip - depth_mm * n
    poses = line_poses(0.0, tuple(start), tuple(end), speed, rate, quat_facing(n, (1.0, 0.0, 0.0)))
    if yaw_turn_deg:
        # The finger turns about the bisector during the approach.
        turned = []
        for t, p, q in poses:
            past = float(np.dot(tip - p, n))  # travel past the edge; the turn starts after contact
            if past <= 1.0:
                turned.append((t, p, q))
                continue
            a = math.radians(yaw_turn_deg * min(1.0, (past - 1.0) / (depth_mm - 1.0)))
            hint = np.cos(a) * np.array([1.0, 0.0, 0.0]) + np.sin(a) * np.cross(n, [1.0, 0.0, 0.0])
            turned.append((t, p, quat_facing(n, tuple(hint))))
        poses = turned
    m = PatternManager()
    outs = run(m, CUBE, poses)
    return m, outs, tip, n


@pytest.mark.parametrize("corner", [False, True])
def test_edges_and_corners_expand_one_frame_per_2mm_along_the_bisector(corner: bool) -> None:
    m, outs, tip, n = bisector_approach(corner, 14.0)
    feature = "corner" if corner else "edge"
    for o in outs:
        if o.state == APPROACHING:
            assert o.feature == feature  # latched: never an edge or a face deeper in
    # Eq. 3: n = floor(travel / d), travel measured along the direction toward the surface.
    assert m.frame == math.floor(14.0 / D_MM)


def test_corner_trial_at_3mm_shows_the_corner_pattern() -> None:
    m, outs, _, _ = bisector_approach(True, 3.0)
    ps = m.patterns
    assert outs[-1].state == APPROACHING and outs[-1].feature == "corner"
    assert m.frame == 1
    assert outs[-1].pattern == ps.frames("corner")[1]
    shown = [pat for o in outs for _, pat in o.frames if o.state == APPROACHING]
    assert shown[0] == ps.frames("corner")[0] != ps.frames("face")[0]


def test_first_frames_tell_the_features_apart() -> None:
    ps = PatternSet(PAD)
    firsts = [ps.frames("face")[0], ps.frames("corner")[0]] + [
        ps.frames("edge", o)[0] for o in EDGE_ORIENTATIONS
    ]
    assert len(set(firsts)) == len(firsts)
    # Face: a ring about the centre; edge: its whole line; corner: centre plus its falloff.
    assert ps.frames("edge", "v")[0] == ps.static("edge", "v")
    assert ps.frames("corner")[0] == ps.static("corner")
    assert sum(ps.frames("face")[0]) < sum(ps.frames("corner")[0])


def test_edge_orientation_is_latched_through_a_turning_approach() -> None:
    _, still, _, _ = bisector_approach(False, 12.0)
    _, turned, _, _ = bisector_approach(False, 12.0, yaw_turn_deg=80.0)
    first = next(o.orientation for o in turned if o.state == APPROACHING)
    assert first == next(o.orientation for o in still if o.state == APPROACHING)
    assert {o.orientation for o in turned if o.state == APPROACHING} == {first}


# --- finding 4: slow approaches expand, Interacting comes when the finger stops -----------------------------


@pytest.mark.parametrize("speed", [1.0, 2.0, 4.0, 7.0])
def test_slow_approach_reaches_frame_15_at_30mm(speed: float) -> None:
    m = PatternManager()
    scene = FakeFloor()
    poses = line_poses(0.0, (0, 0, 0.5), (0, 0, -30.0), speed, 72.0)
    outs = run(m, scene, poses)
    assert all(o.state == APPROACHING for o in outs if o.t_s > 1.0)
    assert m.frame == 15
    # Then the finger stops: Interacting within a second, the frame stays.
    rest = hold_poses(poses[-1][0], (0, 0, -30.0), 1.0, 72.0)
    outs = run(m, scene, rest)
    assert outs[-1].state == INTERACTING
    t_int = next(o.t_s for o in outs if o.state == INTERACTING) - poses[-1][0]
    assert t_int < 0.6


# --- finding 6: slow slides get their texture ---------------------------------------------------------------


@pytest.mark.parametrize(
    ("speed", "k", "hz"), [(5.0, 1, 2.5), (5.0, 2, 1.25), (2.0, 1, 1.0), (20.0, 1, 10.0)]
)
def test_slide_shift_rate_is_v_over_d_k_down_to_2mm_s(speed: float, k: int, hz: float) -> None:
    m, outs, t0 = sliding_stroke(k, speed, 6.0)
    changes = [tf for o in outs if o.context == "sliding" for tf, _ in o.frames]
    window = [tf for tf in changes if t0 + 2.0 <= tf < t0 + 6.0]
    # Eq. 5: s = v / (d k) shifts per second.
    assert len(window) == pytest.approx(4.0 * hz, abs=1.5)


# --- finding 7: contact onset is stability-filtered ---------------------------------------------------------


def hover_fraction(
    height_mm: float, noise_mm: float, seconds: float = 60.0, rate: float = 72.0, seed: int = 1
) -> float:
    rng = np.random.default_rng(seed)
    m = PatternManager()
    scene = FakeFloor()
    on = 0
    n = int(seconds * rate)
    for i in range(n):
        p = np.array([0.0, 0.0, height_mm]) + rng.normal(0.0, noise_mm, 3)
        o = m.update(i / rate, p, PAD_DOWN, scene.query(p))
        on += any(o.pattern)
    return on / n


def test_hovering_with_tracking_noise_is_rarely_stimulated() -> None:
    # Gaussian noise per axis, independent per sample (the worst case for a one-sample trigger).
    assert hover_fraction(2.0, 1.0) < 0.01
    assert hover_fraction(1.0, 0.5) < 0.02


@pytest.mark.parametrize("rate", [30.0, 72.0, 90.0, 120.0, 1000.0])
def test_a_real_press_starts_within_one_72hz_frame(rate: float) -> None:
    m = PatternManager()
    scene = FakeFloor()
    outs = run(m, scene, line_poses(0.0, (0, 0, 1.0), (0, 0, -3.0), 20.0, rate))
    t_touch = next(o.t_s for o in outs if o.t_s * 20.0 >= 1.0)  # first sample on or in the surface
    t_on = next(o.t_s for o in outs if o.state == APPROACHING)
    assert t_on - t_touch <= max(1.0 / 72.0, 1.0 / rate) + 1e-9


# --- finding 8: θ on a bin boundary -------------------------------------------------------------------------


def test_theta_of_30_degrees_from_a_pose_is_steep_right() -> None:
    m = PatternManager()
    scene = FakeFloor()
    q = pad_down(roll_deg=30.0)
    poses = line_poses(0.0, (0, 0, 2.0), (0, 0, -1.0), 20.0, 72.0, q) + hold_poses(
        0.15, (0, 0, -1.0), 1.0, 72.0, q
    )
    outs = run(m, scene, poses)
    assert outs[-1].state == INTERACTING and outs[-1].context == "contact"
    assert m.theta_deg == pytest.approx(30.0, abs=1e-9)
    assert outs[-1].pattern == m.patterns.contact("face", None, 3)
    assert (
        theta_level(30.0 - THETA_TOLERANCE_DEG / 2) == 3 and theta_level(-30.0 - THETA_TOLERANCE_DEG / 2) == 1
    )
    assert theta_level(29.999) == 2 and theta_level(-30.001) == 0


# --- finding 11: lost tracking ------------------------------------------------------------------------------


class RecordingDevice:
    """The calls a renderer makes on a device, in order."""

    def __init__(self) -> None:
        self.mapping = PAD.channel_mapping()
        self.closed = False
        self.current_ua = 0
        self.calls: list[tuple[str, Any]] = []

    def configure(self, cfg: Any) -> None:
        self.calls.append(("configure", None))

    def send_pattern(self, pattern: Any) -> None:
        self.calls.append(("send", tuple(pattern)))

    def keepalive(self) -> None:
        self.calls.append(("keepalive", None))

    def all_off(self) -> None:
        self.calls.append(("all_off", None))

    def set_current(self, ua: int) -> None:
        self.current_ua = ua


def pressed_renderer() -> tuple[Renderer, RecordingDevice, float]:
    dev = RecordingDevice()
    r = Renderer(FakeFloor(), dev)  # type: ignore[arg-type]
    poses = line_poses(0.0, (0, 0, 2.0), (0, 0, -3.0), 20.0, 72.0) + hold_poses(0.25, (0, 0, -3.0), 0.5, 72.0)
    for pose in poses:
        r.step(pose)
    assert any(c[0] == "send" and any(c[1]) for c in dev.calls)
    return r, dev, poses[-1][0]


@pytest.mark.parametrize("bad", ["nan-position", "nan-time", "clock-back"])
def test_lost_tracking_never_feeds_the_watchdog_and_goes_idle(bad: str) -> None:
    r, dev, t_end = pressed_renderer()
    mark = len(dev.calls)
    dt = 1.0 / 72.0
    n = int(LOST_TRACKING_S / dt) + 3
    for i in range(1, n + 1):
        t = t_end + i * dt
        if bad == "nan-position":
            pose = (t, np.array([math.nan, 0.0, -3.0]), PAD_DOWN)
        elif bad == "nan-time":
            pose = (math.nan, np.array([0.0, 0.0, -3.0]), PAD_DOWN)
        else:
            pose = (t - 50.0, np.array([0.0, 0.0, -3.0]), PAD_DOWN)
        recs = r.step(pose)
        after = dev.calls[mark:]
        off_sent = ("send", (0,) * 32) in after
        if not off_sent:
            assert ("keepalive", None) not in after  # a dropped sample is not a frame
        elapsed = i * dt
        # A clock that stepped back 50 s: its first sample is dropped, the next (later than it, earlier
        # than the last one rendered) shows the step, and tracking is lost at once.
        if elapsed < LOST_TRACKING_S - 1e-9 and (bad != "clock-back" or i < 2):
            assert not off_sent and all(not rec.sent for rec in recs)
        if bad == "clock-back" and i == 2:
            assert off_sent and recs[0].dropped == "lost-tracking"
        if off_sent and r.lost_tracking_events == 1 and recs[-1].dropped == "lost-tracking":
            assert recs[-1].state == IDLE and all(rr.state == IDLE for rr in r.renderers.values())
            assert elapsed <= LOST_TRACKING_S + dt
    assert ("send", (0,) * 32) in dev.calls[mark:]
    assert r.lost_tracking_events == 1
    if bad == "clock-back":
        # The new clock, once it has run forward for the resume run, is a fresh start: a new press is
        # rendered again.
        t = t_end + (n + 1) * dt - 50.0
        for tt, p, q in line_poses(t, (0, 0, 2.0), (0, 0, -3.0), 20.0, 72.0):
            r.step((tt, p, q))
        assert r.renderers["tactdeform"].state == APPROACHING


def test_valid_samples_still_feed_the_watchdog() -> None:
    r, dev, t_end = pressed_renderer()
    mark = len(dev.calls)
    r.step((t_end + 1 / 72, np.array([0.0, 0.0, -3.0]), PAD_DOWN))
    assert dev.calls[mark:] == [("keepalive", None)]


# --- extremes -----------------------------------------------------------------------------------------------


def test_ten_metres_per_second_at_1000hz_and_at_rest() -> None:
    m = PatternManager()
    scene = FakeFloor()
    outs = run(m, scene, line_poses(0.0, (0, 0, 50.0), (0, 0, -200.0), 10000.0, 1000.0))
    assert m.frame == 100 and outs[-1].state == APPROACHING
    outs = run(m, scene, hold_poses(outs[-1].t_s, (0, 0, -200.0), 1.0, 1000.0))
    assert outs[-1].state == INTERACTING and m.frame == 100
    assert not any(math.isnan(v) for v in (m.approach.travel_mm, m.slide.travel_mm))


def test_directions_are_the_eight_bins() -> None:
    assert len(DIRECTIONS) == 8


# --- finding 9: tips of meshes are corners ------------------------------------------------------------------


@pytest.fixture(scope="module")
def teapot() -> Any:
    pytest.importorskip("scipy", reason="the teapot's mesh index needs scipy (extra 'mesh')")
    from tactdeform_hw.render.scene import load_scene

    scene = load_scene("teapot")
    scene.prepare()
    return scene


def test_teapot_spout_tip_is_a_corner_and_its_rim_an_edge(teapot: Any) -> None:
    obj = teapot.objects[0]
    v = obj.index.vertices + obj.index.origin
    tip = v[np.argmax(v[:, 0])]  # the spout's end is the pot's furthest point along +x
    assert teapot.query(tip + np.array([3.0, 0.0, 0.0])).feature == "corner"
    # The body's rim is a long, gently curving crease: an edge, never a corner.
    lo, hi = obj.bounds_mm
    rim = [
        q
        for q in (teapot.query(p) for p in obj.features.seg_a + obj.index.origin)
        if q.closest_point_mm[1] > hi[1] - 30.0
    ]
    assert rim and any(q.feature == "edge" for q in rim)


# --- finding 10: CAM through the mesh index -----------------------------------------------------------------


def cam_poses(scene: Any, n: int = 40, seed: int = 0) -> list[tuple[np.ndarray, tuple[float, ...]]]:
    rng = np.random.default_rng(seed)
    lo, hi = scene.bounds_mm
    out = []
    for _ in range(n):
        q = scene.query(rng.uniform(lo - 10.0, hi + 10.0))
        nrm = np.asarray(q.normal)
        r = frame_from_z_y(-nrm + rng.normal(0, 0.3, 3), rng.normal(0, 1, 3))
        out.append((np.asarray(q.closest_point_mm) - nrm * rng.uniform(-2.0, 4.0), tuple(matrix_to_quat(r))))
    return out


def bunny_scene() -> Any:
    pytest.importorskip("scipy", reason="the bunny's mesh index needs scipy (extra 'mesh')")
    from tactdeform_hw.errors import ConfigurationError
    from tactdeform_hw.render.scene import load_scene

    try:
        scene = load_scene("bunny")
    except ConfigurationError as exc:
        pytest.skip(f"../shared/meshes/stanford_bunny.obj is not available: {exc}")
    scene.prepare()
    return scene


@pytest.mark.parametrize("name", ["teapot", "bunny"])
def test_cam_plane_test_agrees_with_the_per_electrode_test(name: str, teapot: Any) -> None:
    from tactdeform_hw.render.baselines import ContactAreaMapping
    from tactdeform_hw.render.manager import quat_axes

    scene = teapot if name == "teapot" else bunny_scene()
    cam = ContactAreaMapping()
    some_in = some_mixed = 0
    for p, q in cam_poses(scene):
        X, Y, _ = quat_axes(*q)
        fast = scene.contains_on_pad(PadPlane.of(p, X, Y, cam._offsets), scene.query(p))
        slow = scene.contains(cam.electrode_positions(tuple(p), q))
        assert fast.tolist() == slow.tolist()
        some_in += bool(fast.any())
        some_mixed += bool(fast.any() and not fast.all())
    assert some_in and some_mixed  # the poses do cut the surface under the pad
