"""Finger poses: the tracking input of the renderer, its validation, and CSV replay.

The finger frame
----------------
Origin at the centre of the finger pad (the centre of the electrode array).  x to the right, y toward the
fingertip, z out of the pad toward what it touches.  A pose's orientation is the unit quaternion
(w, x, y, z) that rotates finger-frame vectors into the world (see :mod:`.geometry` for the world axes):
``p_world = position_mm + R(q) @ p_finger``.  The identity orientation is a finger pointing up with the
pad facing forward, as when pressing a button on a wall ahead.

Bad samples
-----------
Trackers drop out: NaN or infinite coordinates, quaternions that are not rotations, timestamps that go
backwards.  :class:`Pose` refuses them with a clear error; :class:`PoseValidator` turns them into counted
drops for a live stream, so a glitch costs one frame and never reaches the geometry as garbage.  A
quaternion whose norm is within ``norm_tolerance`` of 1 (rounding in a CSV, single-precision trackers) is
normalised; one farther off is not a rotation and is refused.
"""

from __future__ import annotations

import csv
import math
import os
from collections import Counter
from collections.abc import Iterable, Iterator, Sequence
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path
from typing import IO

import numpy as np

from ..errors import ConfigurationError, LimitError

QUAT_NORM_TOLERANCE = 0.01
"""|‖q‖ − 1| up to which a quaternion is normalised rather than refused."""

POSE_CSV_COLUMNS: tuple[str, ...] = ("t_s", "x_mm", "y_mm", "z_mm", "qw", "qx", "qy", "qz")


# --- rotations ---------------------------------------------------------------------------------------


def quat_to_matrix(q: Sequence[float] | np.ndarray) -> np.ndarray:
    """3 × 3 rotation of a unit quaternion (w, x, y, z)."""
    w, x, y, z = (float(v) for v in q)
    return np.array(
        (
            (1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)),
            (2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)),
            (2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)),
        )
    )


