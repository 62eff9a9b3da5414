"""The pattern manager: TactDeform's Idle → Approaching → Interacting state machine.

One call per tracking sample (:meth:`PatternManager.update`) turns a finger pose and the scene's answer
about the nearest surface into the frames to send.  The manager never talks to a device; it says *what*
to send and *when* (only when the pattern changes), and the pipeline sends it.

States (paper): Idle — no contact; Approaching — contact detected, the feature (face / edge / corner)
picks the pattern and it expands one frame per 2 mm of travel toward the surface (eq. 1–3); the
feature, the edge's orientation and the direction "toward the surface" are taken at initial contact and
kept through the approach however deep the finger goes (an edge or corner is approached along its
bisector: the normal seen just before contact); Interacting — sustained, stable contact: a stationary
pad gets the orientation-shifted contact pattern (eq. 4) or the uniform one, a sliding pad the
texture-shifted pattern (eq. 5–7).  Losing contact returns to Idle from any state; Interacting only ends
through Idle.

Temporal filtering.  The paper asks for parameters to be stable over a short window before they change
the state or the pattern, without giving lengths.  Physiological tremor is 8–12 Hz with up to about
1 mm amplitude; tracking noise is white.  The defaults (every one a :class:`ManagerConfig` field):

* **Onset** needs the pad in contact over ``onset_confirm_s`` = 8 ms (two samples at 72–120 Hz, so a
  real press starts within one 72 Hz frame of a stable contact, or one sample at slower rates) or at
  once ``onset_deep_mm`` = 3 mm deep (a fast finger).  A single noisy sample never starts stimulation:
  hovering 2 mm above with 1 mm noise is stimulated 0.19 % of the time, 1 mm above with 0.5 mm noise
  0.30 % (``tools/render_fidelity.py``).
* **Loss**: the mean signed distance over the contact's last ``contact_loss_window_s`` = 0.1 s is above
  ``contact_release_mm`` = 0.75 mm while the pad is outside (noise around a hover averages out, tremor
  on a light press averages to the press), or at once beyond ``contact_loss_far_mm`` = 10 mm.
* The position is first averaged over ``slide_smoothing_s`` = 0.125 s (one 8 Hz period: 1 mm of
  8–12 Hz tremor keeps at most 0.21 mm).  Speeds and the stroke direction come from that average's net
  displacement over ``motion_window_s`` = 0.5 s.
* **Approaching → Interacting** when the finger has stopped advancing: the averaged position has not
  gone ``advance_mm`` = 0.15 mm deeper than its deepest point for ``settle_hold_s`` = 0.25 s (so any
  approach faster than 0.6 mm/s keeps expanding — 1 mm/s reaches frame 15 at 30 mm) and it is not
  withdrawing faster than ``settle_speed_mm_s`` = 8 mm/s over the last ``stop_window_s`` = 0.15 s (a
  press-and-withdraw turns at its bottom without being taken for a rest).  Time since contact plays no
  part (``sustain_s`` = 0 adds an optional minimum).
* **Sliding** from the displacement over the motion window: on at ``slide_on_mm_s`` = 1.5 mm/s (the
  documented floor; texture shifts follow eq. 5 from there, 2.5 Hz rough at 5 mm/s) once the pad has
  left its resting place by ``slide_start_mm`` = 0.75 mm, off below ``slide_off_mm_s`` = 1 mm/s or as
  soon as the last ``stop_window_s`` moved less than ``stop_fraction`` = 1/4 of the window's mean speed
  (a stroke that stops is seen within about 0.2 s).  A start or end the speed alone asks for must hold
  ``slide_window_s`` = 0.1 s (tracking noise around the thresholds).  Tremor around a rest moves the averaged
  position less than 0.45 mm, under both thresholds.
* Edge orientation, θ level, sliding direction, texture level (and, while Interacting, the feature) each
  change only after their new value has held for 0.1 s, and the angular ones also have a margin past the
  bin boundary (7.5°, 5° and 10°); θ bins have a boundary tolerance of 1e-6°
  (:data:`~.contexts.THETA_TOLERANCE_DEG`), frames and shifts one of 1e-9 mm; the expansion frame and the
  texture shift count step down only ``frame_release_mm`` = 1.25 mm below a boundary.
* Texture travel is measured on the averaged position in straight segments, one per sliding direction:
  the tangential distance from the segment's start (the first starts where the pad rested).  Within a
  segment it telescopes, so tremor and tracking noise add a bounded error instead of shifts, and the
  texture is not rocked back and forth; it cannot drift.

Interpretations beyond the windows (all :class:`ManagerConfig` fields): eq. 3's count grows without
bound while a pattern has a few frames — ``approach_overflow="cycle"`` restarts the ring at the centre,
``"hold"`` stops at the outer ring; travel is ``"net"`` (withdrawing contracts the pattern, never below
frame 0) or ``"forward"``; the texture level is the surface's ``k_texture``; which contexts render and in
which sliding directions reproduce the tasks (Task 2 rendered only stationary contact, Task 3 only
rightward strokes).

Frame interpolation.  When the finger moves more than one frame's worth between two samples (a 10 m/s
approach covers 70 frames per 72 Hz sample), the update returns every frame it passed — up to one of
each distinct frame — with timestamps spread over the interval, so none is skipped in effect.

Bad input (NaN / inf position, time or quaternion, a quaternion far from unit length, time going
backwards, a malformed surface query) is dropped and counted; the last pattern stays (the pipeline turns
it off once tracking has been lost for its timeout).  A pose that jumps
further than ``teleport_min_mm`` faster than ``max_speed_mm_s`` is a tracking teleport: its displacement
is not counted as travel and any contact restarts from Idle.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, fields
from enum import Enum
from typing import Any, Literal

from ..errors import LimitError
from .array import ElectrodeArray
from .contexts import (
    ApproachState,
    Debounced,
    FrameAccumulator,
    contact_angle_deg,
    counts_to_show,
    displayed_frame,
    mask_phase,
    quantise_angle,
    theta_level,
)
from .filters import ContactFilter, MotionHistory
from .patterns import DIRECTIONS, EDGE_ORIENTATIONS, FEATURES, Pattern, PatternParams, PatternSet
from .tracking import QUAT_NORM_TOLERANCE


class State(str, Enum):
    """The manager's states (paper): no contact; contact detected, the pattern expanding toward the
    surface; sustained, stable contact.  A member equals its name as text (``State.IDLE == "idle"``)."""

    IDLE = "idle"
    APPROACHING = "approaching"
    INTERACTING = "interacting"

    def __str__(self) -> str:
        return self.value

    def __format__(self, spec: str) -> str:
        return format(self.value, spec)


#: The states as the outputs, frame records and reports name them.
IDLE: str = State.IDLE.value
APPROACHING: str = State.APPROACHING.value
INTERACTING: str = State.INTERACTING.value
STATES: tuple[str, ...] = tuple(s.value for s in State)

ContactMode = Literal["orientation", "uniform"]


@dataclass(frozen=True)
class ManagerConfig:
    """Every choice the renderer makes, with the paper's value or a documented interpretation."""

    # eq. 1–3
    alpha: float = 1.0
    d_electrode_mm: float | None = None  # None: the array's pitch (2.0 mm on the TactDeform array)
    approach_travel: Literal["net", "forward"] = "net"
    approach_overflow: Literal["cycle", "hold"] = "cycle"
    frame_release_mm: float = 1.25
    # contact detection
    contact_enter_mm: float = 0.0
    onset_confirm_s: float = 0.008  # in contact over this long (two samples at ≤ 120 Hz) before onset
    onset_deep_mm: float = 3.0  # ... or at once this deep: no hover noise reaches it
    contact_release_mm: float = 0.75  # mean signed distance over the loss window above this: lost
    contact_loss_window_s: float = 0.1
    contact_loss_far_mm: float = 10.0
    recent_outside_s: float = 0.25  # an outside sample this recent gives the approach normal and start
    # Approaching → Interacting: the finger has stopped advancing
    sustain_s: float = 0.0  # optional minimum contact time (the paper gives none)
    motion_window_s: float = 0.5
    settle_speed_mm_s: float = 8.0
    settle_hold_s: float = 0.25
    advance_mm: float = 0.15
    # stationary / sliding
    slide_on_mm_s: float = 1.5  # the documented sliding floor (≤ 2 mm/s)
    slide_off_mm_s: float = 1.0
    slide_start_mm: float = 0.75  # ... and this far from where the pad last rested
    stop_window_s: float = 0.15  # recent speed below stop_fraction of the window's: stopped
    stop_fraction: float = 0.25
    slide_window_s: float = 0.1  # a start or an end of sliding the speed asks for must hold this long
    slide_smoothing_s: float = 0.125  # position average before every speed, direction and texture travel
    # stability windows and hysteresis margins
    feature_window_s: float = 0.1
    orientation_window_s: float = 0.1
    orientation_margin_deg: float = 7.5
    theta_window_s: float = 0.1
    theta_margin_deg: float = 5.0
    direction_window_s: float = 0.1
    direction_margin_deg: float = 10.0
    texture_window_s: float = 0.1
    # contact context (eq. 4)
    contact_mode: ContactMode = "orientation"
    theta_plane: Literal["finger", "horizontal"] = "finger"
    up_axis: tuple[float, float, float] = (0.0, 1.0, 0.0)
    # sliding context (eq. 5–7)
    beta: float = 1.0
    mask_step_spacings: int | None = None  # None: k spacings per count (the spec's interpretation)
    use_texture: bool = True  # False: every surface renders as smooth (no texture machinery)
    slide_directions: frozenset[str] | None = None  # None: all 8; Task 3 rendered only {"E"}
    render_contact: bool = True  # Task 3 rendered nothing while stationary
    render_sliding: bool = True  # Task 2 rendered nothing while moving
    # input robustness
    max_speed_mm_s: float = 20000.0
    teleport_min_mm: float = 50.0
    quat_norm_tolerance: float = QUAT_NORM_TOLERANCE  # the tracking layer's: rounding, not garbage

    def __post_init__(self) -> None:
        for f in fields(self):
            v = getattr(self, f.name)
            if isinstance(v, float) and not math.isfinite(v):
                raise LimitError(f.name, v, "a finite number")
        nonneg = (
            "contact_release_mm",
            "contact_loss_window_s",
            "contact_loss_far_mm",
            "sustain_s",
            "settle_speed_mm_s",
            "settle_hold_s",
            "onset_confirm_s",
            "onset_deep_mm",
            "recent_outside_s",
            "advance_mm",
            "slide_start_mm",
            "stop_window_s",
            "stop_fraction",
            "slide_window_s",
            "slide_off_mm_s",
            "feature_window_s",
            "orientation_window_s",
            "orientation_margin_deg",
            "theta_window_s",
            "theta_margin_deg",
            "direction_window_s",
            "direction_margin_deg",
            "texture_window_s",
            "teleport_min_mm",
            "frame_release_mm",
            "slide_smoothing_s",
        )
        for name in nonneg:
            if getattr(self, name) < 0:
                raise LimitError(name, getattr(self, name), "≥ 0")
        if not self.alpha > 0:
            raise LimitError("alpha", self.alpha, "> 0")
        if self.d_electrode_mm is not None and not self.d_electrode_mm > 0:
            raise LimitError("d_electrode_mm", self.d_electrode_mm, "> 0 mm")
        if not self.advance_mm > 0:
            raise LimitError("advance_mm", self.advance_mm, "> 0 mm")
        if not self.motion_window_s > 0:
            raise LimitError("motion_window_s", self.motion_window_s, "> 0 s")
        if self.slide_smoothing_s > self.motion_window_s:
            raise LimitError(
                "slide_smoothing_s", self.slide_smoothing_s, f"≤ motion_window_s ({self.motion_window_s})"
            )
        if self.slide_on_mm_s < self.slide_off_mm_s:
            raise LimitError("slide_on_mm_s", self.slide_on_mm_s, f"≥ slide_off_mm_s ({self.slide_off_mm_s})")
        if self.contact_release_mm > self.contact_loss_far_mm:
            raise LimitError(
                "contact_release_mm",
                self.contact_release_mm,
                f"≤ contact_loss_far_mm ({self.contact_loss_far_mm})",
            )
        if self.contact_mode not in ("orientation", "uniform"):
            raise LimitError("contact_mode", self.contact_mode, "'orientation' or 'uniform'")
        if self.approach_overflow not in ("cycle", "hold"):
            raise LimitError("approach_overflow", self.approach_overflow, "'cycle' or 'hold'")
        if self.theta_plane not in ("finger", "horizontal"):
            raise LimitError("theta_plane", self.theta_plane, "'finger' or 'horizontal'")
        if self.beta == 0:
            raise LimitError("beta", self.beta, "+1 (opposite to the finger) or -1")
        if not self.max_speed_mm_s > 0:
            raise LimitError("max_speed_mm_s", self.max_speed_mm_s, "> 0")
        if not 0 < self.quat_norm_tolerance < 1:
            raise LimitError("quat_norm_tolerance", self.quat_norm_tolerance, "between 0 and 1")
        if self.slide_directions is not None:
            bad = set(self.slide_directions) - set(DIRECTIONS)
            if bad:
                raise LimitError("slide_directions", sorted(bad), f"names from {', '.join(DIRECTIONS)}")
        if self.mask_step_spacings is not None and self.mask_step_spacings < 1:
            raise LimitError("mask_step_spacings", self.mask_step_spacings, "≥ 1 spacing (or None for k)")
        u = self.up_axis
        if len(u) != 3 or abs(math.sqrt(sum(c * c for c in u)) - 1.0) > 1e-6:
            raise LimitError("up_axis", u, "a unit 3-vector")


