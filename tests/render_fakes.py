"""Small stand-ins for the scene side of the renderer: a flat object answering with real
:class:`tactdeform_hw.render.geometry.SurfaceQuery` values, and finger poses."""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np

from tactdeform_hw.render.geometry import SurfaceQuery


class FakeFloor:
    """An object filling z ≤ 0 (a table top, outward normal +z).  ``feature`` and ``texture_level``
    may be functions of the query point, to put edges, corners or textured regions anywhere."""

    def __init__(
        self,
        name: str = "floor",
        feature: str | Callable[[np.ndarray], str] = "face",
        edge_direction: tuple[float, float, float] | None = None,
        texture_level: int | Callable[[np.ndarray], int] = 0,
    ) -> None:
        self.name = name
        self.feature = feature
        self.edge_direction = None if edge_direction is None else np.array(edge_direction, dtype=float)
        self.texture_level = texture_level
        self.queries = 0

    def query(self, point_mm: np.ndarray) -> SurfaceQuery:
        self.queries += 1
        p = np.asarray(point_mm, dtype=float)
        feat = self.feature(p) if callable(self.feature) else self.feature
        tex = self.texture_level(p) if callable(self.texture_level) else self.texture_level
        return SurfaceQuery(
            self.name,
            float(p[2]),
            np.array([p[0], p[1], 0.0]),
            np.array([0.0, 0.0, 1.0]),
            feat,
            self.edge_direction if feat == "edge" else None,
            int(tex),
        )

    def contains(self, points_mm: np.ndarray) -> np.ndarray:
        return np.asarray(points_mm, dtype=float)[:, 2] <= 0.0


def quat_from_axes(
    x_axis: np.ndarray, y_axis: np.ndarray, z_axis: np.ndarray
) -> tuple[float, float, float, float]:
    """Unit quaternion (w, x, y, z) of the rotation whose columns are the finger axes."""
    m = np.column_stack([x_axis, y_axis, z_axis]).astype(float)
    tr = m[0, 0] + m[1, 1] + m[2, 2]
    if tr > 0:
        s = math.sqrt(tr + 1.0) * 2
        w, x, y, z = 0.25 * s, (m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s
    elif m[0, 0] > m[1, 1] and m[0, 0] > m[2, 2]:
        s = math.sqrt(1.0 + m[0, 0] - m[1, 1] - m[2, 2]) * 2
        w, x, y, z = (m[2, 1] - m[1, 2]) / s, 0.25 * s, (m[0, 1] + m[1, 0]) / s, (m[0, 2] + m[2, 0]) / s
    elif m[1, 1] > m[2, 2]:
        s = math.sqrt(1.0 + m[1, 1] - m[0, 0] - m[2, 2]) * 2
        w, x, y, z = (m[0, 2] - m[2, 0]) / s, (m[0, 1] + m[1, 0]) / s, 0.25 * s, (m[1, 2] + m[2, 1]) / s
    else:
        s = math.sqrt(1.0 + m[2, 2] - m[0, 0] - m[1, 1]) * 2
        w, x, y, z = (m[1, 0] - m[0, 1]) / s, (m[0, 2] + m[2, 0]) / s, (m[1, 2] + m[2, 1]) / s, 0.25 * s
    q = np.array([w, x, y, z])
    q /= np.linalg.norm(q)
    return tuple(float(c) for c in q)  # type: ignore[return-value]


def pad_down(roll_deg: float = 0.0, yaw_deg: float = 0.0) -> tuple[float, float, float, float]:
    """A finger over the floor, pad facing down (z axis = -z world).  With yaw 0 its right (x) is +x
    world and it points toward -y world.  ``roll_deg`` > 0 turns the pad's right side down toward the
    surface (eq. 4's θ = roll); ``yaw_deg`` turns the finger about the vertical."""
    r = math.radians(roll_deg)
    a = math.radians(yaw_deg)
    X0 = np.array([math.cos(a), math.sin(a), 0.0])
    Z0 = np.array([0.0, 0.0, -1.0])
    Y0 = np.cross(Z0, X0)
    X = math.cos(r) * X0 + math.sin(r) * Z0
    Z = -math.sin(r) * X0 + math.cos(r) * Z0
    return quat_from_axes(X, Y0, Z)


PAD_DOWN = pad_down()


def line_poses(
    t0: float,
    start: tuple[float, float, float],
    end: tuple[float, float, float],
    speed_mm_s: float,
    rate_hz: float,
    q: tuple[float, float, float, float] = PAD_DOWN,
) -> list[tuple[float, np.ndarray, tuple[float, float, float, float]]]:
    """Samples of a straight move at constant speed (the end point included)."""
    a = np.array(start, dtype=float)
    b = np.array(end, dtype=float)
    dist = float(np.linalg.norm(b - a))
    dur = dist / speed_mm_s if speed_mm_s > 0 else 0.0
    n = max(1, int(math.ceil(dur * rate_hz)))
    return [(t0 + dur * i / n, a + (b - a) * (i / n), q) for i in range(n + 1)]


def hold_poses(
    t0: float,
    at: tuple[float, float, float],
    duration_s: float,
    rate_hz: float,
    q: tuple[float, float, float, float] = PAD_DOWN,
) -> list[tuple[float, np.ndarray, tuple[float, float, float, float]]]:
    n = int(round(duration_s * rate_hz))
    p = np.array(at, dtype=float)
    return [(t0 + (i + 1) / rate_hz, p.copy(), q) for i in range(n)]
