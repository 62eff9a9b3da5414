"""The pattern manager's temporal filters: the finger's motion history and the contact filter.

:class:`MotionHistory` keeps the pad's recent positions and their tremor-filtered average, from which
the manager reads speeds, the stroke direction and the depth of an approach.  :class:`ContactFilter`
decides when contact starts (held for a moment, or deep at once) and when it is lost (the mean signed
distance over a window above the release distance).  Their windows and thresholds are
:class:`~tactdeform_hw.render.manager.ManagerConfig` fields; the module docstring of
:mod:`~tactdeform_hw.render.manager` gives the reasons for each.
"""

from __future__ import annotations

import math
from collections import deque
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from .manager import ManagerConfig

#: One sample of a history: (t_s, x_mm, y_mm, z_mm).
Sample = tuple[float, float, float, float]


class MotionHistory:
    """The pad's positions over ``motion_window_s``, their average over ``slide_smoothing_s`` over the same
    window, and that average over the last ``stop_window_s``."""

    def __init__(self, config: ManagerConfig) -> None:
        self.config = config
        self.raw: deque[Sample] = deque()
        self.smoothed: deque[Sample] = deque()
        self.recent: deque[Sample] = deque()

    def clear(self) -> None:
        """Forget every sample (a tracking teleport: the motion before it is no motion of the finger)."""
        self.raw.clear()
        self.smoothed.clear()
        self.recent.clear()

    def add(self, t: float, p: tuple[float, float, float]) -> None:
        """Add the sample at ``t`` and drop what fell out of the windows (the oldest kept sample is the
        last one at or before the window's start, so a window always spans it)."""
        cfg = self.config
        raw = self.raw
        raw.append((t, p[0], p[1], p[2]))
        w0 = t - cfg.motion_window_s
        while len(raw) > 2 and raw[1][0] <= w0:
            raw.popleft()
        smoothed = self.smoothed
        smoothed.append((t, *self.smoothed_position(t)))
        while len(smoothed) > 2 and smoothed[1][0] <= w0:
            smoothed.popleft()
        recent = self.recent
        recent.append(smoothed[-1])
        w1 = t - cfg.stop_window_s
        while len(recent) > 2 and recent[1][0] <= w1:
            recent.popleft()

    @property
    def latest(self) -> Sample:
        """The newest tremor-filtered position."""
        return self.smoothed[-1]

    def smoothed_position(self, t: float) -> tuple[float, float, float]:
        """Mean position over the last ``slide_smoothing_s``: one 8 Hz period, which leaves at most a
        fifth of an 8–12 Hz tremor, so a finger sliding with tremor does not rock the texture back and
        forth, nor its speed and direction.  Recomputed from the samples each time (no running sum to
        drift)."""
        t0 = t - self.config.slide_smoothing_s
        sx = sy = sz = 0.0
        n = 0
        for e in reversed(self.raw):
            if e[0] < t0 and n:
                break
            sx += e[1]
            sy += e[2]
            sz += e[3]
            n += 1
        return (sx / n, sy / n, sz / n)

    def velocity(self) -> tuple[float, float, float] | None:
        """Velocity of the tremor-filtered position: its net displacement over ``motion_window_s``.

        The raw position's displacement over the window keeps up to twice the tremor amplitude, which
        at 1 mm reads as 6.7 mm/s in any direction — more than the 4 mm/s between ``slide_on_mm_s`` and
        ``slide_off_mm_s``, and at a 20 mm/s stroke a direction error of up to 18°, enough to hold the
        stroke in the wrong one of 8 bins.  Averaged over ``slide_smoothing_s`` first, 1 mm of 8–12 Hz
        tremor reads as at most 1.5 mm/s (4° at 20 mm/s).  None when no time has passed over the window."""
        t1, x1, y1, z1 = self.smoothed[-1]
        t0, x0, y0, z0 = self.smoothed[0]
        span = t1 - t0
        if not span > 1e-9:
            return None
        return ((x1 - x0) / span, (y1 - y0) / span, (z1 - z0) / span)

    def recent_normal_speed(self, n0: tuple[float, ...]) -> float:
        """Speed of the filtered position along ``n0`` over the last ``stop_window_s`` (0 with no span)."""
        sh = self.recent
        span = sh[-1][0] - sh[0][0]
        if not span > 1e-9:
            return 0.0
        return (
            (sh[-1][1] - sh[0][1]) * n0[0] + (sh[-1][2] - sh[0][2]) * n0[1] + (sh[-1][3] - sh[0][3]) * n0[2]
        ) / span

    def recent_speed(self, normal: tuple[float, ...]) -> float:
        """Tangential speed of the filtered position over the last ``stop_window_s``."""
        t1, x1, y1, z1 = self.recent[-1]
        t0, x0, y0, z0 = self.recent[0]
        span = t1 - t0
        if not span > 1e-9:
            return math.inf
        dx, dy, dz = x1 - x0, y1 - y0, z1 - z0
        dn = dx * normal[0] + dy * normal[1] + dz * normal[2]
        dx, dy, dz = dx - dn * normal[0], dy - dn * normal[1], dz - dn * normal[2]
        return math.sqrt(dx * dx + dy * dy + dz * dz) / span


class ContactFilter:
    """When contact starts and when it is lost.

    Onset: the pad inside the surface over ``onset_confirm_s``, or at once ``onset_deep_mm`` deep.  Loss:
    the mean signed distance over the contact's last ``contact_loss_window_s`` above
    ``contact_release_mm`` while the pad is outside, or at once beyond ``contact_loss_far_mm``."""

    def __init__(self, config: ManagerConfig) -> None:
        self.config = config
        self.in_since: float | None = None  # Idle: first of the consecutive samples in contact
        self.signed: deque[tuple[float, float]] = deque()  # (t, signed distance) since onset
        self.signed_sum = 0.0

    def reset(self) -> None:
        """No contact, and none building up."""
        self.in_since = None
        self.signed.clear()
        self.signed_sum = 0.0

    def begin(self, t: float, sd: float) -> None:
        """Contact starts at ``t`` with the pad ``sd`` mm from the surface (negative: inside)."""
        self.in_since = None
        self.signed.clear()
        self.signed.append((t, sd))
        self.signed_sum = sd

    def onset_due(self, t: float, sd: float, inside: bool) -> bool:
        """Idle: whether contact starts with this sample (``inside``: the pad at or past the contact
        distance)."""
        cfg = self.config
        if not inside:
            self.in_since = None
        elif self.in_since is None:
            self.in_since = t
        return (
            inside
            and self.in_since is not None
            and (
                t - self.in_since >= cfg.onset_confirm_s - 1e-9
                or sd <= cfg.contact_enter_mm - cfg.onset_deep_mm
            )
        )

    def lost(self, t: float, sd: float) -> bool:
        """In contact: whether this sample loses it.  Noise around a hover averages out; tremor on a light
        press averages to the press."""
        cfg = self.config
        if sd > cfg.contact_loss_far_mm:
            return True
        h = self.signed
        h.append((t, sd))
        self.signed_sum += sd
        w0 = t - cfg.contact_loss_window_s
        while len(h) > 1 and h[0][0] < w0:
            self.signed_sum -= h.popleft()[1]
        return sd > cfg.contact_enter_mm and self.signed_sum / len(h) > cfg.contact_release_mm
