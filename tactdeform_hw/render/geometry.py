"""Shared value types of the renderer's geometry: what a surface query answers, and what an object is.

Units and frames
----------------
Every length is in millimetres, every point in world coordinates.  The world follows the VR engines the
studies ran in: x to the participant's right, y up, z forward (away from the participant); the eye is at
the origin.  The algebra is the ordinary one (``z = x × y`` numerically), so the finger frame of
:mod:`.tracking` — x to the right, y toward the fingertip, z out of the pad toward what it touches — is
reached from the world by a proper rotation.

The two helpers at the end, :func:`contact_theta_deg` and :func:`edge_angle_in_finger_deg`, turn a query
into the finger-frame angles the patterns are chosen from; they live here so that the synthetic
trajectories and the renderer measure those angles the same way.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Protocol, runtime_checkable

import numpy as np

from ..errors import ConfigurationError

FEATURES: tuple[str, ...] = ("face", "edge", "corner")
"""Local features under a contact, in the order of how much of the surface meets there."""

TEXTURE_LEVELS: tuple[int, ...] = (0, 1, 2)
"""k_texture of the paper: 0 smooth (static pattern), 1 rough (2 mm period), 2 rougher (4 mm period)."""

TEXTURE_NAMES: dict[int, str] = {0: "smooth", 1: "rough", 2: "rougher"}

DEFAULT_FEATURE_BAND_MM = 3.0
"""How close (along the surface) an edge or corner must be to the contact point to be the feature felt.

The 6 × 6 array spans 10 mm centre to centre, so an edge within 3 mm of the contact point runs under the
central electrodes; farther out it would only touch the outer ring.  A parameter of every object."""


def check_texture_level(field: str, value: object) -> int:
    """Return a texture level (0, 1 or 2) or raise naming the field."""
    if (
        isinstance(value, bool)
        or not isinstance(value, (int, np.integer))
        or int(value) not in TEXTURE_LEVELS
    ):
        raise ConfigurationError(
            f"{field}={value!r} is not a texture level: 0 (smooth), 1 (rough) or 2 (rougher)"
        )
    return int(value)


def check_band_mm(field: str, value: object) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float, np.floating, np.integer)):
        raise ConfigurationError(f"{field}={value!r} must be a non-negative number of millimetres")
    fvalue = float(value)
    if not math.isfinite(fvalue) or fvalue < 0:
        raise ConfigurationError(f"{field}={value!r} must be a non-negative number of millimetres")
    return fvalue


@dataclass(frozen=True, eq=False)
class SurfaceQuery:
    """The surface nearest to a point, as the renderer needs it.

    ``signed_distance_mm`` is positive outside and negative inside (penetration depth is its negative).
    ``normal`` is the outward unit normal that governs motion relative to the surface: the gradient of the
    signed distance away from the surface (so that the approach speed is the rate at which the distance
    shrinks), and the face / edge / vertex normal on it.  ``edge_direction`` is a unit vector along the edge
    in world coordinates when ``feature == "edge"``, otherwise ``None``.  The arrays belong to the caller
    but are shared with nothing; treat them as read-only values.
    """

    object_name: str
    signed_distance_mm: float
    closest_point_mm: np.ndarray
    normal: np.ndarray
    feature: str
    edge_direction: np.ndarray | None
    texture_level: int
    region: str | None = None
    """Name of the texture region the closest point falls in, ``None`` for the object's own level."""

    @property
    def depth_mm(self) -> float:
        """Penetration depth (≥ 0): how far the point is inside the solid."""
        return max(0.0, -self.signed_distance_mm)

    @property
    def in_contact(self) -> bool:
        """True on or inside the surface."""
        return self.signed_distance_mm <= 0.0