@dataclass(slots=True)
class ManagerOutput:
    """What one update decided.  ``frames`` are the patterns to send now, in order, with the time each
    stands for (interpolated frames get times inside the last interval); empty when nothing changed."""

    t_s: float
    state: str
    feature: str | None
    orientation: str | None
    texture: int | None
    context: str | None
    pattern: Pattern
    frames: list[tuple[float, Pattern]] = field(default_factory=list)
    dropped: str | None = None


@dataclass
class ManagerStats:
    updates: int = 0
    dropped: dict[str, int] = field(default_factory=dict)
    teleports: int = 0
    transitions: int = 0
    frames_out: int = 0
    interpolated: int = 0
    normalised_quaternions: int = 0

    @property
    def dropped_total(self) -> int:
        return sum(self.dropped.values())


def quat_axes(w: float, x: float, y: float, z: float) -> tuple[tuple[float, float, float], ...]:
    """The finger frame's x (right), y (toward the fingertip) and z (out of the pad) axes in world
    coordinates: the columns of the rotation matrix of a unit quaternion (w, x, y, z)."""
    xx, yy, zz = x * x, y * y, z * z
    xy, xz, yz = x * y, x * z, y * z
    wx, wy, wz = w * x, w * y, w * z
    return (
        (1.0 - 2.0 * (yy + zz), 2.0 * (xy + wz), 2.0 * (xz - wy)),
        (2.0 * (xy - wz), 1.0 - 2.0 * (xx + zz), 2.0 * (yz + wx)),
        (2.0 * (xz + wy), 2.0 * (yz - wx), 1.0 - 2.0 * (xx + yy)),
    )