def matrix_to_quat(r: np.ndarray) -> np.ndarray:
    """Unit quaternion (w, x, y, z) with w ≥ 0 of a proper rotation matrix (Shepperd's method)."""
    m = np.asarray(r, dtype=float)
    tr = m[0, 0] + m[1, 1] + m[2, 2]
    if tr > 0:
        s = math.sqrt(tr + 1.0) * 2
        q = (0.25 * s, (m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s)
    elif m[0, 0] > m[1, 1] and m[0, 0] > m[2, 2]:
        s = math.sqrt(1.0 + m[0, 0] - m[1, 1] - m[2, 2]) * 2
        q = ((m[2, 1] - m[1, 2]) / s, 0.25 * s, (m[0, 1] + m[1, 0]) / s, (m[0, 2] + m[2, 0]) / s)
    elif m[1, 1] > m[2, 2]:
        s = math.sqrt(1.0 + m[1, 1] - m[0, 0] - m[2, 2]) * 2
        q = ((m[0, 2] - m[2, 0]) / s, (m[0, 1] + m[1, 0]) / s, 0.25 * s, (m[1, 2] + m[2, 1]) / s)
    else:
        s = math.sqrt(1.0 + m[2, 2] - m[0, 0] - m[1, 1]) * 2
        q = ((m[1, 0] - m[0, 1]) / s, (m[0, 2] + m[2, 0]) / s, (m[1, 2] + m[2, 1]) / s, 0.25 * s)
    out = np.array(q)
    out /= np.linalg.norm(out)
    return -out if out[0] < 0 else out


def quat_multiply(a: Sequence[float] | np.ndarray, b: Sequence[float] | np.ndarray) -> np.ndarray:
    """Hamilton product a ⊗ b (apply b, then a)."""
    aw, ax, ay, az = (float(v) for v in a)
    bw, bx, by, bz = (float(v) for v in b)
    return np.array(
        (
            aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
        )
    )


def quat_from_axis_angle(axis: Sequence[float] | np.ndarray, angle_deg: float) -> np.ndarray:
    a = np.asarray(axis, dtype=float)
    norm = float(np.linalg.norm(a))
    if norm == 0.0 or not math.isfinite(norm):
        raise ConfigurationError(f"rotation axis={list(axis)!r} must be a finite non-zero vector")
    half = math.radians(float(angle_deg)) / 2.0
    return np.concatenate(([math.cos(half)], math.sin(half) * a / norm))


def rotation_from_euler_deg(rx: float, ry: float, rz: float) -> np.ndarray:
    """Rotation about the world x axis by ``rx``, then y by ``ry``, then z by ``rz`` (R = Rz·Ry·Rx)."""
    cx, sx = math.cos(math.radians(rx)), math.sin(math.radians(rx))
    cy, sy = math.cos(math.radians(ry)), math.sin(math.radians(ry))
    cz, sz = math.cos(math.radians(rz)), math.sin(math.radians(rz))
    rxm = np.array(((1, 0, 0), (0, cx, -sx), (0, sx, cx)))
    rym = np.array(((cy, 0, sy), (0, 1, 0), (-sy, 0, cy)))
    rzm = np.array(((cz, -sz, 0), (sz, cz, 0), (0, 0, 1)))
    out: np.ndarray = rzm @ rym @ rxm
    return out


def frame_from_z_y(z_axis: Sequence[float] | np.ndarray, y_hint: Sequence[float] | np.ndarray) -> np.ndarray:
    """World-from-finger rotation whose z axis is ``z_axis`` and whose y axis is as close as possible to
    ``y_hint`` (falls back to another hint when the two are parallel)."""
    z = np.asarray(z_axis, dtype=float)
    z = z / np.linalg.norm(z)
    for hint in (np.asarray(y_hint, dtype=float), np.array((0.0, 0.0, 1.0)), np.array((0.0, 1.0, 0.0))):
        y = hint - np.dot(hint, z) * z
        n = float(np.linalg.norm(y))
        if n > 1e-6:
            y /= n
            break
    x = np.cross(y, z)
    return np.column_stack((x, y, z))


def slerp(q0: np.ndarray, q1: np.ndarray, u: float) -> np.ndarray:
    """Spherical interpolation between unit quaternions along the shorter arc."""
    a = np.asarray(q0, dtype=float)
    b = np.asarray(q1, dtype=float)
    d = float(np.dot(a, b))
    if d < 0.0:
        b, d = -b, -d
    if d > 0.9995:
        out = a + u * (b - a)
        unit: np.ndarray = out / np.linalg.norm(out)
        return unit
    theta = math.acos(min(1.0, d))
    s = math.sin(theta)
    return (math.sin((1 - u) * theta) * a + math.sin(u * theta) * b) / s


# --- poses --------------------------------------------------------------------------------------------


def _normalised_quaternion(q: np.ndarray, tolerance: float, field_name: str = "orientation") -> np.ndarray:
    if q.shape != (4,):
        raise ConfigurationError(f"{field_name} must be 4 numbers (w, x, y, z), got shape {q.shape}")
    if not np.isfinite(q).all():
        raise LimitError(field_name, q.tolist(), "finite numbers")
    norm = math.sqrt(float(q @ q))
    if abs(norm - 1.0) > tolerance:
        raise LimitError(
            f"{field_name} norm", round(norm, 6), f"a unit quaternion, norm within 1 ± {tolerance}"
        )
    return q / norm


@dataclass(frozen=True, eq=False)
class Pose:
    """One tracking sample: time in seconds, pad-centre position in world mm, orientation (w, x, y, z).

    Construction validates: a NaN, an infinity or a quaternion that is not (nearly) unit raises
    :class:`~tactdeform_hw.errors.LimitError` naming the field; a nearly unit quaternion is normalised.
    """

    t_s: float
    position_mm: np.ndarray
    orientation: np.ndarray = field(default_factory=lambda: np.array((1.0, 0.0, 0.0, 0.0)))

    def __post_init__(self) -> None:
        self._validate(QUAT_NORM_TOLERANCE)

    def _validate(self, tolerance: float) -> None:
        t = self.t_s
        if isinstance(t, bool) or not isinstance(t, (int, float, np.integer, np.floating)):
            raise LimitError("t_s", t, "a finite number of seconds")
        t = float(t)
        if not math.isfinite(t):
            raise LimitError("t_s", t, "a finite number of seconds")
        p = np.array(self.position_mm, dtype=float)
        if p.shape != (3,):
            raise ConfigurationError(f"position_mm must be 3 numbers, got shape {p.shape}")
        if not np.isfinite(p).all():
            raise LimitError("position_mm", p.tolist(), "finite numbers")
        q = _normalised_quaternion(np.array(self.orientation, dtype=float), tolerance)
        p.flags.writeable = False
        q.flags.writeable = False
        object.__setattr__(self, "t_s", t)
        object.__setattr__(self, "position_mm", p)
        object.__setattr__(self, "orientation", q)

    @cached_property
    def rotation(self) -> np.ndarray:
        """World-from-finger rotation matrix; its columns are the finger axes in world coordinates."""
        r = quat_to_matrix(self.orientation)
        r.flags.writeable = False
        return r

    @property
    def x_axis(self) -> np.ndarray:
        """The finger's right, in world coordinates."""
        return self.rotation[:, 0]

    @property
    def y_axis(self) -> np.ndarray:
        """Toward the fingertip, in world coordinates."""
        return self.rotation[:, 1]

    @property
    def z_axis(self) -> np.ndarray:
        """Out of the pad toward what it touches, in world coordinates."""
        return self.rotation[:, 2]

    def to_world(self, points_finger_mm: np.ndarray) -> np.ndarray:
        """Finger-frame points (N, 3) or (3,) in mm → world mm."""
        pts = np.asarray(points_finger_mm, dtype=float)
        out: np.ndarray = pts @ self.rotation.T + self.position_mm
        return out

    def to_finger(self, points_world_mm: np.ndarray) -> np.ndarray:
        """World points (N, 3) or (3,) in mm → finger frame mm."""
        pts = np.asarray(points_world_mm, dtype=float)
        out: np.ndarray = (pts - self.position_mm) @ self.rotation
        return out

    def direction_to_finger(self, vector_world: np.ndarray) -> np.ndarray:
        """A world direction (no translation) expressed in the finger frame."""
        out: np.ndarray = np.asarray(vector_world, dtype=float) @ self.rotation
        return out

    def __repr__(self) -> str:
        p = ", ".join(f"{v:.3f}" for v in self.position_mm)
        q = ", ".join(f"{v:.5f}" for v in self.orientation)
        return f"Pose(t_s={self.t_s:.6f}, position_mm=({p}), orientation=({q}))"


class PoseValidator:
    """Turns a raw tracking stream into poses, counting what it drops and why.

    ``check`` returns a :class:`Pose` or ``None`` (dropped).  Reasons: ``non_finite`` (NaN or infinity in
    time, position or orientation), ``quaternion_norm`` (not a rotation), ``malformed`` (wrong number of
    values), ``time_not_increasing`` (a repeated or earlier timestamp: the renderer divides by Δt).
    With ``on_invalid="error"`` the first bad sample raises instead.
    """

    REASONS = ("non_finite", "quaternion_norm", "malformed", "time_not_increasing")

    def __init__(self, *, norm_tolerance: float = QUAT_NORM_TOLERANCE, on_invalid: str = "drop") -> None:
        if on_invalid not in ("drop", "error"):
            raise ConfigurationError(f"on_invalid={on_invalid!r} must be 'drop' or 'error'")
        if not (math.isfinite(norm_tolerance) and 0 <= norm_tolerance < 1):
            raise ConfigurationError(f"norm_tolerance={norm_tolerance!r} must be in [0, 1)")
        self.norm_tolerance = float(norm_tolerance)
        self.on_invalid = on_invalid
        self.drops: Counter[str] = Counter()
        self.accepted = 0
        self._last_t: float | None = None

    @property
    def dropped(self) -> int:
        return sum(self.drops.values())

    @property
    def last_t_s(self) -> float | None:
        """The time of the last sample accepted (None before the first): the next must come after it."""
        return self._last_t

    def reset(self) -> None:
        self.drops.clear()
        self.accepted = 0
        self._last_t = None

    def _drop(self, reason: str, message: str) -> None:
        if self.on_invalid == "error":
            raise ConfigurationError(message)
        self.drops[reason] += 1

    def check(
        self, t_s: float, position_mm: Sequence[float] | np.ndarray, orientation: Sequence[float] | np.ndarray
    ) -> Pose | None:
        try:
            t = float(t_s)
            p = np.asarray(position_mm, dtype=float)
            q = np.asarray(orientation, dtype=float)
        except (TypeError, ValueError):
            self._drop("malformed", f"pose sample is not numeric: t_s={t_s!r}, position={position_mm!r}")
            return None
        if p.shape != (3,) or q.shape != (4,):
            self._drop(
                "malformed", f"pose sample needs 3 position and 4 quaternion values, got {p.shape}, {q.shape}"
            )
            return None
        if not (math.isfinite(t) and np.isfinite(p).all() and np.isfinite(q).all()):
            self._drop(
                "non_finite",
                f"pose sample at t_s={t!r} has a NaN or infinite value: {p.tolist()}, {q.tolist()}",
            )
            return None
        norm = math.sqrt(float(q @ q))
        if abs(norm - 1.0) > self.norm_tolerance:
            self._drop(
                "quaternion_norm",
                f"pose sample at t_s={t!r}: quaternion norm {norm:.6g} is not within 1 ± "
                f"{self.norm_tolerance}",
            )
            return None
        if self._last_t is not None and t <= self._last_t:
            self._drop("time_not_increasing", f"pose sample time t_s={t!r} does not follow {self._last_t!r}")
            return None
        pose = Pose(t, p, q / norm)
        self._last_t = t
        self.accepted += 1
        return pose

    def check_pose(self, pose: Pose) -> Pose | None:
        """Apply the stream checks (time order) to an already valid pose."""
        return self.check(pose.t_s, pose.position_mm, pose.orientation)


# --- CSV replay ---------------------------------------------------------------------------------------


def _open_text(source: str | os.PathLike[str] | IO[str]) -> tuple[IO[str], str, bool]:
    if isinstance(source, (str, os.PathLike)):
        path = Path(source)
        try:
            return path.open("r", newline="", encoding="utf-8"), str(path), True
        except OSError as exc:
            raise ConfigurationError(f"cannot read pose file {str(path)!r}: {exc.strerror or exc}") from exc
    return source, getattr(source, "name", "<stream>"), False


def _csv_rows(source: str | os.PathLike[str] | IO[str]) -> Iterator[tuple[str, str, list[float]]]:
    """(file name, where, the eight numbers) of each data row of a replay file, in the header's order of
    :data:`POSE_CSV_COLUMNS`; a missing or non-numeric cell raises, naming the line, the row and the column.
    NaN and infinities are numbers here: judging them is the caller's business."""
    stream, name, owned = _open_text(source)
    try:
        # Keep each row's line number in the file, so an error points at the line a text editor shows.
        numbered = [
            (n, line)
            for n, line in enumerate(stream, start=1)
            if line.strip() and not line.lstrip().startswith("#")
        ]
        line_of = [n for n, _ in numbered]
        reader = csv.reader(line for _, line in numbered)
        header = next(reader, None)
        if header is None:
            raise ConfigurationError(
                f"{name}: empty pose file; expected the header {','.join(POSE_CSV_COLUMNS)}"
            )
        header = [h.strip() for h in header]
        missing = [c for c in POSE_CSV_COLUMNS if c not in header]
        if missing:
            raise ConfigurationError(
                f"{name}: header lacks column(s) {', '.join(missing)}; expected {','.join(POSE_CSV_COLUMNS)}"
            )
        cols = [header.index(c) for c in POSE_CSV_COLUMNS]
        for row_number, row in enumerate(reader, start=1):
            where = f"line {line_of[row_number]}, row {row_number}"
            values: list[float] = []
            for column, index in zip(POSE_CSV_COLUMNS, cols):
                if index >= len(row):
                    raise ConfigurationError(f"{name}: {where}, column {column!r}: missing value")
                cell = row[index].strip()
                try:
                    values.append(float(cell))
                except ValueError:
                    raise ConfigurationError(
                        f"{name}: {where}, column {column!r}: {cell!r} is not a number"
                    ) from None
            yield name, where, values
    finally:
        if owned:
            stream.close()


def iter_pose_csv(
    source: str | os.PathLike[str] | IO[str],
    *,
    invalid: str = "error",
    validator: PoseValidator | None = None,
) -> Iterator[Pose]:
    """Poses of a replay file, one per data row (``t_s,x_mm,y_mm,z_mm,qw,qx,qy,qz``; extra columns ignored,
    blank lines and lines starting with ``#`` skipped).

    A cell that is not a number is always an error naming the row and the column.  A row that parses but
    is not a valid pose (NaN, non-unit quaternion, time going backwards) raises with ``invalid="error"``
    and is counted in ``validator.drops`` and skipped with ``invalid="drop"``.  To hand every row to the
    renderer as a tracker delivered it, bad ones included, use :func:`read_pose_rows`.
    """
    if invalid not in ("error", "drop"):
        raise ConfigurationError(f"invalid={invalid!r} must be 'error' or 'drop'")
    check = validator if validator is not None else PoseValidator(on_invalid="drop")
    for name, where, values in _csv_rows(source):
        if invalid == "error":
            _check_row(name, where, values, check)
        pose = check.check(values[0], values[1:4], values[4:8])
        if pose is not None:
            yield pose


#: One replayed tracking sample as the tracker delivered it: time, position (3), quaternion (w, x, y, z).
PoseRow = tuple[float, np.ndarray, np.ndarray]


def read_pose_rows(source: str | os.PathLike[str] | IO[str]) -> list[PoseRow]:
    """Every data row of a replay file as a ``(t_s, position_mm, orientation)`` sample, unjudged: NaN,
    infinities, a quaternion that is not a rotation and a time that does not advance are kept, so that
    :meth:`~tactdeform_hw.render.pipeline.Renderer.run` meets them as it would from a live tracker and
    its lost-tracking rules decide.  A cell that is not a number is still an error naming its line, row
    and column (a tracker cannot deliver one)."""
    return [(v[0], np.array(v[1:4]), np.array(v[4:8])) for _, _, v in _csv_rows(source)]


def _check_row(name: str, where: str, values: list[float], validator: PoseValidator) -> None:
    for column, value in zip(POSE_CSV_COLUMNS, values):
        if not math.isfinite(value):
            raise ConfigurationError(f"{name}: {where}, column {column!r}: {value!r} is not finite")
    q = np.array(values[4:8])
    norm = math.sqrt(float(q @ q))
    if abs(norm - 1.0) > validator.norm_tolerance:
        raise ConfigurationError(
            f"{name}: {where}, columns 'qw'..'qz': quaternion norm {norm:.6g} is not within "
            f"1 ± {validator.norm_tolerance}"
        )
    last = validator.last_t_s
    if last is not None and values[0] <= last:
        raise ConfigurationError(
            f"{name}: {where}, column 't_s': {values[0]!r} does not follow the previous time {last!r}"
        )


def read_pose_csv(
    source: str | os.PathLike[str] | IO[str],
    *,
    invalid: str = "error",
    validator: PoseValidator | None = None,
) -> list[Pose]:
    """All poses of a replay file (see :func:`iter_pose_csv`)."""
    return list(iter_pose_csv(source, invalid=invalid, validator=validator))


def write_pose_csv(target: str | os.PathLike[str] | IO[str], poses: Iterable[Pose]) -> int:
    """Write poses as a replay file; returns the number of rows.  Floats are written exactly (repr), so a
    file read back gives the same poses."""
    if isinstance(target, (str, os.PathLike)):
        with Path(target).open("w", newline="", encoding="utf-8") as fh:
            return write_pose_csv(fh, poses)
    writer = csv.writer(target, lineterminator="\n")
    writer.writerow(POSE_CSV_COLUMNS)
    n = 0
    for pose in poses:
        writer.writerow(
            [repr(float(pose.t_s))]
            + [repr(float(v)) for v in pose.position_mm]
            + [repr(float(v)) for v in pose.orientation]
        )
        n += 1
    return n
