"""Base patterns (face ring, four edges, corner falloff), contact shifts and texture masks, and the
equations of the three contexts."""

from __future__ import annotations

import math

import numpy as np
import pytest

from tactdeform_hw.errors import LimitError
from tactdeform_hw.render.array import ElectrodeArray
from tactdeform_hw.render.contexts import (
    ApproachState,
    Debounced,
    FrameAccumulator,
    contact_angle_deg,
    counts_to_show,
    displayed_frame,
    expansion_rate,
    frame_index,
    frame_interval_s,
    mask_phase,
    quantise_angle,
    shift_count,
    shift_interval_s,
    shift_rate,
    theta_level,
)
from tactdeform_hw.render.patterns import (
    DIRECTIONS,
    EDGE_ORIENTATIONS,
    PatternParams,
    PatternSet,
    active,
    render_ascii,
)


@pytest.fixture(scope="module")
def pad() -> ElectrodeArray:
    return ElectrodeArray.tactdeform()


@pytest.fixture(scope="module")
def ps(pad: ElectrodeArray) -> PatternSet:
    return PatternSet(pad)


def on(pattern: tuple[int, ...]) -> np.ndarray:
    return np.array([v != 0 for v in pattern])


def radius(pad: ElectrodeArray) -> np.ndarray:
    rel = pad.positions_mm - pad.centre_mm
    return np.hypot(rel[:, 0], rel[:, 1])


# --- face ---------------------------------------------------------------------------------------------


def test_face_is_a_ring_diverging_one_spacing_per_frame(pad: ElectrodeArray, ps: PatternSet) -> None:
    frames = ps.frames("face")
    assert [active(f) for f in frames] == [4, 12, 16]
    r = radius(pad)
    masks = [on(f) for f in frames]
    # Rings are disjoint and together cover the pad.
    assert sum(m.astype(int) for m in masks).tolist() == [1] * 32
    # Each ring lies further out than the previous one: its nearest electrode is at least one spacing
    # (less the diagonal slack of a square grid) beyond the previous ring's nearest.
    for a, b in zip(masks, masks[1:]):
        assert r[b].min() > r[a].max() - 1e-9 or r[b].min() - r[a].min() >= pad.pitch_mm * 0.85
        assert r[b].mean() - r[a].mean() == pytest.approx(pad.pitch_mm, rel=0.25)
    # Every face frame is symmetric about both axes (centred on the pad).
    pos = pad.positions_mm
    for m in masks:
        pts = {tuple(p) for p in pos[m]}
        assert pts == {(-x, y) for x, y in pts} == {(x, -y) for x, y in pts}
    assert ps.static("face") == ps.all_on


# --- edges ----------------------------------------------------------------------------------------------


@pytest.mark.parametrize("orientation", EDGE_ORIENTATIONS)
def test_edge_is_a_line_through_the_centre_in_its_orientation(
    pad: ElectrodeArray, ps: PatternSet, orientation: str
) -> None:
    angle = {"h": 0.0, "d1": 45.0, "v": 90.0, "d2": 135.0}[orientation]
    static = on(ps.static("edge", orientation))
    rel = pad.positions_mm - pad.centre_mm
    a = math.radians(angle)
    along = rel @ np.array([math.cos(a), math.sin(a)])
    across = rel @ np.array([-math.sin(a), math.cos(a)])
    assert np.all(np.abs(across[static]) <= pad.pitch_mm / math.sqrt(2) + 1e-9)
    # A line: it spans the array along its direction and is narrow across it.
    assert np.ptp(along[static]) >= 4 * pad.pitch_mm
    assert np.ptp(across[static]) <= 2 * pad.pitch_mm
    # It passes through the centre: symmetric under a half turn.
    pts = {tuple(p) for p in rel[static]}
    assert pts == {(-x, -y) for x, y in pts}
    frames = [on(f) for f in ps.frames("edge", orientation)]
    # Frame 0 is the whole line (recognisable at once); later frames are the lines one spacing further
    # out on both sides, diverging across the pad like the face's ring: disjoint, covering the pad.
    assert np.array_equal(frames[0], static) and len(frames) >= 3
    assert sum(f.astype(int) for f in frames).tolist() == [1] * 32
    for a_, b_ in zip(frames, frames[1:]):
        assert np.abs(across[b_]).mean() - np.abs(across[a_]).mean() == pytest.approx(pad.pitch_mm, rel=0.3)
        assert {tuple(p) for p in rel[b_]} == {(-x, -y) for x, y in rel[b_]}