def _floats(v: Any, n: int) -> tuple[float, ...] | None:
    """``n`` finite floats from a sequence or numpy array, or None."""
    try:
        vals = v.tolist() if hasattr(v, "tolist") else list(v)
    except TypeError:
        return None
    if len(vals) != n:
        return None
    out: list[float] = []
    for c in vals:
        try:
            f = float(c)
        except (TypeError, ValueError):
            return None
        if f - f != 0.0:  # NaN or ±inf
            return None
        out.append(f)
    return tuple(out)


def check_pose(
    t_s: Any, position_mm: Any, orientation_wxyz: Any, t_prev: float | None, quat_tolerance: float
) -> tuple[float, tuple[float, float, float], tuple[float, float, float, float], bool] | str:
    """A tracking sample as plain floats with a unit quaternion, or the reason it cannot be used:
    ``time`` (not a finite number), ``time-backwards``, ``position`` (not three finite numbers),
    ``orientation`` (not four finite numbers) or ``orientation-norm`` (length off 1 by more than
    ``quat_tolerance`` — a zero or garbage quaternion rather than rounding).  The flag says whether the
    quaternion was renormalised."""
    try:
        t = float(t_s)
    except (TypeError, ValueError):
        return "time"
    if t - t != 0.0:
        return "time"
    if t_prev is not None and t < t_prev:
        return "time-backwards"
    pos = _floats(position_mm, 3)
    if pos is None:
        return "position"
    p = (pos[0], pos[1], pos[2])
    quat = _floats(orientation_wxyz, 4)
    if quat is None:
        return "orientation"
    q = (quat[0], quat[1], quat[2], quat[3])
    qn = math.sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3])
    if not abs(qn - 1.0) <= quat_tolerance:
        return "orientation-norm"
    renormed = False
    if qn != 1.0:
        renormed = abs(qn - 1.0) > 1e-9
        q = (q[0] / qn, q[1] / qn, q[2] / qn, q[3] / qn)
    return t, p, q, renormed