@runtime_checkable
class SceneObject(Protocol):
    """A solid the finger can touch.

    ``query`` answers for one point (the pad centre); ``contains`` answers for many at once (the
    electrode positions of contact-area mapping), which is why it is vectorised.
    """

    name: str

    def query(self, point_mm: np.ndarray) -> SurfaceQuery: ...

    def contains(self, points_mm: np.ndarray) -> np.ndarray: ...


@dataclass(frozen=True, eq=False)
class SurfaceSite:
    """A representative place on an object for a feature: where a study task touches it.

    Trajectories are built from sites: the approach runs along ``normal`` into ``point_mm``; an edge site
    carries the edge direction so the finger can be turned to show the edge in a given orientation.
    """

    object_name: str
    feature: str
    point_mm: np.ndarray
    normal: np.ndarray
    edge_direction: np.ndarray | None = None
    texture_level: int = 0


@dataclass(frozen=True)
class TextureRegion:
    """A texture level over the part of an object's surface inside an axis-aligned world box.

    The closest point of a query is tested against the regions in order; the first box holding it gives
    the level, otherwise the object's own level applies.  Boxes are simple to write in a scene file and
    cover the study's cases (a textured top face, one half of a surface, a whole object).
    """

    lo_mm: tuple[float, ...]
    hi_mm: tuple[float, ...]
    level: int
    name: str = ""

    def __post_init__(self) -> None:
        lo = tuple(float(v) for v in self.lo_mm)
        hi = tuple(float(v) for v in self.hi_mm)
        if len(lo) != 3 or len(hi) != 3:
            raise ConfigurationError(f"texture region {self.name!r}: lo_mm and hi_mm need 3 values each")
        if not all(math.isfinite(v) for v in lo + hi) or any(a > b for a, b in zip(lo, hi)):
            raise ConfigurationError(
                f"texture region {self.name!r}: lo_mm={lo} must be finite and ≤ hi_mm={hi} on every axis"
            )
        object.__setattr__(self, "lo_mm", lo)
        object.__setattr__(self, "hi_mm", hi)
        object.__setattr__(
            self, "level", check_texture_level(f"texture region {self.name!r} level", self.level)
        )


class RegionLookup:
    """Compiled texture regions of one object.  Built only when a scene has a textured surface."""

    __slots__ = ("_lo", "_hi", "_levels", "_names")

    def __init__(self, regions: tuple[TextureRegion, ...]) -> None:
        self._lo = np.array([r.lo_mm for r in regions], dtype=float) - 1e-6
        self._hi = np.array([r.hi_mm for r in regions], dtype=float) + 1e-6
        self._levels = [r.level for r in regions]
        self._names = [r.name or f"region{i}" for i, r in enumerate(regions)]

    def lookup(self, point_mm: np.ndarray) -> tuple[int, str] | None:
        inside = np.all((point_mm >= self._lo) & (point_mm <= self._hi), axis=1)
        hits = np.flatnonzero(inside)
        if hits.size == 0:
            return None
        i = int(hits[0])
        return self._levels[i], self._names[i]


@dataclass(frozen=True, eq=False)
class PadPlane:
    """The pad's electrodes as points of one plane, what a plane test (``contains_on_pad``) is asked
    about: ``centre_mm + u·x_axis + v·y_axis`` for the rows (u, v) of ``offsets_mm`` (mm).  One value, so
    the scene and each object that answers for a plane at once read the same points the same way."""

    centre_mm: np.ndarray
    x_axis: np.ndarray
    y_axis: np.ndarray
    offsets_mm: np.ndarray

    @classmethod
    def of(cls, centre_mm: object, x_axis: object, y_axis: object, offsets_mm: object) -> PadPlane:
        """The plane from anything array-like, as float arrays (an ``offsets_mm`` array already of floats
        is kept as it is: a mesh keeps what it derives from it by its identity)."""
        c, x, y, off = (np.asarray(v, dtype=float) for v in (centre_mm, x_axis, y_axis, offsets_mm))
        return cls(c, x, y, off)

    def points(self) -> np.ndarray:
        """(N, 3) the electrodes' positions in mm."""
        off = self.offsets_mm
        pts: np.ndarray = self.centre_mm + off[:, 0:1] * self.x_axis + off[:, 1:2] * self.y_axis
        return pts


