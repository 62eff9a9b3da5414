"""The three interaction contexts as equations and small state holders: approaching (eq. 1–3), contact
(eq. 4) and sliding (eq. 5–7).

Travel is accumulated from successive positions — the displacement between two tracking samples,
projected on the surface normal (approach) or on the sliding direction — never from a velocity that was
differentiated and integrated again: the sum of displacements telescopes to the net displacement, so
timestamp jitter, dropped samples and Δt = 0 cannot add error (``tools/frame_error.py`` measures the
difference).  Travel is held as whole frames plus a compensated remainder so an eight-hour session does
not lose the sub-millimetre part to floating-point rounding.

Everything here is pure Python on floats: these functions run once per tracking sample and a numpy
call on a 3-vector costs more than the arithmetic itself.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any, Literal

from ..errors import LimitError

# --- defaults from the paper -----------------------------------------------------------------------------
ALPHA = 1.0  # eq. 1 expansion gain
D_ELECTRODE_MM = 2.0  # eq. 1–3, 5–7 electrode spacing
BETA = 1.0  # eq. 5: +1, the pattern shifts opposite to the finger
THETA_EDGES_DEG = (-30.0, 0.0, 30.0)  # eq. 4 level boundaries
TEXTURE_NAMES: tuple[str, ...] = ("smooth", "rough", "rougher")  # k_texture 0, 1, 2


# --- eq. 1–3 and 5–7 ---------------------------------------------------------------------------------------


def expansion_rate(
    v_approach_mm_s: float, alpha: float = ALPHA, d_electrode_mm: float = D_ELECTRODE_MM
) -> float:
    """Eq. 1: r = α · v / d, in electrode spacings per second (negative while the finger withdraws)."""
    return alpha * v_approach_mm_s / d_electrode_mm


def frame_interval_s(
    v_approach_mm_s: float, d_electrode_mm: float = D_ELECTRODE_MM, alpha: float = ALPHA
) -> float:
    """Eq. 2: Δt = d / (α v); ``inf`` when the finger is not moving toward the surface."""
    v = alpha * v_approach_mm_s
    if not v > 0.0:
        return math.inf
    return d_electrode_mm / v


def frame_index(travel_mm: float, alpha: float = ALPHA, d_electrode_mm: float = D_ELECTRODE_MM) -> int:
    """Eq. 3: n = ⌊α · travel / d⌋ with travel = ∫ v_approach dt (one frame per 2 mm at α = 1)."""
    return math.floor(alpha * travel_mm / d_electrode_mm)


def shift_rate(
    v_slide_mm_s: float, k_texture: int, d_electrode_mm: float = D_ELECTRODE_MM, beta: float = BETA
) -> float:
    """Eq. 5: s = β · v / (d · k) shifts per second; 0 for a smooth surface (k = 0: no shift at any speed)."""
    if k_texture == 0:
        return 0.0
    return beta * v_slide_mm_s / (d_electrode_mm * k_texture)


def shift_interval_s(v_slide_mm_s: float, k_texture: int, d_electrode_mm: float = D_ELECTRODE_MM) -> float:
    """Eq. 6: Δt_shift = d · k / v (20 mm/s: rough 0.1 s, rougher 0.2 s); ``inf`` when k = 0 or at rest."""
    if k_texture == 0 or not v_slide_mm_s > 0.0:
        return math.inf
    return d_electrode_mm * k_texture / v_slide_mm_s


def shift_count(slide_travel_mm: float, k_texture: int, d_electrode_mm: float = D_ELECTRODE_MM) -> int:
    """Eq. 7 interpretation: n_s = ⌊∫ v_slide / (d · k) dτ⌋ = ⌊travel / (d · k)⌋; 0 when k = 0."""
    if k_texture == 0:
        return 0
    return math.floor(slide_travel_mm / (d_electrode_mm * k_texture))


def mask_phase(
    count: int, k_texture: int, period_factor: int = 3, step_spacings: int | None = None, beta: float = BETA
) -> int:
    """Where the texture mask stands after ``count`` shifts, in spacings modulo its period.

    The spec's interpretation: the mask (period ``period_factor · k``) moves ``k`` spacings per count,
    opposite to the finger for β = +1 — a mask read at coordinate ``q + phase`` along the motion, so
    features move toward −q.  The period must exceed twice the step: at exactly 2k a shift of k inverts
    the stripes, consecutive counts alternate between two complementary masks and the motion has no
    direction (β = +1 and β = −1 give the same sequence).
    """
    if k_texture == 0:
        return 0
    period = period_factor * k_texture
    step = k_texture if step_spacings is None else step_spacings
    sign = 1 if beta >= 0 else -1
    return (sign * step * count) % period


# --- accumulation without drift -----------------------------------------------------------------------------


#: Travel within this of a frame (or shift) boundary counts as on it: far below any tracker's
#: resolution, far above the rounding of summed float displacements (~1e-14 mm).
BOUNDARY_TOLERANCE_MM = 1e-9


class FrameAccumulator:
    """Travel stored as a whole number of ``unit_mm`` plus a Kahan-compensated remainder in
    [-tol, unit - tol) (tol = :data:`BOUNDARY_TOLERANCE_MM`).

    A plain float sum of eight hours of 72 Hz displacements keeps every rounding error; here the float
    that is rounded never exceeds one unit, and the compensation carries what rounding dropped.  With
    ``clamp_at_zero`` the travel cannot go negative (a finger withdrawing past its onset point).
    """

    __slots__ = ("unit_mm", "whole", "rem", "_comp", "clamp_at_zero")

    def __init__(self, unit_mm: float, *, clamp_at_zero: bool = False) -> None:
        if not (math.isfinite(unit_mm) and unit_mm > 0.0):
            raise LimitError("unit_mm", unit_mm, "a finite length > 0 mm")
        self.unit_mm = float(unit_mm)
        self.clamp_at_zero = clamp_at_zero
        self.whole = 0
        self.rem = 0.0
        self._comp = 0.0

    def reset(self, travel_mm: float = 0.0) -> None:
        self.whole = 0
        self.rem = 0.0
        self._comp = 0.0
        if travel_mm:
            self.add(travel_mm)

    def add(self, delta_mm: float) -> int:
        """Add a (finite) displacement; return the whole-unit count."""
        y = delta_mm - self._comp
        t = self.rem + y
        self._comp = (t - self.rem) - y
        self.rem = t
        unit = self.unit_mm
        tol = BOUNDARY_TOLERANCE_MM
        if t >= unit - tol or t < -tol:
            # A travel within ``tol`` of a whole unit counts as having reached it: a finger that moved
            # exactly 14 mm, summed from 72 Hz steps, reads 13.999999999999996 mm and must show frame 7.
            k = math.floor((t + tol) / unit)
            self.whole += k
            self.rem = t - k * unit  # in [-tol, unit - tol): the travel itself stays exact
            if self.clamp_at_zero and self.whole < 0:
                self.whole = 0
                self.rem = 0.0
                self._comp = 0.0
        return self.whole

    @property
    def travel_mm(self) -> float:
        return self.whole * self.unit_mm + self.rem


# --- approaching (eq. 1–3) ----------------------------------------------------------------------------------

Overflow = Literal["cycle", "hold"]


class ApproachState:
    """Eq. 3's frame counter for one contact, with a release hysteresis on decreasing frames.

    ``travel`` is the finger's travel toward the surface since the contact began (the penetration at
    onset plus every later displacement projected on the normal).  ``mode``: ``"net"`` counts motion
    away from the surface negatively (the pattern contracts while the finger withdraws; the frame index
    follows the deformation) — *interpretation*; ``"forward"`` counts only motion toward the surface.
    A frame goes down only once travel is ``release_mm`` below its start, so a finger resting on a
    frame boundary with tremor does not flicker between two frames.
    """

    __slots__ = ("acc", "mode", "release_mm", "frame")

    def __init__(
        self, unit_mm: float, *, mode: Literal["net", "forward"] = "net", release_mm: float = 1.25
    ) -> None:
        if mode not in ("net", "forward"):
            raise LimitError("approach_travel", mode, "'net' or 'forward'")
        if not (math.isfinite(release_mm) and 0.0 <= release_mm < unit_mm):
            raise LimitError("frame_release_mm", release_mm, f"0 ≤ release < one frame ({unit_mm:g} mm)")
        self.acc = FrameAccumulator(unit_mm, clamp_at_zero=True)
        self.mode = mode
        self.release_mm = release_mm
        self.frame = 0

    def begin(self, penetration_mm: float) -> int:
        self.acc.reset(max(0.0, penetration_mm))
        self.frame = self.acc.whole
        return self.frame

    def advance(self, toward_mm: float) -> int:
        if self.mode == "forward" and toward_mm < 0.0:
            return self.frame
        whole = self.acc.add(toward_mm)
        if whole > self.frame:
            self.frame = whole
        elif whole < self.frame:
            # Step down to the highest frame whose start is within the release band.
            travel = self.acc.travel_mm
            held = math.floor((travel + self.release_mm) / self.acc.unit_mm)
            self.frame = min(self.frame, max(whole, held))
        return self.frame

    @property
    def travel_mm(self) -> float:
        return self.acc.travel_mm


def displayed_frame(n: int, frame_count: int, overflow: Overflow) -> int:
    """Which of a pattern's frames expansion count ``n`` shows.

    *Interpretation* (eq. 3 grows without bound, a pattern has a few frames): ``"cycle"`` restarts the
    ring at the centre, so the expansion keeps its speed-coupled rate for as long as the finger presses
    in; ``"hold"`` stops at the outermost frame."""
    if n <= 0:
        return 0
    if overflow == "cycle":
        return n % frame_count
    return min(n, frame_count - 1)


def counts_to_show(n_from: int | None, n_to: int, distinct: int) -> list[int]:
    """The counts between two updates that must each be shown once so no frame is skipped in effect.

    Returns the counts after ``n_from`` up to ``n_to`` (either direction).  When more counts passed than
    the pattern has ``distinct`` frames, only the last few are kept: at least ``distinct`` (every frame
    shown once) and as many more (below ``2·distinct``) as keep the sequence continuous — the first kept
    count follows ``n_from`` modulo ``distinct`` — so the expansion never jumps a frame between two
    updates either."""
    if n_from is None:
        lo = max(0, n_to - distinct + 1)
        return list(range(lo, n_to + 1))
    if n_to == n_from:
        return [n_to]
    step = 1 if n_to > n_from else -1
    span = abs(n_to - n_from)
    d = max(1, distinct)
    m = span if span <= d else d + span % d
    return [n_to - step * (m - 1 - i) for i in range(m)]


# --- contact (eq. 4) ----------------------------------------------------------------------------------------

ThetaPlane = Literal["finger", "horizontal"]


def contact_angle_deg(
    normal: Sequence[float],
    x_axis: Sequence[float],
    z_axis: Sequence[float],
    *,
    plane: ThetaPlane = "finger",
    up: Sequence[float] = (0.0, 1.0, 0.0),
) -> float:
    """Eq. 4's θ in degrees, in [-90, 90]; negative when the contact lies on the left of the pad.

    *Interpretation.*  The paper's θ is the angle between the ray from the finger-pad centre to the
    contact point and the surface tangent.  On a pad whose cross-section is round, the contact point
    sits where the pad's own normal is opposite to the surface normal; the ray from the pad centre to
    it turns, with the surface tangent, by the pad's roll against the surface.  So θ is the roll of the
    pad relative to the surface, read in the pad's cross-section: ``atan2(-n·x̂, -n·ẑ)`` with x̂ the
    pad's right axis and ẑ its outward normal.  0 means the pad presses flat (centre of the pad),
    ±90° means the surface touches the pad's right / left side.  World y is up (the VR engines' and
    :mod:`tactdeform_hw.render.geometry`'s convention).

    ``plane="finger"`` reads the angle in the plane across the finger (x̂, ẑ); ``"horizontal"`` first
    projects the vectors onto the world's horizontal plane (perpendicular to ``up``), as the paper
    writes it, and falls back to the finger plane when the surface is (nearly) horizontal and its
    normal has no horizontal part.
    """
    nx, ny, nz = normal
    X = x_axis
    Z = z_axis
    if plane == "horizontal":
        ux, uy, uz = up
        nu = nx * ux + ny * uy + nz * uz
        hx, hy, hz = nx - nu * ux, ny - nu * uy, nz - nu * uz
        if hx * hx + hy * hy + hz * hz > 1e-6:
            xu = X[0] * ux + X[1] * uy + X[2] * uz
            zu = Z[0] * ux + Z[1] * uy + Z[2] * uz
            Xh = (X[0] - xu * ux, X[1] - xu * uy, X[2] - xu * uz)
            Zh = (Z[0] - zu * ux, Z[1] - zu * uy, Z[2] - zu * uz)
            a = -(hx * Xh[0] + hy * Xh[1] + hz * Xh[2])
            b = -(hx * Zh[0] + hy * Zh[1] + hz * Zh[2])
            return _clip90(a, b)
    elif plane != "finger":
        raise LimitError("theta_plane", plane, "'finger' or 'horizontal'")
    a = -(nx * X[0] + ny * X[1] + nz * X[2])
    b = -(nx * Z[0] + ny * Z[1] + nz * Z[2])
    return _clip90(a, b)


def _clip90(a: float, b: float) -> float:
    """atan2 in degrees clipped to [-90, 90]: a surface behind the pad (b < 0) touches it fully on one
    side.  Same convention as :func:`tactdeform_hw.render.geometry.contact_theta_deg`, which the
    synthetic trajectories use to place the finger."""
    if a == 0.0 and b == 0.0:
        return 0.0
    th = math.degrees(math.atan2(a, b))
    return -90.0 if th < -90.0 else (90.0 if th > 90.0 else th)


#: Tolerance on eq. 4's bin boundaries: a θ within this of a boundary counts as on it, so an angle of
#: exactly 30° that reaches the renderer as 29.999999999999996° (a pose's rotation and the normal's
#: rounding) lands in the bin the paper gives 30° (steep right, [30°, 90°]).  1e-6° is far below any
#: tracker's resolution and far above double rounding of a unit vector's angle (~1e-14°).
THETA_TOLERANCE_DEG = 1e-6


def theta_level(theta_deg: float, current: int | None = None, margin_deg: float = 0.0) -> int:
    """Eq. 4's bins — steep left [-90, -30), shallow left [-30, 0), shallow right [0, 30), steep right
    [30, 90] → 0..3, each boundary taken with :data:`THETA_TOLERANCE_DEG` — with hysteresis: the current
    level is kept until θ is ``margin_deg`` past its boundary."""
    theta_deg += THETA_TOLERANCE_DEG
    e0, e1, e2 = THETA_EDGES_DEG
    if current is not None:
        lo = -math.inf if current == 0 else THETA_EDGES_DEG[current - 1]
        hi = math.inf if current == 3 else THETA_EDGES_DEG[current]
        if lo - margin_deg <= theta_deg < hi + margin_deg:
            return current
    if theta_deg < e0:
        return 0
    if theta_deg < e1:
        return 1
    if theta_deg < e2:
        return 2
    return 3


# --- angular quantisers (edge orientation, sliding direction) -----------------------------------------------


def quantise_angle(
    angle_deg: float, bins: int, period_deg: float, current: int | None = None, margin_deg: float = 0.0
) -> int:
    """Nearest of ``bins`` centres spaced evenly from 0° over ``period_deg`` (180° for an undirected
    edge, 360° for a direction), keeping ``current`` while the angle is within half a bin plus
    ``margin_deg`` of its centre."""
    width = period_deg / bins
    if current is not None:
        diff = (angle_deg - current * width + period_deg / 2.0) % period_deg - period_deg / 2.0
        if abs(diff) <= width / 2.0 + margin_deg:
            return current
    return int(math.floor((angle_deg % period_deg) / width + 0.5)) % bins


# --- time-window debouncing ---------------------------------------------------------------------------------


class Debounced:
    """A quantised parameter that changes only after its new value has held for ``window_s``.

    The window starts at the first sample showing the new value; any sample showing another value
    restarts it.  With a window of 0 it follows every change at once."""

    __slots__ = ("value", "window_s", "_pending", "_since")

    def __init__(self, window_s: float, value: Any = None) -> None:
        if not (math.isfinite(window_s) and window_s >= 0.0):
            raise LimitError("window_s", window_s, "a finite duration ≥ 0 s")
        self.window_s = window_s
        self.value: Any = value
        self._pending: Any = None
        self._since = 0.0

    def force(self, value: Any) -> None:
        self.value = value
        self._pending = None

    def update(self, candidate: Any, t_s: float) -> bool:
        """Offer the current sample's value; return True when the stable value changed."""
        if candidate == self.value:
            self._pending = None
            return False
        if candidate != self._pending:
            self._pending = candidate
            self._since = t_s
        if t_s - self._since >= self.window_s:
            self.value = candidate
            self._pending = None
            return True
        return False