def test_the_four_edge_orientations_are_distinct(ps: PatternSet) -> None:
    statics = {o: ps.static("edge", o) for o in EDGE_ORIENTATIONS}
    assert len(set(statics.values())) == 4
    assert [active(statics[o]) for o in EDGE_ORIENTATIONS] == [12, 14, 12, 14]


# --- corner ----------------------------------------------------------------------------------------------


def test_corner_is_concentrated_with_a_parametric_falloff(pad: ElectrodeArray, ps: PatternSet) -> None:
    frames = ps.frames("corner")
    static = on(ps.static("corner"))
    r = radius(pad)
    assert r[static].max() < r[~static].min() + 1e-9  # a disc about the centre, nothing beyond it
    # Frame 0 is the concentrated disc itself (falloff one spacing: centre 2 x 2 and its 8 neighbours),
    # not the face's or the edge's first frame; each later frame reaches one spacing further.
    assert np.array_equal(on(frames[0]), static) and active(frames[0]) == 12
    assert frames[0] not in (ps.frames("face")[0], *(ps.frames("edge", o)[0] for o in EDGE_ORIENTATIONS))
    rho = r - r.min()
    for m, f in enumerate(frames):
        assert on(f).tolist() == (rho <= pad.pitch_mm * (1 + m) + 1e-9).tolist()
    assert active(frames[-1]) == 32
    sizes = []
    for falloff in (0.0, 1.0, 2.0, 3.0, 4.5):
        p = PatternSet(pad, PatternParams(corner_falloff_mm=falloff))
        sizes.append(active(p.static("corner")))
    assert sizes == sorted(sizes) and sizes[0] == 4 and sizes[-1] > 12
    assert active(PatternSet(pad, PatternParams(corner_falloff_mm=0.0)).static("corner")) == 4


# --- contact (eq. 4) ---------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "feature,orientation", [("face", None), ("corner", None), ("edge", "v"), ("edge", "h")]
)
def test_contact_levels_shift_left_to_right_only(
    pad: ElectrodeArray, ps: PatternSet, feature: str, orientation: str | None
) -> None:
    pos = pad.positions_mm
    centroids = []
    for level, c in enumerate((-4.0, -2.0, 2.0, 4.0)):
        m = on(ps.contact(feature, orientation, level))
        assert m.any()
        centroids.append(pos[m, 0].mean())
        # Eq. 4 on the whole base pattern: P(x, y) = P_base(x - c, y).
        base = on(ps.static(feature, orientation))
        want = [bool(base[j]) if (j := pad.index_at(x - c, y)) >= 0 else False for x, y in pos]
        assert m.tolist() == want
    assert centroids == sorted(centroids)
    assert ps.contact_centres_mm == (-4.0, -2.0, 2.0, 4.0)


def test_contact_levels_land_in_the_leftmost_to_rightmost_regions(
    pad: ElectrodeArray, ps: PatternSet
) -> None:
    # The vertical line (two columns) lands on the leftmost, left-centre, right-centre, rightmost columns.
    cols = [set(pad.positions_mm[on(ps.contact("edge", "v", level)), 0]) for level in range(4)]
    assert cols == [{-5.0, -3.0}, {-3.0, -1.0}, {1.0, 3.0}, {3.0, 5.0}]
    col = pad.regions % 3
    assert set(col[on(ps.contact("edge", "v", 0))]) == {0}
    assert set(col[on(ps.contact("edge", "v", 3))]) == {2}


# --- texture masks (eq. 5–7) --------------------------------------------------------------------------------


def test_mask_k0_is_ones_and_never_divides(ps: PatternSet) -> None:
    assert ps.mask(0, 0, 0).all()
    for phase in range(5):
        assert ps.sliding("face", None, 0, 0, phase) == ps.static("face")


