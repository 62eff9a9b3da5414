"""Analytic solids: the sphere and the box (the cube of Phase 2, the bars and slabs of Tasks 1–3).

Their signed distance, closest point, normal and local feature are closed-form, so a query costs a few
microseconds of scalar arithmetic; numpy is used only to hand the results back as arrays.

Feature of a box contact
------------------------
For the closest point q on the box (in box coordinates, half sizes h), s_i = h_i − |q_i| is its distance
to the pair of planes bounding axis i (0 for the axis of the face q lies on).  q is within
``feature_band_mm`` of a corner when √(Σ s_i²) ≤ band (that is its distance to the nearest corner), and
then reads as a corner; otherwise within the band of an edge when a second s_i ≤ band (the edge runs
along the remaining axis); otherwise it is on a face.  These are the distances a mesh of the same box
measures, so the analytic and the mesh answers agree.  A point outside the box beside an edge projects
onto the edge itself and reads as that edge; beside a corner, as the corner.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import TYPE_CHECKING, TypedDict

import numpy as np

from ..errors import ConfigurationError
from .geometry import (
    DEFAULT_FEATURE_BAND_MM,
    RegionLookup,
    SurfaceQuery,
    SurfaceSite,
    TextureRegion,
    as_point,
    as_points,
    check_band_mm,
    check_texture_level,
)

if TYPE_CHECKING:
    from typing_extensions import Unpack  # typing's own from Python 3.11


def _check_vec3(field: str, value: object) -> np.ndarray:
    v = np.asarray(value, dtype=float)
    if v.shape != (3,) or not np.isfinite(v).all():
        raise ConfigurationError(f"{field}={value!r} must be 3 finite numbers")
    return v


def _check_rotation(field: str, value: object | None) -> np.ndarray | None:
    """A proper 3 × 3 rotation (world from object), or ``None`` for none."""
    if value is None:
        return None
    r = np.asarray(value, dtype=float)
    if r.shape != (3, 3) or not np.isfinite(r).all():
        raise ConfigurationError(f"{field} must be a finite 3 × 3 rotation matrix")
    if not np.allclose(r.T @ r, np.eye(3), atol=1e-6) or np.linalg.det(r) < 0:
        raise ConfigurationError(f"{field} is not a proper rotation (orthonormal, determinant +1)")
    if np.allclose(r, np.eye(3), atol=1e-12):
        return None
    return r


class SurfaceOptions(TypedDict, total=False):
    """The surface options every kind of object takes by keyword (defaults and checks:
    :class:`PlacedSolid`): its texture level, its textured regions, how near an edge or a corner a contact
    reads as one (``feature_band_mm``), and whether features are classified at all."""

    texture_level: int
    texture_regions: Sequence[TextureRegion]
    feature_band_mm: float
    classify_features: bool


class PlacedSolid:
    """What every object shares: a name, a pose in the world, a texture level and its regions.  The
    surface options (:class:`SurfaceOptions`) have their defaults here, so every kind of object takes the
    same ones."""

    def __init__(
        self,
        name: str,
        center_mm: Sequence[float],
        rotation: object | None,
        *,
        texture_level: int = 0,
        texture_regions: Sequence[TextureRegion] = (),
        feature_band_mm: float = DEFAULT_FEATURE_BAND_MM,
        classify_features: bool = True,
    ) -> None:
        if not isinstance(name, str) or not name:
            raise ConfigurationError(f"object name={name!r} must be a non-empty string")
        self.name = name
        self.center_mm = _check_vec3(f"{name}.center_mm", center_mm)
        self.rotation = _check_rotation(f"{name}.rotation", rotation)
        self.texture_level = check_texture_level(f"{name}.texture_level", texture_level)
        self.texture_regions = tuple(texture_regions)
        self.feature_band_mm = check_band_mm(f"{name}.feature_band_mm", feature_band_mm)
        self.classify_features = bool(classify_features)
        # Region lookup is compiled only when a region is textured; a smooth object keeps none.
        self._regions: RegionLookup | None = (
            RegionLookup(self.texture_regions) if any(r.level for r in self.texture_regions) else None
        )
        self._cx, self._cy, self._cz = (float(v) for v in self.center_mm)
        rot = self.rotation if self.rotation is not None else np.eye(3)
        self._r = [[float(rot[i, j]) for j in range(3)] for i in range(3)]
        self._rotated = self.rotation is not None

    @property
    def has_texture_lookup(self) -> bool:
        """Whether per-region texture machinery was built for this object."""
        return self._regions is not None

    def max_texture_level(self) -> int:
        return max([self.texture_level, *(r.level for r in self.texture_regions)])

    def _texture_at(self, point: np.ndarray) -> tuple[int, str | None]:
        if self._regions is not None:
            hit = self._regions.lookup(point)
            if hit is not None:
                return hit
        return self.texture_level, None

    def _to_local(self, p: np.ndarray) -> tuple[float, float, float]:
        dx = float(p[0]) - self._cx
        dy = float(p[1]) - self._cy
        dz = float(p[2]) - self._cz
        if not self._rotated:
            return dx, dy, dz
        r = self._r
        return (
            r[0][0] * dx + r[1][0] * dy + r[2][0] * dz,
            r[0][1] * dx + r[1][1] * dy + r[2][1] * dz,
            r[0][2] * dx + r[1][2] * dy + r[2][2] * dz,
        )

    def _dir_to_world(self, x: float, y: float, z: float) -> np.ndarray:
        if not self._rotated:
            return np.array((x, y, z))
        r = self._r
        return np.array(
            (
                r[0][0] * x + r[0][1] * y + r[0][2] * z,
                r[1][0] * x + r[1][1] * y + r[1][2] * z,
                r[2][0] * x + r[2][1] * y + r[2][2] * z,
            )
        )

    def _point_to_world(self, x: float, y: float, z: float) -> np.ndarray:
        w = self._dir_to_world(x, y, z)
        w[0] += self._cx
        w[1] += self._cy
        w[2] += self._cz
        return w

    def _points_to_local(self, points: np.ndarray) -> np.ndarray:
        d = points - self.center_mm
        out: np.ndarray = d @ self.rotation if self.rotation is not None else d
        return out


class Sphere(PlacedSolid):
    """A sphere: every contact is a face.  ``surface``: :class:`SurfaceOptions`."""

    kind = "sphere"

    def __init__(
        self,
        name: str,
        radius_mm: float,
        center_mm: Sequence[float] = (0.0, 0.0, 0.0),
        **surface: Unpack[SurfaceOptions],
    ) -> None:
        super().__init__(name, center_mm, None, **surface)
        r = float(radius_mm)
        if not math.isfinite(r) or r <= 0:
            raise ConfigurationError(f"{name}.radius_mm={radius_mm!r} must be a positive finite number")
        self.radius_mm = r

    @property
    def bounds_mm(self) -> tuple[np.ndarray, np.ndarray]:
        return self.center_mm - self.radius_mm, self.center_mm + self.radius_mm

    def query(self, point_mm: np.ndarray) -> SurfaceQuery:
        p = as_point(point_mm)
        dx, dy, dz = self._to_local(p)
        dist = math.sqrt(dx * dx + dy * dy + dz * dz)
        if dist > 0.0:
            nx, ny, nz = dx / dist, dy / dist, dz / dist
        else:  # the centre: every direction is nearest; pick "up" so the answer is defined
            nx, ny, nz = 0.0, 1.0, 0.0
        rad = self.radius_mm
        closest = np.array((self._cx + nx * rad, self._cy + ny * rad, self._cz + nz * rad))
        level, region = self._texture_at(closest)
        return SurfaceQuery(
            self.name, dist - rad, closest, np.array((nx, ny, nz)), "face", None, level, region
        )

    def contains(self, points_mm: np.ndarray) -> np.ndarray:
        p = as_points(points_mm)
        d = p - self.center_mm
        inside: np.ndarray = np.einsum("ij,ij->i", d, d) <= self.radius_mm * self.radius_mm
        return inside

    def sites(self, feature: str, toward: np.ndarray | None = None) -> list[SurfaceSite]:
        """26 face sites (toward the faces, edges and corners of a cube around it).  A sphere has no
        edges or corners."""
        if feature != "face":
            return []
        out = []
        for i in (-1.0, 0.0, 1.0):
            for j in (-1.0, 0.0, 1.0):
                for k in (-1.0, 0.0, 1.0):
                    if i == j == k == 0.0:
                        continue
                    n = np.array((i, j, k)) / math.sqrt(i * i + j * j + k * k)
                    point = self.center_mm + self.radius_mm * n
                    out.append(SurfaceSite(self.name, "face", point, n, None, self._texture_at(point)[0]))
        return out


class Box(PlacedSolid):
    """A rectangular box (the cube when all sizes are equal), optionally rotated.  ``surface``:
    :class:`SurfaceOptions`."""

    kind = "box"

    def __init__(
        self,
        name: str,
        size_mm: float | Sequence[float],
        center_mm: Sequence[float] = (0.0, 0.0, 0.0),
        *,
        rotation: object | None = None,
        **surface: Unpack[SurfaceOptions],
    ) -> None:
        super().__init__(name, center_mm, rotation, **surface)
        size = np.broadcast_to(np.asarray(size_mm, dtype=float), (3,)).copy()
        if not np.isfinite(size).all() or (size <= 0).any():
            raise ConfigurationError(f"{name}.size_mm={size_mm!r} must be positive finite lengths")
        self.size_mm = size
        self._h = tuple(float(v) / 2.0 for v in size)

    @property
    def bounds_mm(self) -> tuple[np.ndarray, np.ndarray]:
        half = np.array(self._h)
        if self.rotation is not None:
            half = np.abs(self.rotation) @ half
        return self.center_mm - half, self.center_mm + half

    def query(self, point_mm: np.ndarray) -> SurfaceQuery:
        p = as_point(point_mm)
        local = self._to_local(p)
        h = self._h
        q = [abs(local[i]) - h[i] for i in range(3)]
        ox, oy, oz = max(q[0], 0.0), max(q[1], 0.0), max(q[2], 0.0)
        outside = math.sqrt(ox * ox + oy * oy + oz * oz)
        if outside > 0.0:
            cl = [min(max(local[i], -h[i]), h[i]) for i in range(3)]
            n = [(local[i] - cl[i]) / outside for i in range(3)]
            sd = outside
        else:
            # On or inside: the nearest face is the axis with the largest (least negative) q.
            a = 0 if q[0] >= q[1] and q[0] >= q[2] else (1 if q[1] >= q[2] else 2)
            sign = 1.0 if local[a] >= 0.0 else -1.0
            cl = list(local)
            cl[a] = sign * h[a]
            n = [0.0, 0.0, 0.0]
            n[a] = sign
            sd = q[a]
        feature = "face"
        edge_dir = None
        if self.classify_features:
            # a point exactly on the band's border must classify the same however the box is turned: the
            # rotation's rounding (~1e-14 mm) may not move it across
            band = self.feature_band_mm + 1e-9
            s = [h[i] - abs(cl[i]) for i in range(3)]
            near = [s[i] <= band for i in range(3)]
            count = near[0] + near[1] + near[2]
            if s[0] * s[0] + s[1] * s[1] + s[2] * s[2] <= band * band:
                feature = "corner"
            elif count >= 2:
                feature = "edge"
                free = 0 if s[0] >= s[1] and s[0] >= s[2] else (1 if s[1] >= s[2] else 2)
                axis = [0.0, 0.0, 0.0]
                axis[free] = 1.0
                edge_dir = self._dir_to_world(*axis)
        closest = self._point_to_world(*cl)
        level, region = self._texture_at(closest)
        return SurfaceQuery(self.name, sd, closest, self._dir_to_world(*n), feature, edge_dir, level, region)

    def contains(self, points_mm: np.ndarray) -> np.ndarray:
        local = self._points_to_local(as_points(points_mm))
        inside: np.ndarray = np.all(np.abs(local) <= np.array(self._h), axis=1)
        return inside

    def sites(self, feature: str, toward: np.ndarray | None = None) -> list[SurfaceSite]:
        """Face centres (and quarter centres), edge midpoints (normal along the bisector) or corners, in world
        coordinates."""
        h = np.array(self._h)
        rot = self.rotation if self.rotation is not None else np.eye(3)
        out: list[SurfaceSite] = []
        signs = (-1.0, 1.0)
        if feature == "face":
            # Each face's centre, then the centres of its four quarters.
            for a in range(3):
                b, c = (i for i in range(3) if i != a)
                for s in signs:
                    n_local = np.zeros(3)
                    n_local[a] = s
                    for u, v in ((0.0, 0.0), (-0.5, -0.5), (0.5, -0.5), (-0.5, 0.5), (0.5, 0.5)):
                        offset = n_local * h
                        offset[b] += u * h[b]
                        offset[c] += v * h[c]
                        point = self.center_mm + rot @ offset
                        out.append(
                            SurfaceSite(
                                self.name, "face", point, rot @ n_local, None, self._texture_at(point)[0]
                            )
                        )
        elif feature == "edge":
            for free in range(3):
                a, b = (i for i in range(3) if i != free)
                for sa in signs:
                    for sb in signs:
                        d_local = np.zeros(3)
                        d_local[a], d_local[b] = sa, sb
                        point = self.center_mm + rot @ (d_local * h)
                        normal = rot @ (d_local / math.sqrt(2.0))
                        axis = np.zeros(3)
                        axis[free] = 1.0
                        out.append(
                            SurfaceSite(
                                self.name, "edge", point, normal, rot @ axis, self._texture_at(point)[0]
                            )
                        )
        elif feature == "corner":
            for sx in signs:
                for sy in signs:
                    for sz in signs:
                        d_local = np.array((sx, sy, sz))
                        point = self.center_mm + rot @ (d_local * h)
                        normal = rot @ (d_local / math.sqrt(3.0))
                        out.append(
                            SurfaceSite(self.name, "corner", point, normal, None, self._texture_at(point)[0])
                        )
        return out