def check_query(query: Any) -> tuple[float, tuple[float, float, float] | None, str | None] | str:
    """The scene's answer for the pad centre as (signed distance in mm, unit normal, feature), with no
    surface (None) as (0, None, None); ``"query"`` when the answer cannot be used (not numbers, an unknown
    feature, a normal of no direction)."""
    if query is None:
        return 0.0, None, None
    try:
        sd = float(query.signed_distance_mm)
        raw_normal = _floats(query.normal, 3)
        feat = query.feature
    except (AttributeError, TypeError, ValueError):
        return "query"
    if sd - sd != 0.0 or raw_normal is None or feat not in FEATURES:
        return "query"
    nn = math.sqrt(raw_normal[0] ** 2 + raw_normal[1] ** 2 + raw_normal[2] ** 2)
    if not nn > 0.5:
        return "query"
    return sd, (raw_normal[0] / nn, raw_normal[1] / nn, raw_normal[2] / nn), feat


def counted_pose(
    stats: ManagerStats,
    t_s: Any,
    position_mm: Any,
    orientation_wxyz: Any,
    t_prev: float | None,
    quat_tolerance: float,
) -> tuple[float, tuple[float, float, float], tuple[float, float, float, float]] | str:
    """A pattern manager's sample, counted in ``stats`` alike for TactDeform and the baselines: the
    update, then :func:`check_pose` — its reason when the sample cannot be used (for the manager's own
    drop), else time, position and unit quaternion, a renormalised quaternion counted."""
    stats.updates += 1
    checked = check_pose(t_s, position_mm, orientation_wxyz, t_prev, quat_tolerance)
    if isinstance(checked, str):
        return checked
    t, p, q, renormed = checked
    if renormed:
        stats.normalised_quaternions += 1
    return t, p, q


def count_drop(stats: ManagerStats, t: Any, reason: str) -> float:
    """Count a dropped sample under ``reason``; its time as a float (NaN when it is not a number)."""
    stats.dropped[reason] = stats.dropped.get(reason, 0) + 1
    try:
        return float(t)
    except (TypeError, ValueError):
        return math.nan