@pytest.mark.parametrize("k", [1, 2])
def test_mask_has_period_3k_and_moves_k_spacings_per_count(
    pad: ElectrodeArray, ps: PatternSet, k: int
) -> None:
    x = pad.positions_mm[:, 0]
    m0 = ps.mask(DIRECTIONS.index("E"), k, 0)
    # Stripes across the motion (constant along y), k columns on, 2k off.
    cols = sorted(set(x))
    by_col = [bool(m0[x == c][0]) for c in cols]
    for c in cols:
        assert len(set(m0[x == c])) == 1
    assert by_col == [((i // k) % 3) == 0 for i in range(6)]
    # One count moves the mask k spacings against the (rightward) finger: column i shows what column
    # i + k showed.  Three counts come back; the states in between are not complements of each other.
    m1 = ps.mask(DIRECTIONS.index("E"), k, mask_phase(1, k))
    m1_cols = [bool(m1[x == c][0]) for c in cols]
    assert m1_cols == [((i // k + 1) % 3) == 0 for i in range(6)]
    assert not np.array_equal(m1, ~m0)
    assert np.array_equal(ps.mask(0, k, mask_phase(3, k)), m0)
    assert ps.mask_period(k) == 3 * k


def test_mask_moves_opposite_to_the_finger_for_a_one_spacing_step(
    pad: ElectrodeArray, ps: PatternSet
) -> None:
    # With a step of one spacing (k = 2), a rightward (E) finger sees the stripes move left.
    x = pad.positions_mm[:, 0]
    row = pad.positions_mm[:, 1] == 1.0
    m0 = ps.mask(0, 2, mask_phase(0, 2, step_spacings=1))
    m1 = ps.mask(0, 2, mask_phase(1, 2, step_spacings=1))
    order = np.argsort(x[row])
    a = m0[row][order].tolist()
    b = m1[row][order].tolist()
    assert b == a[1:] + [b[-1]]  # every stripe one column to the left
    back = ps.mask(0, 2, mask_phase(1, 2, step_spacings=1, beta=-1.0))[row][order].tolist()
    assert back[1:] == a[:-1]  # β = -1: with the finger


def test_diagonal_and_vertical_masks_run_across_their_direction(pad: ElectrodeArray, ps: PatternSet) -> None:
    pos = pad.positions_mm
    n = ps.mask(DIRECTIONS.index("N"), 1, 0)
    for y in set(pos[:, 1]):
        assert len(set(n[pos[:, 1] == y])) == 1  # stripes are rows
    ne = ps.mask(DIRECTIONS.index("NE"), 1, 0)
    s = pos[:, 0] + pos[:, 1]
    for v in set(s):
        assert len(set(ne[s == v])) == 1  # stripes are anti-diagonals


def test_sliding_pattern_is_base_times_mask(ps: PatternSet) -> None:
    for o in EDGE_ORIENTATIONS:
        for d in range(8):
            pat = on(ps.sliding("edge", o, d, 1, 0))
            assert np.array_equal(pat, on(ps.static("edge", o)) & ps.mask(d, 1, 0))


# --- equations ----------------------------------------------------------------------------------------------


def test_equations_1_to_3() -> None:
    assert expansion_rate(20.0) == pytest.approx(10.0)  # 20 mm/s / 2 mm
    assert frame_interval_s(20.0) == pytest.approx(0.1)
    assert frame_interval_s(0.0) == math.inf and frame_interval_s(-5.0) == math.inf
    assert [frame_index(t) for t in (0.0, 1.99, 2.0, 5.9, 6.0)] == [0, 0, 1, 2, 3]
    assert frame_index(3.0, alpha=2.0) == 3
    assert frame_index(-0.1) == -1


def test_equations_5_to_7_rough_10hz_rougher_5hz_smooth_never() -> None:
    assert shift_rate(20.0, 1) == pytest.approx(10.0)
    assert shift_rate(20.0, 2) == pytest.approx(5.0)
    assert shift_rate(20.0, 1, beta=-1.0) == pytest.approx(-10.0)
    assert shift_interval_s(20.0, 1) == pytest.approx(0.1)
    assert shift_interval_s(20.0, 2) == pytest.approx(0.2)
    for v in (0.0, 20.0, 1e9, math.inf):
        assert shift_rate(v, 0) == 0.0
        assert shift_interval_s(v, 0) == math.inf
        assert shift_count(v, 0) == 0
    assert shift_interval_s(0.0, 1) == math.inf
    assert [shift_count(s, 1) for s in (0.0, 1.9, 2.0, 4.0)] == [0, 0, 1, 2]
    assert [shift_count(s, 2) for s in (3.9, 4.0, 8.0)] == [0, 1, 2]


def test_frame_accumulator_carries_whole_frames() -> None:
    acc = FrameAccumulator(2.0)
    for _ in range(7):
        acc.add(0.5)
    assert acc.whole == 1 and acc.rem == pytest.approx(1.5)
    acc.add(-3.6)
    assert acc.whole == -1 and acc.travel_mm == pytest.approx(-0.1)
    clamped = FrameAccumulator(2.0, clamp_at_zero=True)
    clamped.add(-5.0)
    assert clamped.whole == 0 and clamped.travel_mm == 0.0
    clamped.add(1e6)
    assert clamped.whole == 500000
    with pytest.raises(LimitError):
        FrameAccumulator(0.0)


def test_approach_state_steps_down_only_past_the_release_band() -> None:
    st = ApproachState(2.0, release_mm=1.25)
    assert st.begin(4.1) == 2
    assert st.advance(-0.5) == 2  # travel 3.6: below frame 2's start but within the band
    assert st.advance(-0.4) == 2  # travel 3.2: still within 1.25 mm of frame 2's start
    assert st.advance(-0.5) == 1  # travel 2.7 < 4 - 1.25 → down
    assert st.advance(+1.5) == 2  # travel 4.2: up at once
    fwd = ApproachState(2.0, mode="forward")
    fwd.begin(0.0)
    fwd.advance(3.0)
    assert fwd.advance(-2.0) == 1 and fwd.travel_mm == pytest.approx(3.0)


def test_displayed_frame_and_interpolated_counts() -> None:
    assert [displayed_frame(n, 3, "cycle") for n in range(7)] == [0, 1, 2, 0, 1, 2, 0]
    assert [displayed_frame(n, 3, "hold") for n in range(7)] == [0, 1, 2, 2, 2, 2, 2]
    assert counts_to_show(2, 3, 3) == [3]
    assert counts_to_show(2, 6, 3) == [3, 4, 5, 6]
    assert counts_to_show(2, 8, 3) == [6, 7, 8]
    assert counts_to_show(6, 2, 3) == [5, 4, 3, 2]
    assert counts_to_show(None, 1, 3) == [0, 1]
    assert counts_to_show(-1, 40, 3) == [36, 37, 38, 39, 40]  # continues from -1: 0 (mod 3) first
    assert counts_to_show(4, 4, 3) == [4]


def test_theta_bins_and_hysteresis() -> None:
    assert [theta_level(t) for t in (-90, -31, -30, -1, 0, 29.9, 30, 90)] == [0, 0, 1, 1, 2, 2, 3, 3]
    assert theta_level(32.0, current=2, margin_deg=5.0) == 2  # within the margin: kept
    assert theta_level(36.0, current=2, margin_deg=5.0) == 3
    assert theta_level(-3.0, current=2, margin_deg=5.0) == 2
    assert theta_level(-6.0, current=2, margin_deg=5.0) == 1


def test_angle_quantiser_with_hysteresis() -> None:
    assert [quantise_angle(a, 8, 360.0) for a in (0, 22, 23, 90, 180, -45, 359)] == [0, 0, 1, 2, 4, 7, 0]
    assert quantise_angle(30.0, 8, 360.0, current=0, margin_deg=10.0) == 0
    assert quantise_angle(33.0, 8, 360.0, current=0, margin_deg=10.0) == 1
    assert quantise_angle(-30.0, 8, 360.0, current=0, margin_deg=10.0) == 0
    assert [quantise_angle(a, 4, 180.0) for a in (0, 44, 46, 90, 135, 170, -10)] == [0, 1, 1, 2, 3, 0, 0]


def test_debounce_needs_the_value_to_hold_for_the_window() -> None:
    d = Debounced(0.1, "face")
    assert not d.update("edge", 0.00)
    assert not d.update("edge", 0.05)
    assert not d.update("face", 0.08)  # back: the window restarts
    assert not d.update("edge", 0.10)
    assert d.update("edge", 0.20) and d.value == "edge"


def test_contact_angle_is_the_pad_roll_against_the_surface() -> None:
    n = (0.0, 1.0, 0.0)  # a table top, world y up
    for roll in (-75.0, -40.0, -10.0, 0.0, 10.0, 40.0, 75.0):
        r = math.radians(roll)
        # Pad facing down; its right is +x; rolling turns the right side down (toward the surface).
        X = (math.cos(r), -math.sin(r), 0.0)
        Z = (math.sin(r), -math.cos(r), 0.0)
        assert contact_angle_deg(n, X, Z) == pytest.approx(roll)
    # The back of the finger on the surface: clipped to the side.
    assert contact_angle_deg(n, (1.0, 0.0, 0.0), (0.0, 1.0, 0.0)) in (-90.0, 90.0, 0.0)
    # The horizontal-plane variant falls back on a horizontal surface, and agrees on a wall.
    wall = (1.0, 0.0, 0.0)
    X = (0.0, 0.0, 1.0)
    Z = (-math.cos(0.3), math.sin(0.3), 0.0)
    assert contact_angle_deg(wall, X, Z, plane="horizontal") == pytest.approx(0.0, abs=1e-9)
    assert contact_angle_deg(n, (1.0, 0.0, 0.0), (0.0, -1.0, 0.0), plane="horizontal") == pytest.approx(0.0)


# --- other arrays -------------------------------------------------------------------------------------------


def test_patterns_build_on_other_layouts() -> None:
    big_pad = ElectrodeArray.grid(8, 8, pitch_mm=2.0, radius_mm=0.7)
    big = PatternSet(big_pad)
    rings = [on(f) for f in big.frames("face")]
    assert sum(m.astype(int) for m in rings).tolist() == [1] * 64  # round rings tile the pad
    r = radius(big_pad)
    means = [r[m].mean() for m in rings]
    assert all(b - a == pytest.approx(2.0, rel=0.35) for a, b in zip(means, means[1:]))
    assert all(active(big.contact("face", None, lv)) > 0 for lv in range(4))
    odd = PatternSet(ElectrodeArray.grid(5, 5, pitch_mm=2.0, radius_mm=0.7))
    assert active(odd.frames("face")[0]) == 1  # an odd grid has a centre electrode
    board = ElectrodeArray(
        np.array([(-5, 15), (5, 15), (-10, 5), (0, 5), (10, 5), (-10, -5), (0, -5), (10, -5)], float), 1.0
    )
    bs = PatternSet(board)
    assert sum(active(f) for f in bs.frames("face")) == 8
    for o in EDGE_ORIENTATIONS:
        assert active(bs.static("edge", o)) >= 1


def test_params_are_checked() -> None:
    with pytest.raises(LimitError, match="on_level"):
        PatternParams(on_level=3)
    with pytest.raises(LimitError, match="mask_period_factor"):
        PatternParams(mask_period_factor=1)
    with pytest.raises(LimitError, match="corner_falloff_mm"):
        PatternParams(corner_falloff_mm=-1.0)
    with pytest.raises(LimitError, match="feature"):
        PatternSet(ElectrodeArray.tactdeform()).frames("vertex")
    with pytest.raises(LimitError, match="orientation"):
        PatternSet(ElectrodeArray.tactdeform()).static("edge", "x")


def test_biphasic_level_and_ascii_picture(pad: ElectrodeArray) -> None:
    p = PatternSet(pad, PatternParams(on_level=2))
    assert set(p.frames("face")[0]) == {0, 2}
    pic = render_ascii(pad, p.frames("face")[0])
    assert pic.splitlines()[2] == "..##.."
