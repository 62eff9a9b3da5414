"""Synthetic finger-pose streams that reproduce the study tasks on any scene.

========================  ===================================================================================
``approach-face``         from ≥ 8 cm away along the normal of the face best facing the participant, into
                          contact and a few mm of penetration, dwell, withdraw
``approach-edge-h/-v``    the same onto an edge, the finger turned so that the edge lies along the pad's x
``approach-edge-d1/-d2``  axis (h), along the finger (v), or on the ``/`` (d1, 45°) or ``\\`` (d2, 135°)
                          diagonal of the pad (see :func:`.geometry.edge_angle_in_finger_deg`)
``approach-corner``       onto a corner along its bisecting normal
``contact-<level>``       a stationary press on a face with the pad rolled so that θ (eq. 4, see
                          :func:`.geometry.contact_theta_deg`) is −60° (steep-left), −15° (shallow-left),
                          +15° (shallow-right) or +60° (steep-right): the centre of each level
``slide-<texture>``       a rightward stroke over an upward-facing surface of texture level smooth (0),
                          rough (1) or rougher (2), palm down, fingertip forward
``explore``               free exploration of every object: touches on the faces best facing the
                          participant, strokes that follow the surface in changing directions, lift-offs
========================  ===================================================================================

``speed_mm_s`` is the speed of the motion that defines the task (the approach, the stroke, the
exploration); lead-ins and withdrawals run at ``approach_speed_mm_s``.  Tremor (a sinusoid of
``tremor_mm`` amplitude at ``tremor_hz``, 8–12 Hz drawn from the seed when not given) and white
position/orientation noise are added last and are reproducible from ``seed``.

A slide needs a surface of its texture level: :func:`scene_for_trajectory` returns the scene unchanged
when it has one and otherwise a copy whose objects carry that level.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from ..errors import ConfigurationError, LimitError
from .geometry import TEXTURE_NAMES, SurfaceSite
from .scene import Scene
from .tracking import (
    Pose,
    frame_from_z_y,
    matrix_to_quat,
    quat_from_axis_angle,
    quat_multiply,
    quat_to_matrix,
    slerp,
)

APPROACH_EDGE_ANGLES_DEG: dict[str, float] = {"h": 0.0, "v": 90.0, "d1": 45.0, "d2": 135.0}
CONTACT_THETA_DEG: dict[str, float] = {
    "steep-left": -60.0,
    "shallow-left": -15.0,
    "shallow-right": 15.0,
    "steep-right": 60.0,
}
SLIDE_LEVELS: dict[str, int] = {"smooth": 0, "rough": 1, "rougher": 2}

#: The study tasks' trajectories (Task 1 approaches, Task 2 contacts, Task 3 slides, Phase 2 exploration).
TRAJECTORIES: tuple[str, ...] = (
    "approach-face",
    "approach-edge-h",
    "approach-edge-v",
    "approach-edge-d1",
    "approach-edge-d2",
    "approach-corner",
    "contact-steep-left",
    "contact-shallow-left",
    "contact-shallow-right",
    "contact-steep-right",
    "slide-smooth",
    "slide-rough",
    "slide-rougher",
    "explore",
)

DEFAULT_SPEED_MM_S: dict[str, float] = {"approach": 100.0, "contact": 100.0, "slide": 20.0, "explore": 40.0}
"""Defaults per task family; 20 mm/s is the paper's worked sliding example (rough shifts at 10 Hz)."""

MAX_SAMPLES = 2_000_000
EYE_MM = np.zeros(3)
UP = np.array((0.0, 1.0, 0.0))
FORWARD = np.array((0.0, 0.0, 1.0))
RIGHT = np.array((1.0, 0.0, 0.0))


def _family(name: str) -> str:
    return name.split("-", 1)[0]


