"""The two Phase 2 baselines TactDeform was compared with, exactly as the paper defines them.

* UA, uniform activation: every electrode on while the fingertip is inside the object's boundary.
* CAM, contact-area mapping: each electrode on when its own position is in contact, i.e. inside the
  surface.

Neither has states, stability windows or expansion; both share the manager's input checks (a bad sample
is dropped and counted, never rendered) and its event-driven output (a frame only when the pattern
changes), so the three approaches are compared on the same footing.
"""

from __future__ import annotations

from typing import Any, Protocol

import numpy as np

from .array import ElectrodeArray
from .geometry import PadPlane
from .manager import IDLE, INTERACTING, ManagerOutput, ManagerStats, count_drop, counted_pose, quat_axes
from .patterns import Pattern
from .scene import APPROACHES as APPROACHES
from .tracking import QUAT_NORM_TOLERANCE

#: A position (mm) and a unit quaternion (w, x, y, z), as the pose checks return them.
Vec3 = tuple[float, float, float]
Quat = tuple[float, ...]


class ContainsScene(Protocol):
    def contains(self, points_mm: np.ndarray) -> np.ndarray: ...


class _Baseline:
    """Shared input checks and change detection."""

    name = "baseline"

    def __init__(
        self,
        array: ElectrodeArray | None = None,
        *,
        on_level: int = 1,
        quat_norm_tolerance: float = QUAT_NORM_TOLERANCE,
    ) -> None:
        self.array = array if array is not None else ElectrodeArray.tactdeform()
        self.on_level = on_level
        self.quat_norm_tolerance = quat_norm_tolerance
        self.stats = ManagerStats()
        n = self.array.count
        self.off: Pattern = (0,) * n
        self.all_on: Pattern = (on_level,) * n
        self._prepare()
        self.reset()

    def _prepare(self) -> None:
        """What a baseline derives from its array once (none by default)."""

    def reset(self) -> None:
        self._t: float | None = None
        self.state = IDLE
        self.pattern: Pattern = self.off
        self.last_sent: Pattern | None = None

    def _drop(self, t: Any, reason: str) -> ManagerOutput:
        tf = count_drop(self.stats, t, reason)
        return ManagerOutput(tf, self.state, None, None, None, self.name, self.pattern, [], reason)

    def drop(self, t_s: Any, reason: str) -> ManagerOutput:
        """Count a sample its stream judged unusable (``reason``) without looking at it (see
        :meth:`~.manager.PatternManager.drop`)."""
        return self._drop(t_s, reason)

    def update(
        self, t_s: float, position_mm: Any, orientation_wxyz: Any, query: Any, scene: Any = None
    ) -> ManagerOutput:
        checked = counted_pose(
            self.stats, t_s, position_mm, orientation_wxyz, self._t, self.quat_norm_tolerance
        )
        if isinstance(checked, str):
            return self._drop(t_s, checked)
        t, p, q = checked
        sd = None
        if query is not None:
            try:
                sd = float(query.signed_distance_mm)
            except (AttributeError, TypeError, ValueError):
                return self._drop(t, "query")
            if sd - sd != 0.0:
                return self._drop(t, "query")
        self._t = t
        pat = self._pattern(p, q, sd, scene, query)
        state = INTERACTING if any(pat) else IDLE
        if state != self.state:
            self.stats.transitions += 1
        self.state = state
        self.pattern = pat
        frames: list[tuple[float, Pattern]] = []
        if pat != self.last_sent:
            frames.append((t, pat))
            self.last_sent = pat
            self.stats.frames_out += 1
        feature = getattr(query, "feature", None) if state == INTERACTING else None
        texture = getattr(query, "texture_level", None) if state == INTERACTING else None
        return ManagerOutput(t, state, feature, None, texture, self.name, pat, frames)

    def _pattern(self, p: Vec3, q: Quat, sd: float | None, scene: Any, query: Any = None) -> Pattern:
        raise NotImplementedError


class UniformActivation(_Baseline):
    """UA: all electrodes while the pad centre is inside (signed distance ≤ 0) the nearest object."""

    name = "ua"

    def _pattern(self, p: Vec3, q: Quat, sd: float | None, scene: Any, query: Any = None) -> Pattern:
        return self.all_on if (sd is not None and sd <= 0.0) else self.off


class ContactAreaMapping(_Baseline):
    """CAM: electrode i on when its own centre, placed on the pad in the world, is inside the scene.

    The electrodes lie in the pad plane (finger-frame z = 0) at their array positions relative to the
    array centre, which is the tracked pad position.  A pad far outside every object skips the
    per-electrode test (``reach_mm`` beyond the array's radius cannot reach a surface), one pressed deeper
    than that has every electrode inside, and a scene that can answer for points of one plane
    (``contains_on_pad``: meshes, through their index and the pad-plane cross-section) does so instead of
    32 separate inside tests."""

    name = "cam"

    def _prepare(self) -> None:
        rel = self.array.world_offsets()
        self._rel = np.ascontiguousarray(rel, dtype=float)
        self.reach_mm = float(np.hypot(rel[:, 0], rel[:, 1]).max()) + 1e-6
        self._levels = np.array([0, self.on_level], dtype=np.int64)
        self._offsets = np.ascontiguousarray(self.array.positions_mm - self.array.centre_mm, dtype=float)
        self._scene_seen: Any = None
        self._scene_plane = False
        self._last_key: tuple[Any, ...] | None = None
        self._last_pattern: Pattern = self.off

    def _plane_test(self, scene: Any) -> bool:
        if scene is not self._scene_seen:
            self._scene_seen = scene
            self._scene_plane = bool(getattr(scene, "has_plane_test", False))
        return self._scene_plane

    def electrode_positions(self, p: Vec3, q: Quat) -> np.ndarray:
        """World positions (N, 3) of the electrode centres for a pad pose."""
        X, Y, _ = quat_axes(*q)
        basis = np.array((X, Y))
        world: np.ndarray = np.asarray(p) + self._rel @ basis
        return world

    def _pattern(self, p: Vec3, q: Quat, sd: float | None, scene: Any, query: Any = None) -> Pattern:
        if sd is None or sd > self.reach_mm or scene is None:
            return self.off
        if sd < -self.reach_mm and getattr(scene, "is_single_object", False):
            return self.all_on  # deeper than the array's radius inside the one solid: every electrode in
        key = (p, q, scene)
        if key == self._last_key:
            return self._last_pattern  # a pad at rest: the same electrodes are in contact
        on_pad = getattr(scene, "contains_on_pad", None) if self._plane_test(scene) else None
        if on_pad is not None:
            X, Y, _ = quat_axes(*q)
            inside = np.asarray(on_pad(PadPlane.of(p, X, Y, self._offsets), query), dtype=bool)
        else:
            inside = np.asarray(scene.contains(self.electrode_positions(p, q)), dtype=bool)
        pat: Pattern = tuple(self._levels[inside.astype(np.int64)].tolist())
        self._last_key = key
        self._last_pattern = pat
        return pat


def make_baseline(name: str, array: ElectrodeArray | None = None, *, on_level: int = 1) -> _Baseline:
    if name == "ua":
        return UniformActivation(array, on_level=on_level)
    if name == "cam":
        return ContactAreaMapping(array, on_level=on_level)
    from ..errors import LimitError

    raise LimitError("approach", name, "'ua' or 'cam' for a baseline")