def as_point(point_mm: object, field: str = "point_mm") -> np.ndarray:
    """A finite (3,) float array, or a clear error: NaN never reaches the distance code."""
    p = np.asarray(point_mm, dtype=float)
    if p.shape != (3,):
        raise ConfigurationError(f"{field} must have shape (3,), got {p.shape}")
    if not all(map(math.isfinite, p.tolist())):  # per query: cheaper than a numpy reduction on 3 values
        raise ConfigurationError(f"{field}={p.tolist()} must be finite")
    return p


def as_points(points_mm: object, field: str = "points_mm") -> np.ndarray:
    p = np.asarray(points_mm, dtype=float)
    if p.ndim != 2 or p.shape[1] != 3:
        raise ConfigurationError(f"{field} must have shape (N, 3), got {p.shape}")
    if not np.isfinite(p).all():
        raise ConfigurationError(f"{field} must be finite")
    return p


def _finger_components(world_from_finger: np.ndarray, v: np.ndarray, a: int, b: int) -> tuple[float, float]:
    """Components ``a`` and ``b`` (0 x, 1 y, 2 z) of the world vector ``v`` in the finger frame: dot
    products with those columns of the rotation, written out so every caller sums in the same order."""
    r = np.asarray(world_from_finger, dtype=float)
    w = np.asarray(v, dtype=float)
    return (
        float(r[0, a] * w[0] + r[1, a] * w[1] + r[2, a] * w[2]),
        float(r[0, b] * w[0] + r[1, b] * w[1] + r[2, b] * w[2]),
    )


def contact_theta_deg(world_from_finger: np.ndarray, normal: np.ndarray) -> float:
    """θ of eq. 4: the angle at which the surface meets the pad, left negative, right positive.

    *Interpretation.*  The paper takes the angle between the ray from the pad centre to the contact point
    and the surface tangent, projected onto the horizontal plane.  When a pad tilted against a surface
    touches it, the contact point lies on the pad on the side that meets the surface first, so that ray
    runs along the pad and its angle to the tangent equals the tilt between pad and surface.  We measure
    that tilt in the finger's x–z plane (left–right and out of the pad: the plane across the finger that
    contains the left–right shift of the pattern):

        n_f = R^T n   (surface normal in the finger frame)
        θ   = atan2(−n_f.x, −n_f.z)   clipped to [−90°, 90°]

    A pad pressed flat gives 0°; a pad rolled so that its right side meets the surface gives θ > 0 and
    the contact point on the right of the pad.  A surface facing away from the pad (−n_f.z < 0) clips to
    ±90°.  ``world_from_finger`` is the pose's 3 × 3 rotation.
    """
    nx, nz = _finger_components(world_from_finger, normal, 0, 2)
    if nx == 0.0 and nz == 0.0:
        return 0.0
    theta = math.degrees(math.atan2(-nx, -nz))
    return max(-90.0, min(90.0, theta))


def edge_angle_in_finger_deg(world_from_finger: np.ndarray, edge_direction: np.ndarray) -> float:
    """Orientation of an edge as seen on the pad, in [0°, 180°): 0 horizontal (along finger x), 90 vertical
    (along the finger), 45 the ``/`` diagonal, 135 the ``\\`` diagonal.

    The edge is projected onto the pad plane (finger x–y); an edge pointing straight out of the pad has
    no orientation there and reads 0°.
    """
    ex, ey = _finger_components(world_from_finger, edge_direction, 0, 1)
    if ex == 0.0 and ey == 0.0:
        return 0.0
    angle = math.degrees(math.atan2(ey, ex)) % 180.0
    return 0.0 if angle >= 180.0 else angle