def describe(name: str) -> str:
    """One line on what a trajectory does (for ``--help`` and listings)."""
    if name.startswith("approach-edge-"):
        o = name.rsplit("-", 1)[1]
        return f"approach an edge shown at {APPROACH_EDGE_ANGLES_DEG[o]:.0f}° on the pad"
    if name == "approach-face":
        return "approach the face best facing the participant"
    if name == "approach-corner":
        return "approach a corner along its bisector"
    if name.startswith("contact-"):
        level = name.split("-", 1)[1]
        return f"stationary press with θ = {CONTACT_THETA_DEG[level]:+.0f}° ({level})"
    if name.startswith("slide-"):
        return f"rightward stroke over a {name.split('-', 1)[1]} surface"
    if name == "explore":
        return "free exploration of every object"
    raise ConfigurationError(f"unknown trajectory {name!r}; choose from {', '.join(TRAJECTORIES)}")


# --- keyframed motion ----------------------------------------------------------------------------------


class _Timeline:
    """Keyframes (time, position, orientation); sampled at the tracker rate afterwards."""

    def __init__(self, position: np.ndarray, rotation: np.ndarray) -> None:
        self.t = [0.0]
        self.p = [np.asarray(position, dtype=float)]
        self.q = [matrix_to_quat(rotation)]

    @property
    def position(self) -> np.ndarray:
        return self.p[-1]

    def _add(self, dt: float, position: np.ndarray, q: np.ndarray) -> None:
        if np.dot(q, self.q[-1]) < 0:
            q = -q
        self.t.append(self.t[-1] + dt)
        self.p.append(np.asarray(position, dtype=float))
        self.q.append(q)

    def hold(self, duration_s: float) -> None:
        if duration_s > 0:
            self._add(duration_s, self.p[-1], self.q[-1])

    def move(self, position: np.ndarray, speed_mm_s: float, rotation: np.ndarray | None = None) -> None:
        q = self.q[-1] if rotation is None else matrix_to_quat(rotation)
        dist = float(np.linalg.norm(np.asarray(position) - self.p[-1]))
        turn = 2.0 * math.degrees(math.acos(min(1.0, abs(float(np.dot(q, self.q[-1]))))))
        # Pure turns take the time of turning at 180°/s.
        dt = max(dist / speed_mm_s, turn / 180.0)
        if dt > 0:
            self._add(dt, position, q)

    def path(
        self, positions: Sequence[np.ndarray] | np.ndarray, rotations: Sequence[np.ndarray], speed_mm_s: float
    ) -> None:
        for position, rotation in zip(positions, rotations):
            self.move(position, speed_mm_s, rotation)

    def sample(self, rate_hz: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        t = np.array(self.t)
        n = int(math.floor(t[-1] * rate_hz + 1e-9)) + 1
        if n > MAX_SAMPLES:
            raise LimitError(
                "trajectory samples", n, f"at most {MAX_SAMPLES} (raise the speed or lower the rate)"
            )
        ts = np.arange(n) / rate_hz
        pos = np.array(self.p)
        quats = np.array(self.q)
        idx = np.clip(np.searchsorted(t, ts, side="right") - 1, 0, len(t) - 2)
        span = t[idx + 1] - t[idx]
        u = np.where(span > 0, (ts - t[idx]) / np.where(span > 0, span, 1.0), 1.0)
        u = np.clip(u, 0.0, 1.0)
        p = pos[idx] + u[:, None] * (pos[idx + 1] - pos[idx])
        q = np.array([slerp(quats[i], quats[i + 1], float(w)) for i, w in zip(idx.tolist(), u.tolist())])
        return ts, p, q


# --- sites ---------------------------------------------------------------------------------------------


def _object_sites(scene: Scene, feature: str, toward: np.ndarray | None = None) -> list[SurfaceSite]:
    out: list[SurfaceSite] = []
    for obj in scene.objects:
        sites = getattr(obj, "sites", None)
        if sites is not None:
            out.extend(sites(feature, toward))
    return out


def refine_site(scene: Scene, site: SurfaceSite, penetration_mm: float) -> SurfaceSite:
    """The site as the renderer will see it with the pad ``penetration_mm`` inside: the normal (and edge
    direction) of the query there, so that a frame built on it matches what is measured in contact."""
    q = scene.query(site.point_mm - penetration_mm * site.normal)
    if q.object_name != site.object_name or q.feature != site.feature:
        return site
    edge = (
        q.edge_direction if site.feature == "edge" and q.edge_direction is not None else site.edge_direction
    )
    if site.feature != "face":
        return SurfaceSite(
            site.object_name, site.feature, site.point_mm, site.normal, edge, site.texture_level
        )
    return SurfaceSite(site.object_name, site.feature, q.closest_point_mm, q.normal, edge, site.texture_level)


def _clear_approach(scene: Scene, site: SurfaceSite, distance_mm: float) -> bool:
    """The site reads as its feature from just outside, and nothing else is in the way of the approach."""
    q = scene.query(site.point_mm + 0.5 * site.normal)
    if q.object_name != site.object_name or q.feature != site.feature:
        return False
    for d in (5.0, 20.0, 0.5 * distance_mm, distance_mm):
        if scene.query(site.point_mm + d * site.normal).signed_distance_mm < 0.8 * d:
            return False
    return True


def _facing_score(site: SurfaceSite) -> float:
    to_eye = EYE_MM - site.point_mm
    return float(np.dot(site.normal, to_eye / np.linalg.norm(to_eye)))


def pick_site(
    scene: Scene,
    feature: str,
    *,
    distance_mm: float = 100.0,
    texture_level: int | None = None,
    upward: bool = False,
) -> SurfaceSite:
    """The site of ``feature`` that best faces the participant (or, with ``upward``, points up) and can
    be approached from ``distance_mm`` away without touching anything else."""
    sites = _object_sites(scene, feature, UP if upward else None)
    if texture_level is not None:
        sites = [s for s in sites if s.texture_level == texture_level]
    if upward:
        sites = [s for s in sites if float(np.dot(s.normal, UP)) > 0.7]
    key: Callable[[SurfaceSite], float] = (lambda s: float(np.dot(s.normal, UP))) if upward else _facing_score
    for site in sorted(sites, key=key, reverse=True):
        if _clear_approach(scene, site, distance_mm):
            return refine_site(scene, site, 3.0)
    what = feature if texture_level is None else f"{TEXTURE_NAMES[texture_level]} {feature}"
    raise ConfigurationError(
        f"scene {scene.name!r} has no {what}{' facing up' if upward else ''} that can be approached"
    )


# --- finger frames -------------------------------------------------------------------------------------


def _hint_up(normal: np.ndarray) -> np.ndarray:
    return UP if abs(float(np.dot(normal, UP))) < 0.95 else FORWARD


def press_frame(normal: np.ndarray) -> np.ndarray:
    """Pad facing the surface (z = −normal), fingertip as close to world up (or forward) as it can be."""
    return frame_from_z_y(-normal, _hint_up(normal))


def edge_frame(normal: np.ndarray, edge_direction: np.ndarray, angle_deg: float) -> np.ndarray:
    """Pad facing the surface with the edge at ``angle_deg`` from the pad's x axis."""
    z = -np.asarray(normal, dtype=float)
    psi = math.radians(angle_deg)
    best = None
    for sign in (1.0, -1.0):
        u = sign * np.asarray(edge_direction, dtype=float)
        u = u - np.dot(u, z) * z
        u /= np.linalg.norm(u)
        w = np.cross(z, u)
        x = math.cos(psi) * u - math.sin(psi) * w
        y = math.sin(psi) * u + math.cos(psi) * w
        score = float(np.dot(y, _hint_up(normal)))
        if best is None or score > best[0]:
            best = (score, np.column_stack((x, y, z)))
    assert best is not None
    return best[1]


def rolled_frame(normal: np.ndarray, theta_deg: float) -> np.ndarray:
    """Pad against the surface, rolled about the finger's axis so that θ of eq. 4 equals ``theta_deg``."""
    base = press_frame(normal)
    y = base[:, 1]
    a = -np.asarray(normal, dtype=float)
    t = np.cross(y, a)
    th = math.radians(theta_deg)
    z = math.cos(th) * a - math.sin(th) * t
    x = math.cos(th) * t + math.sin(th) * a
    return np.column_stack((x, y, z))


def slide_frame(normal: np.ndarray, direction: np.ndarray) -> np.ndarray:
    """Palm toward the surface, the stroke direction along the pad's x axis (rightward)."""
    z = -np.asarray(normal, dtype=float)
    x = np.asarray(direction, dtype=float) - np.dot(direction, z) * z
    x /= np.linalg.norm(x)
    return np.column_stack((x, np.cross(z, x), z))


# --- surface walking -----------------------------------------------------------------------------------


def walk_surface(
    scene: Scene,
    start: SurfaceSite,
    direction: np.ndarray,
    length_mm: float,
    step_mm: float = 1.0,
    stop: Callable[[np.ndarray, np.ndarray], bool] | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Points and normals of a path that follows the surface from ``start`` along ``direction`` (kept
    tangent at every step), so strokes run over curved and faceted objects alike.  ``stop(point,
    normal)`` ends the path early."""
    p = np.asarray(start.point_mm, dtype=float)
    n = np.asarray(start.normal, dtype=float)
    d = np.asarray(direction, dtype=float)
    d = d - np.dot(d, n) * n
    if np.linalg.norm(d) < 1e-9:
        raise ConfigurationError("stroke direction is along the surface normal")
    d /= np.linalg.norm(d)
    points, normals = [p], [n]
    steps = max(1, int(math.ceil(length_mm / step_mm)))
    for _ in range(steps):
        q = scene.query(p + step_mm * d + 0.25 * n)
        p, n_new = q.closest_point_mm, q.normal
        d_new = d - np.dot(d, n_new) * n_new
        if np.linalg.norm(d_new) > 1e-6:
            d = d_new / np.linalg.norm(d_new)
        n = n_new
        if stop is not None and stop(p, n):
            break
        points.append(p)
        normals.append(n)
    normals_arr = np.array(normals)
    # Meshes have noisy normals; a short moving average keeps the finger from wobbling.
    kernel = np.ones(5) / 5.0
    padded = np.pad(normals_arr, ((2, 2), (0, 0)), mode="edge")
    smooth = np.stack([np.convolve(padded[:, k], kernel, mode="valid") for k in range(3)], axis=1)
    smooth /= np.linalg.norm(smooth, axis=1)[:, None]
    return np.array(points), smooth


# --- the tasks -----------------------------------------------------------------------------------------


@dataclass(frozen=True)
class _Params:
    speed_mm_s: float
    approach_speed_mm_s: float
    start_distance_mm: float
    penetration_mm: float
    dwell_s: float
    withdraw: bool


def _approach(
    tl: _Timeline | None, site: SurfaceSite, rotation: np.ndarray, prm: _Params, dwell_s: float
) -> _Timeline:
    start = site.point_mm + prm.start_distance_mm * site.normal
    end = site.point_mm - prm.penetration_mm * site.normal
    if tl is None:
        tl = _Timeline(start, rotation)
        tl.hold(0.25)  # a still start: the renderer sees a settled pose before anything moves
    else:
        tl.move(start, prm.approach_speed_mm_s, rotation)
    tl.move(end, prm.speed_mm_s)
    tl.hold(dwell_s)
    if prm.withdraw:
        tl.move(start, prm.approach_speed_mm_s)
        tl.hold(0.25)
    return tl


def _approach_task(name: str, scene: Scene, prm: _Params) -> _Timeline:
    if name == "approach-face":
        site = pick_site(scene, "face", distance_mm=prm.start_distance_mm)
        return _approach(None, site, press_frame(site.normal), prm, prm.dwell_s)
    if name == "approach-corner":
        site = pick_site(scene, "corner", distance_mm=prm.start_distance_mm)
        return _approach(None, site, press_frame(site.normal), prm, prm.dwell_s)
    orientation = name.rsplit("-", 1)[1]
    site = pick_site(scene, "edge", distance_mm=prm.start_distance_mm)
    assert site.edge_direction is not None
    frame = edge_frame(site.normal, site.edge_direction, APPROACH_EDGE_ANGLES_DEG[orientation])
    return _approach(None, site, frame, prm, prm.dwell_s)


def _contact_task(name: str, scene: Scene, prm: _Params) -> _Timeline:
    theta = CONTACT_THETA_DEG[name.split("-", 1)[1]]
    site = pick_site(scene, "face", distance_mm=prm.start_distance_mm)
    # Stationary contact is the task: hold it long enough for the contact context to settle.
    return _approach(None, site, rolled_frame(site.normal, theta), prm, max(prm.dwell_s, 1.5))


def _stroke_direction(normal: np.ndarray) -> np.ndarray:
    d = RIGHT - np.dot(RIGHT, normal) * normal
    if np.linalg.norm(d) < 1e-6:
        d = FORWARD - np.dot(FORWARD, normal) * normal
    unit: np.ndarray = d / np.linalg.norm(d)
    return unit


def _stroke_length(scene: Scene, site: SurfaceSite, direction: np.ndarray, wanted_mm: float) -> float:
    """As much of ``wanted_mm`` as stays on the face the stroke starts on (centred on the site)."""
    lo, hi = scene.bounds_mm
    obj = scene.object(site.object_name)
    bounds = getattr(obj, "bounds_mm", (lo, hi))
    extent = float(np.abs(np.asarray(bounds[1]) - np.asarray(bounds[0])) @ np.abs(direction))
    return max(10.0, min(wanted_mm, 0.7 * extent))


def _slide_task(name: str, scene: Scene, prm: _Params) -> _Timeline:
    level = SLIDE_LEVELS[name.split("-", 1)[1]]
    site = pick_site(scene, "face", distance_mm=prm.start_distance_mm, texture_level=level, upward=True)
    direction = _stroke_direction(site.normal)
    length = _stroke_length(scene, site, direction, 100.0)
    back = SurfaceSite(site.object_name, "face", site.point_mm, site.normal, None, site.texture_level)
    # Start half a stroke to the left of the site and stroke rightward through it.
    pts_back, nrm_back = walk_surface(scene, back, -direction, length / 2.0)
    start = SurfaceSite(site.object_name, "face", pts_back[-1], nrm_back[-1], None, site.texture_level)
    pts, nrms = walk_surface(scene, start, direction, length)
    frames = [slide_frame(n, direction) for n in nrms]
    pads = pts - prm.penetration_mm * nrms
    lead = pts[0] + prm.start_distance_mm * nrms[0]
    tl = _Timeline(lead, frames[0])
    tl.hold(0.25)
    tl.move(pads[0], prm.approach_speed_mm_s)
    tl.hold(prm.dwell_s)
    tl.path(pads[1:], frames[1:], prm.speed_mm_s)
    tl.hold(0.3)
    if prm.withdraw:
        tl.move(pts[-1] + prm.start_distance_mm * nrms[-1], prm.approach_speed_mm_s)
        tl.hold(0.25)
    return tl


def _spread_sites(sites: list[SurfaceSite], count: int, min_gap_mm: float) -> list[SurfaceSite]:
    chosen: list[SurfaceSite] = []
    for s in sorted(sites, key=_facing_score, reverse=True):
        if _facing_score(s) < 0.5:  # explore what faces the participant; lifts then go toward them
            continue
        if all(np.linalg.norm(s.point_mm - c.point_mm) >= min_gap_mm for c in chosen):
            chosen.append(s)
        if len(chosen) == count:
            break
    return chosen


def _transit(
    tl: _Timeline, target: np.ndarray, rotation: np.ndarray, speed: float, centre: np.ndarray, radius: float
) -> None:
    """Move through free space to ``target``: out to a sphere around the object, along it, and in, so the
    path never cuts through the object; the orientation turns smoothly on the way."""
    start = tl.position
    q0, q1 = tl.q[-1], matrix_to_quat(rotation)
    a, b = start - centre, target - centre
    ra, rb = float(np.linalg.norm(a)), float(np.linalg.norm(b))
    ua, ub = a / max(ra, 1e-9), b / max(rb, 1e-9)
    r = max(radius, ra, rb)
    angle = math.acos(max(-1.0, min(1.0, float(np.dot(ua, ub)))))
    if angle > math.pi - 1e-3:  # opposite sides: go over the top
        ub_mid = _unit(np.cross(ua, np.cross(UP, ua))) if abs(float(np.dot(ua, UP))) < 0.99 else FORWARD
        dirs = [ua, ub_mid, ub]
    else:
        dirs = [ua, ub]
    arc: list[np.ndarray] = []
    for d0, d1 in zip(dirs[:-1], dirs[1:]):
        ang = math.acos(max(-1.0, min(1.0, float(np.dot(d0, d1)))))
        n = max(1, int(math.ceil(ang * r / 10.0)))
        for i in range(1, n + 1):
            u = i / n
            if ang < 1e-9:
                d = d1
            else:
                d = (math.sin((1 - u) * ang) * d0 + math.sin(u * ang) * d1) / math.sin(ang)
            arc.append(centre + r * d)
    waypoints = [centre + r * ua, *arc, target]
    for i, w in enumerate(waypoints, start=1):
        tl.move(w, speed, quat_to_matrix(slerp(q0, q1, i / len(waypoints))))
    del angle


def _explore_task(scene: Scene, prm: _Params) -> _Timeline:
    tl: _Timeline | None = None
    directions = (RIGHT, UP, -RIGHT, -UP)
    touches = 0
    last_normal = -FORWARD
    # Transits between touches go around a sphere enclosing the whole scene, so they cross nothing.
    lo, hi = scene.bounds_mm
    centre = (lo + hi) / 2.0
    safe_radius = float(np.linalg.norm(hi - lo)) / 2.0 + 40.0
    for obj in scene.objects:
        sites_of = getattr(obj, "sites", None)
        if sites_of is None:
            continue
        candidates = [s for s in sites_of("face") if _clear_approach(scene, s, 60.0)]
        for k, site in enumerate(_spread_sites(candidates, 3, 30.0)):
            direction = directions[(touches + k) % len(directions)]
            direction = direction - np.dot(direction, site.normal) * site.normal
            if np.linalg.norm(direction) < 1e-6:
                direction = _stroke_direction(site.normal)
            # Strokes stay on the side that faces the participant.
            pts, nrms = walk_surface(scene, site, direction, 60.0, stop=lambda p, n: _facing(p, n) < 0.2)
            frames = [press_frame(n) for n in nrms]
            pads = pts - prm.penetration_mm * nrms
            lift = 40.0 if tl is not None else prm.start_distance_mm
            above = pts[0] + lift * nrms[0]
            if tl is None:
                tl = _Timeline(above, frames[0])
                tl.hold(0.25)
            else:
                _transit(tl, above, frames[0], prm.approach_speed_mm_s, centre, safe_radius)
            tl.move(pads[0], prm.approach_speed_mm_s)
            tl.hold(0.3)
            tl.path(pads[1:], frames[1:], prm.speed_mm_s)
            tl.move(pts[-1] + 40.0 * nrms[-1], prm.approach_speed_mm_s)
            last_normal = nrms[-1]
        touches += 3
    if tl is None:
        raise ConfigurationError(f"scene {scene.name!r} has no face to explore")
    if prm.withdraw:
        tl.move(tl.position + prm.start_distance_mm * last_normal, prm.approach_speed_mm_s)
        tl.hold(0.25)
    return tl


def _facing(point: np.ndarray, normal: np.ndarray) -> float:
    to_eye = EYE_MM - point
    return float(np.dot(normal, to_eye / np.linalg.norm(to_eye)))


def _unit(v: np.ndarray) -> np.ndarray:
    n = float(np.linalg.norm(v))
    return v / n if n > 1e-9 else UP


# --- entry points --------------------------------------------------------------------------------------


def _positive(field_name: str, value: float, hi: float, unit: str) -> float:
    v = float(value)
    if not math.isfinite(v) or v <= 0 or v > hi:
        raise LimitError(field_name, value, f"a positive number up to {hi:g} {unit}")
    return v


def scene_for_trajectory(name: str, scene: Scene) -> Scene:
    """The scene to run ``name`` on: unchanged, except that a slide over a texture the scene lacks gets
    a copy of the scene whose objects carry that texture level."""
    if name not in TRAJECTORIES:
        raise ConfigurationError(f"unknown trajectory {name!r}; choose from {', '.join(TRAJECTORIES)}")
    if not name.startswith("slide-"):
        return scene
    level = SLIDE_LEVELS[name.split("-", 1)[1]]
    try:
        pick_site(scene, "face", texture_level=level, upward=True)
        return scene
    except ConfigurationError:
        return scene.with_texture_level(level)


#: A finger presses a few millimetres into a surface; beyond this a trajectory is not a touch (and its
#: arithmetic leaves the floats).
MAX_PENETRATION_MM = 100.0
#: Ten metres: further than any tracked room.
MAX_START_DISTANCE_MM = 10_000.0


def make_trajectory(
    name: str,
    scene: Scene,
    speed_mm_s: float | None = None,
    rate_hz: float = 72.0,
    seed: int = 0,
    *,
    tremor_mm: float = 0.0,
    tremor_hz: float | None = None,
    noise_mm: float = 0.0,
    noise_deg: float = 0.0,
    start_distance_mm: float = 100.0,
    penetration_mm: float = 3.0,
    dwell_s: float = 0.5,
    approach_speed_mm_s: float = 100.0,
    withdraw: bool = True,
) -> list[Pose]:
    """Poses of the study task ``name`` on ``scene``, sampled at ``rate_hz`` from t = 0."""
    if name not in TRAJECTORIES:
        raise ConfigurationError(f"unknown trajectory {name!r}; choose from {', '.join(TRAJECTORIES)}")
    family = _family(name)
    speed = (
        DEFAULT_SPEED_MM_S[family] if speed_mm_s is None else _positive("speed_mm_s", speed_mm_s, 1e5, "mm/s")
    )
    rate = _positive("rate_hz", rate_hz, 10_000.0, "Hz")
    for field_name, value in (
        ("tremor_mm", tremor_mm),
        ("noise_mm", noise_mm),
        ("noise_deg", noise_deg),
        ("penetration_mm", penetration_mm),
        ("dwell_s", dwell_s),
    ):
        if not math.isfinite(float(value)) or float(value) < 0:
            raise LimitError(field_name, value, "a finite number ≥ 0")
    if float(penetration_mm) > MAX_PENETRATION_MM:
        raise LimitError(
            "penetration_mm", penetration_mm, f"at most {MAX_PENETRATION_MM:g} mm into the surface"
        )
    if not math.isfinite(float(start_distance_mm)) or start_distance_mm < 80.0:
        raise LimitError("start_distance_mm", start_distance_mm, "≥ 80 mm (the studies withdrew beyond 8 cm)")
    if start_distance_mm > MAX_START_DISTANCE_MM:
        raise LimitError("start_distance_mm", start_distance_mm, f"at most {MAX_START_DISTANCE_MM:g} mm")
    prm = _Params(
        speed_mm_s=speed,
        approach_speed_mm_s=_positive("approach_speed_mm_s", approach_speed_mm_s, 1e5, "mm/s"),
        start_distance_mm=float(start_distance_mm),
        penetration_mm=float(penetration_mm),
        dwell_s=float(dwell_s),
        withdraw=bool(withdraw),
    )
    if family == "approach":
        tl = _approach_task(name, scene, prm)
    elif family == "contact":
        tl = _contact_task(name, scene, prm)
    elif family == "slide":
        tl = _slide_task(name, scene, prm)
    else:
        tl = _explore_task(scene, prm)
    ts, pos, quats = tl.sample(rate)
    rng = np.random.default_rng(seed)
    if tremor_mm > 0:
        hz = (
            float(rng.uniform(8.0, 12.0))
            if tremor_hz is None
            else _positive("tremor_hz", tremor_hz, rate / 2, "Hz")
        )
        axis = rng.normal(size=3)
        axis /= np.linalg.norm(axis)
        phase = float(rng.uniform(0.0, 2.0 * math.pi))
        pos = pos + tremor_mm * np.sin(2.0 * math.pi * hz * ts + phase)[:, None] * axis
    if noise_mm > 0:
        pos = pos + rng.normal(scale=noise_mm, size=pos.shape)
    if noise_deg > 0:
        axes = rng.normal(size=(len(ts), 3))
        angles = rng.normal(scale=noise_deg, size=len(ts))
        quats = np.array(
            [quat_multiply(quat_from_axis_angle(a, ang), q) for a, ang, q in zip(axes, angles, quats)]
        )
    return [Pose(float(t), p, q) for t, p, q in zip(ts, pos, quats)]