class PatternManager:
    """State machine + stability filters + event-driven output for one finger on one array."""

    name = "tactdeform"

    def __init__(
        self,
        array: ElectrodeArray | None = None,
        config: ManagerConfig | None = None,
        *,
        patterns: PatternSet | None = None,
        pattern_params: PatternParams | None = None,
    ) -> None:
        self.array = (
            array
            if array is not None
            else (patterns.array if patterns is not None else ElectrodeArray.tactdeform())
        )
        self.config = config or ManagerConfig()
        self.patterns = patterns if patterns is not None else PatternSet(self.array, pattern_params)
        cfg = self.config
        self.d_mm = cfg.d_electrode_mm if cfg.d_electrode_mm is not None else self.array.pitch_mm
        self.frame_unit_mm = self.d_mm / cfg.alpha
        if cfg.frame_release_mm >= self.frame_unit_mm:
            raise LimitError(
                "frame_release_mm", cfg.frame_release_mm, f"< one frame ({self.frame_unit_mm:g} mm)"
            )
        self.stats = ManagerStats()
        self._allowed_dirs = (
            None
            if cfg.slide_directions is None
            else frozenset(DIRECTIONS.index(d) for d in cfg.slide_directions)
        )
        self.reset()

    # --- lifecycle ------------------------------------------------------------------------------------------

    def reset(self) -> None:
        """Forget the finger: Idle, nothing shown, no history (statistics are kept)."""
        cfg = self.config
        self.state = State.IDLE
        self.context: str | None = None
        self._t: float | None = None
        self._p: tuple[float, float, float] | None = None
        self._n: tuple[float, float, float] | None = None
        self.motion = MotionHistory(cfg)
        self.contact = ContactFilter(cfg)
        self._anchor: tuple[float, float, float, float] | None = None
        self._onset_t = 0.0
        self._outside: tuple[float, tuple[float, float, float], tuple[float, float, float], float] | None = (
            None
        )
        self._n_onset: tuple[float, float, float] = (0.0, 0.0, 1.0)
        self._m_onset: tuple[float, float, float] = (0.0, 0.0, 0.0)
        self._peak_mm = 0.0
        self._advanced_t = 0.0
        self.feature = Debounced(cfg.feature_window_s)
        self.orientation = Debounced(cfg.orientation_window_s)
        self.texture = Debounced(cfg.texture_window_s)
        self.theta = Debounced(cfg.theta_window_s)
        self.direction = Debounced(cfg.direction_window_s)
        self.approach = ApproachState(
            self.frame_unit_mm, mode=cfg.approach_travel, release_mm=cfg.frame_release_mm
        )
        self.slide = FrameAccumulator(self.d_mm)
        self._seg: tuple[float, float, float] | None = None
        self._slide_change_t: float | None = None
        self._seg_dir: int | None = None
        self._seg_len = 0.0
        self._ns: int | None = None
        self._ns_k = 0
        self.sliding = False
        self.theta_deg: float | None = None
        self._family: tuple[Any, ...] | None = None
        self._count: int | None = None
        self.pattern: Pattern = self.patterns.off
        self.last_sent: Pattern | None = None

    # --- public ---------------------------------------------------------------------------------------------

    @property
    def frame(self) -> int:
        """Eq. 3's frame count n in the current contact."""
        return self.approach.frame

    @property
    def shift_count(self) -> int:
        """Eq. 7's n_s for the current texture level (0 when smooth)."""
        k = self._k()
        if not k:
            return 0
        return self._ns if (self._ns is not None and self._ns_k == k) else self.slide.whole // k

    def update(
        self, t_s: float, position_mm: Any, orientation_wxyz: Any, query: Any, scene: Any = None
    ) -> ManagerOutput:
        """Advance by one tracking sample.  ``query`` is the scene's
        :class:`~tactdeform_hw.render.geometry.SurfaceQuery` for the pad centre, or None (no object);
        ``scene`` is unused (the query holds all TactDeform needs; the baselines' CAM asks the scene)."""
        # --- validate everything before any state changes ------------------------------------------------
        checked = counted_pose(
            self.stats, t_s, position_mm, orientation_wxyz, self._t, self.config.quat_norm_tolerance
        )
        if isinstance(checked, str):
            return self._drop(t_s, checked)
        t, p, q = checked
        surface = check_query(query)
        if isinstance(surface, str):
            return self._drop(t, surface)
        sd, normal, feat = surface
        cfg = self.config
        t_prev, p_prev = self._t, self._p
        teleport = self._track(t, p)
        # --- contact ----------------------------------------------------------------------------------------
        old_state = self.state
        if self.state is not State.IDLE and (teleport or normal is None or self.contact.lost(t, sd)):
            self._to_idle()
        seq: list[Pattern]
        if self.state is State.IDLE:
            inside = normal is not None and sd <= cfg.contact_enter_mm
            if self.contact.onset_due(t, sd, inside):
                assert feat is not None and normal is not None  # a normal is only kept with a checked feature
                seq = self._onset(t, p, q, sd, normal, feat, query)
            else:
                seq = [self.patterns.off]
        else:
            # In contact implies a query (no query loses contact) and a previous sample.
            assert normal is not None and feat is not None and p_prev is not None
            seq = self._in_contact(t, p, p_prev, q, normal, feat, query)
        if self.state != old_state:
            self.stats.transitions += 1
        self._n = normal
        if normal is not None and sd > cfg.contact_enter_mm:
            self._outside = (t, p, normal, sd)
        return self._emit(t, t_prev, seq)

    def _track(self, t: float, p: tuple[float, float, float]) -> bool:
        """Take the sample into the motion history; whether it is a tracking teleport (a jump further than
        ``teleport_min_mm`` faster than ``max_speed_mm_s``), which forgets the motion before it."""
        cfg = self.config
        t_prev, p_prev = self._t, self._p
        teleport = False
        if p_prev is not None and t_prev is not None:
            dx, dy, dz = p[0] - p_prev[0], p[1] - p_prev[1], p[2] - p_prev[2]
            step = math.sqrt(dx * dx + dy * dy + dz * dz)
            if step > cfg.teleport_min_mm and step > cfg.max_speed_mm_s * (t - t_prev):
                teleport = True
                self.stats.teleports += 1
                self._outside = None
                self.motion.clear()
        self._t = t
        self._p = p
        self.motion.add(t, p)
        return teleport

    def drop(self, t_s: Any, reason: str) -> ManagerOutput:
        """Count a sample its stream judged unusable (``reason``) without looking at it: nothing changes,
        the output holds what is shown.  The renderer judges time order against every sample received,
        which an approach reset at lost tracking no longer remembers."""
        return self._drop(t_s, reason)

    # --- internals -----------------------------------------------------------------------------------------

    def _drop(self, t: Any, reason: str) -> ManagerOutput:
        return self._output(count_drop(self.stats, t, reason), [], reason)

    def _output(
        self, t: float, frames: list[tuple[float, Pattern]], dropped: str | None = None
    ) -> ManagerOutput:
        """The manager as a sample at ``t`` leaves it (state, parameters, context, pattern), with the frames
        that sample sends; a dropped sample sends none and says why."""
        return ManagerOutput(
            t,
            self.state.value,
            self.feature.value,
            self._orient_value_name(),
            self.texture.value,
            self.context,
            self.pattern,
            frames,
            dropped,
        )

    def _to_idle(self) -> None:
        self.state = State.IDLE
        self.context = None
        self.contact.reset()
        self.sliding = False
        self._slide_change_t = None
        self.theta_deg = None
        self._family = None
        self._count = None
        for d in (self.feature, self.orientation, self.texture, self.theta, self.direction):
            d.force(None)

    def _k(self) -> int:
        v = self.texture.value
        return int(v) if (v and self.config.use_texture) else 0

    def _edge_bin(self, query: Any, q: tuple[float, ...], current: int | None) -> int | None:
        e = query.edge_direction
        if e is None:
            return current
        ev = _floats(e, 3)
        if ev is None:
            return current
        X, Y, _ = quat_axes(*q)
        ex = ev[0] * X[0] + ev[1] * X[1] + ev[2] * X[2]
        ey = ev[0] * Y[0] + ev[1] * Y[1] + ev[2] * Y[2]
        if ex * ex + ey * ey < 0.04:  # the edge points (almost) into the pad: orientation undefined
            return current
        ang = math.degrees(math.atan2(ey, ex))
        return quantise_angle(ang, 4, 180.0, current, self.config.orientation_margin_deg)

    def _texture_of(self, query: Any) -> int:
        if not self.config.use_texture:
            return 0
        try:
            k = int(query.texture_level)
        except (AttributeError, TypeError, ValueError):
            return 0
        return k if 0 <= k <= 8 else 0

    def _onset(
        self,
        t: float,
        p: tuple[float, ...],
        q: tuple[float, ...],
        sd: float,
        normal: tuple[float, ...],
        feat: str,
        query: Any,
    ) -> list[Pattern]:
        cfg = self.config
        self.state = State.APPROACHING
        self.context = APPROACHING
        self._onset_t = t
        self.contact.begin(t, sd)
        # Latched at initial contact and kept through the approach (paper): the feature, the edge's
        # orientation and the direction "toward the surface".  That direction is the normal seen just
        # before contact (an edge's or corner's bisector, where the nearest surface point was the edge
        # or corner itself); once inside, the nearest point moves onto a face and its normal would
        # count travel along a bisector short by cos 45°.
        out = self._outside
        n0: tuple[float, ...]
        if out is not None and t - out[0] <= cfg.recent_outside_s:
            n0 = out[2]
            po = out[1]
            travel = -((p[0] - po[0]) * n0[0] + (p[1] - po[1]) * n0[1] + (p[2] - po[2]) * n0[2]) - (
                out[3] - cfg.contact_enter_mm
            )
        else:
            n0 = normal
            travel = cfg.contact_enter_mm - sd
        self._n_onset = (n0[0], n0[1], n0[2])
        m = self.motion.latest
        self._m_onset = (m[1], m[2], m[3])
        self._peak_mm = 0.0
        self._advanced_t = t
        self.feature.force(feat)
        self.orientation.force(self._edge_bin(query, q, None) if feat == "edge" else None)
        if feat == "edge" and self.orientation.value is None:
            self.orientation.force(0)
        self.texture.force(self._texture_of(query))
        self.approach.begin(max(0.0, travel))
        self.slide.reset()
        self._seg = None
        self._ns = None
        self._family = None
        self._count = -1
        return self._approach_seq(onset=True)

    def _approach_seq(self, onset: bool = False) -> list[Pattern]:
        feat = self.feature.value
        orient = EDGE_ORIENTATIONS[self.orientation.value] if feat == "edge" else None
        frames = self.patterns.frames(feat, orient)
        nf = len(frames)
        fam = ("approach", feat, orient)
        n = self.approach.frame
        if onset or fam == self._family:
            counts = counts_to_show(self._count, n, nf)
        else:
            counts = [n]
        self._family = fam
        self._count = n
        ov = self.config.approach_overflow
        return [frames[displayed_frame(c, nf, ov)] for c in counts]

    def _in_contact(
        self,
        t: float,
        p: tuple[float, ...],
        p_prev: tuple[float, ...],
        q: tuple[float, ...],
        normal: tuple[float, ...],
        feat: str,
        query: Any,
    ) -> list[Pattern]:
        v = self.motion.velocity()
        if self.state is State.APPROACHING:
            seq = self._approaching(t, p, p_prev, query)
            if seq is not None:
                return seq
        self._hold_parameters(t, feat, q, query)
        # Stationary contact or sliding.
        if v is None and self.sliding:
            # No time has passed since the window's start (repeated timestamps): keep sliding as is.
            self.context = "sliding"
            return self._sliding_seq()
        vt, speed = self._judge_sliding(t, v, normal)
        if self.sliding and vt is not None and speed > 0.0:
            return self._slide(t, q, vt, speed, normal)
        return self._contact(t, q, normal)

    def _approaching(
        self, t: float, p: tuple[float, ...], p_prev: tuple[float, ...], query: Any
    ) -> list[Pattern] | None:
        """One sample while Approaching: the expansion's frames, or None once the finger has settled
        (the state is then Interacting and the sample is rendered as contact)."""
        cfg = self.config
        # Eq. 3's travel: displacement along the direction latched at contact; feature and
        # orientation stay as they were at contact, however deep the finger goes.
        n0 = self._n_onset
        self.approach.advance(
            -((p[0] - p_prev[0]) * n0[0] + (p[1] - p_prev[1]) * n0[1] + (p[2] - p_prev[2]) * n0[2])
        )
        self.texture.update(self._texture_of(query), t)
        # Stopped advancing: the tremor-filtered position has not gone ``advance_mm`` deeper than its
        # deepest point for ``settle_hold_s`` (any approach faster than advance_mm / settle_hold_s,
        # 0.6 mm/s by default, keeps expanding) and is not withdrawing fast.
        m = self.motion.latest
        mo = self._m_onset
        depth = -((m[1] - mo[0]) * n0[0] + (m[2] - mo[1]) * n0[1] + (m[3] - mo[2]) * n0[2])
        if depth >= self._peak_mm + cfg.advance_mm:
            self._peak_mm = depth
            self._advanced_t = t
        # Not withdrawing fast either: judged on the recent window, which a turn at the bottom of a
        # press-and-withdraw leaves quickly (the long window reads such a turn as still).
        vn = self.motion.recent_normal_speed(n0)
        if (
            t - self._advanced_t >= cfg.settle_hold_s
            and t - self._onset_t >= cfg.sustain_s
            and abs(vn) <= cfg.settle_speed_mm_s
        ):
            self.state = State.INTERACTING
            self._family = None
            self.theta.force(None)
            self.direction.force(None)
            self.sliding = False
            self._slide_change_t = None
            self._anchor = self.motion.latest
        else:
            self.context = APPROACHING
            return self._approach_seq()
        return None

    def _hold_parameters(self, t: float, feat: str, q: tuple[float, ...], query: Any) -> None:
        """Interacting: feature, edge orientation and texture change only after holding for their
        stability windows."""
        self.feature.update(feat, t)
        if self.feature.value == "edge":
            cur = self.orientation.value
            cand = self._edge_bin(query, q, cur) if feat == "edge" else cur
            if cand is None:
                cand = 0
            if cur is None:
                self.orientation.force(cand)
            else:
                self.orientation.update(cand, t)
        self.texture.update(self._texture_of(query), t)

    def _judge_sliding(
        self, t: float, v: tuple[float, float, float] | None, normal: tuple[float, ...]
    ) -> tuple[tuple[float, float, float] | None, float]:
        """Whether the pad slides (``self.sliding``); returns its tangential velocity and speed."""
        cfg = self.config
        vt = None
        speed = 0.0
        if v is not None:
            vn = v[0] * normal[0] + v[1] * normal[1] + v[2] * normal[2]
            vt = (v[0] - vn * normal[0], v[1] - vn * normal[1], v[2] - vn * normal[2])
            speed = math.sqrt(vt[0] * vt[0] + vt[1] * vt[1] + vt[2] * vt[2])
            # Sliding from displacement over the motion window (any speed above the slide_on floor),
            # ended early when the last stop_window_s moved much less than the window's mean (a
            # stroke that stopped need not wait for the long window to empty), and restarted only
            # once the pad has left its resting place by slide_start_mm (tremor and noise around a
            # rest move the filtered position far less).
            # A change the speed alone asks for must hold for ``slide_window_s`` (noise around the
            # thresholds); a stop is taken at once.
            stopped = self.motion.recent_speed(normal) < cfg.stop_fraction * speed
            if self.sliding:
                if stopped:
                    self.sliding = False
                elif speed > cfg.slide_off_mm_s:
                    self._slide_change_t = None
                elif self._slide_change_t is None:
                    self._slide_change_t = t
                if self._slide_change_t is not None and t - self._slide_change_t >= cfg.slide_window_s:
                    self.sliding = False
                if not self.sliding:
                    self._slide_change_t = None
                    self._anchor = self.motion.latest
            else:
                anc = self._anchor
                m = self.motion.latest
                if anc is None:
                    far = True
                else:
                    dx, dy, dz = m[1] - anc[1], m[2] - anc[2], m[3] - anc[3]
                    dn = dx * normal[0] + dy * normal[1] + dz * normal[2]
                    far = dx * dx + dy * dy + dz * dz - dn * dn >= cfg.slide_start_mm**2
                want = speed >= cfg.slide_on_mm_s and far and not stopped
                if not want:
                    self._slide_change_t = None
                elif self._slide_change_t is None:
                    self._slide_change_t = t
                since = self._slide_change_t
                if want and since is not None and t - since >= cfg.slide_window_s:
                    self.sliding = True
                    self._slide_change_t = None
        return vt, speed

    def _slide(
        self,
        t: float,
        q: tuple[float, ...],
        vt: tuple[float, float, float],
        speed: float,
        normal: tuple[float, ...],
    ) -> list[Pattern]:
        """A sliding sample: the direction (held for its window) and the texture travel."""
        cfg = self.config
        X, Y, _ = quat_axes(*q)
        m = self.motion.latest
        ux, uy, uz = vt[0] / speed, vt[1] / speed, vt[2] / speed
        a = math.degrees(math.atan2(ux * Y[0] + uy * Y[1] + uz * Y[2], ux * X[0] + uy * X[1] + uz * X[2]))
        cur = self.direction.value
        cand = quantise_angle(a, 8, 360.0, cur, cfg.direction_margin_deg)
        if cur is None:
            self.direction.force(cand)
        else:
            self.direction.update(cand, t)
        # Texture travel (eq. 7's ∫ v_slide): the stroke in straight segments, one per sliding
        # direction, each measured as the tangential distance of the filtered position from the
        # segment's start.  Within a segment the sum telescopes, so tremor and tracking noise add a
        # bounded error, never a drift (a per-sample projection on a noisy direction would add
        # their correlated part at every sample); a stroke's first segment starts where the pad
        # rested, so the travel before sliding was recognised counts too.
        seg = self._seg
        if seg is None or self.direction.value != self._seg_dir:
            anc = self._anchor
            self._seg = seg = (
                (anc[1], anc[2], anc[3]) if (seg is None and anc is not None) else (m[1], m[2], m[3])
            )
            self._seg_dir = self.direction.value
            self._seg_len = 0.0
        dx, dy, dz = m[1] - seg[0], m[2] - seg[1], m[3] - seg[2]
        dn = dx * normal[0] + dy * normal[1] + dz * normal[2]
        length = math.sqrt(max(0.0, dx * dx + dy * dy + dz * dz - dn * dn))
        if self._k():
            self.slide.add(length - self._seg_len)
        self._seg_len = length
        self.context = "sliding"
        return self._sliding_seq()

    def _contact(self, t: float, q: tuple[float, ...], normal: tuple[float, ...]) -> list[Pattern]:
        """A stationary contact sample: the feature's static or contact-angle pattern."""
        cfg = self.config
        self._seg = None
        self.context = "contact"
        if not cfg.render_contact:
            self._family = None
            return [self.patterns.off]
        feat_v = self.feature.value
        orient = EDGE_ORIENTATIONS[self.orientation.value] if feat_v == "edge" else None
        self._family = None
        if cfg.contact_mode == "uniform":
            return [self.patterns.static(feat_v, orient)]
        X, _, Z = quat_axes(*q)
        th = contact_angle_deg(normal, X, Z, plane=cfg.theta_plane, up=cfg.up_axis)
        self.theta_deg = th
        cur = self.theta.value
        cand = theta_level(th, cur, cfg.theta_margin_deg)
        if cur is None:
            self.theta.force(cand)
        else:
            self.theta.update(cand, t)
        return [self.patterns.contact(feat_v, orient, self.theta.value)]

    def _shift_shown(self, k: int) -> int:
        """Eq. 7's n_s with the same release band as the expansion frames: the count goes down only
        once the travel is ``frame_release_mm`` below the count's start."""
        unit = self.d_mm * k
        travel = self.slide.travel_mm
        n_true = self.slide.whole // k
        cur = self._ns if self._ns_k == k else None
        if cur is None or n_true > cur:
            cur = n_true
        elif n_true < cur and travel < cur * unit - self.config.frame_release_mm:
            cur = max(n_true, math.floor((travel + self.config.frame_release_mm) / unit))
        self._ns = cur
        self._ns_k = k
        return cur

    def _sliding_seq(self) -> list[Pattern]:
        cfg = self.config
        feat = self.feature.value
        orient = EDGE_ORIENTATIONS[self.orientation.value] if feat == "edge" else None
        direction: int = self.direction.value
        if not cfg.render_sliding or (self._allowed_dirs is not None and direction not in self._allowed_dirs):
            self._family = None
            return [self.patterns.off]
        k = self._k()
        ps = self.patterns
        if k == 0:
            self._family = None
            return [ps.static(feat, orient)]
        count = self._shift_shown(k)
        period = ps.mask_period(k)
        step = k if cfg.mask_step_spacings is None else cfg.mask_step_spacings
        distinct = period // math.gcd(step, period)
        fam = ("slide", feat, orient, direction, k)
        counts = counts_to_show(self._count, count, distinct) if fam == self._family else [count]
        self._family = fam
        self._count = count
        pf = ps.params.mask_period_factor
        return [
            ps.sliding(feat, orient, direction, k, mask_phase(c, k, pf, cfg.mask_step_spacings, cfg.beta))
            for c in counts
        ]

    def _emit(self, t: float, t_prev: float | None, seq: list[Pattern]) -> ManagerOutput:
        last = self.last_sent
        out: list[Pattern] = []
        for pat in seq:
            if pat != (out[-1] if out else last):
                out.append(pat)
        frames: list[tuple[float, Pattern]] = []
        if out:
            m = len(out)
            if m > 1 and t_prev is not None and t > t_prev:
                dt = (t - t_prev) / m
                frames = [(t_prev + dt * (i + 1) if i < m - 1 else t, pat) for i, pat in enumerate(out)]
            else:
                frames = [(t, pat) for pat in out]
            self.last_sent = out[-1]
            self.stats.frames_out += m
            self.stats.interpolated += m - 1
        if seq:
            self.pattern = seq[-1]
        return self._output(t, frames)

    def _orient_value_name(self) -> str | None:
        if self.feature.value != "edge" or self.orientation.value is None:
            return None
        return str(EDGE_ORIENTATIONS[self.orientation.value])
