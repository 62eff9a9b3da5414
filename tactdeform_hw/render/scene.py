"""Scenes: the objects a participant can touch, where they are, how they are rendered, and — from that —
which parts of the renderer have to exist at all.

A scene comes from a built-in name (``sphere``, ``cube``, ``teapot``, ``bunny`` of Phase 2 and the study
layouts ``task1``, ``task2``, ``task3``), from a mesh file (OBJ/STL/PLY, fitted into the 20 cm box), or from
a description file (TOML or JSON, same structure)::

    name = "two-bars"
    [options]
    contact_mode = "orientation"     # or "uniform": the same pattern wherever the contact is
    approach = "tactdeform"          # or "ua" / "cam", the Phase 2 baselines
    [[objects]]
    type = "box"                     # sphere | box | cube | teapot | bunny | mesh
    name = "left"
    size_mm = [200, 50, 50]
    center_mm = [-200, -200, 400]
    rotation_deg = [0, 0, 0]         # about world x, then y, then z
    texture_level = 0                # 0 smooth, 1 rough, 2 rougher
    approach = "cam"                 # optional, overrides the run's approach for this object
    [[objects.texture_regions]]      # optional: a level for the part of the surface inside a box
    lo_mm = [-300, -180, 300]
    hi_mm = [-100, -170, 500]
    level = 2

Mesh objects take ``path`` (relative to the description file), ``fit_mm`` (default 200, or ``scale``),
``up_axis`` (``"y"`` default, ``"z"`` for z-up files) and the feature parameters of
:class:`~.mesh.TriangleMesh`.  TOML needs Python ≥ 3.11 (``tomllib``) or the ``tomli`` package; JSON
always works.

What a scene needs
------------------
:attr:`Scene.needs` says which machinery the run uses, decided from the objects and the options before
anything is built, and the scene builds only that: no mesh index (and no scipy import) for a scene of
primitives; no face/edge/corner classification when no object is rendered with TactDeform; no texture
region look-up when every TactDeform surface is smooth; the pipeline skips θ (eq. 4) when the contact mode
is uniform.  Mesh indexes are built on first use or by :meth:`Scene.prepare`.
"""

from __future__ import annotations

import json
import math
import os
import sys
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import ConfigurationError
from .geometry import (
    DEFAULT_FEATURE_BAND_MM,
    PadPlane,
    SceneObject,
    SurfaceQuery,
    TextureRegion,
    as_point,
    as_points,
    check_band_mm,
    check_texture_level,
)
from .mesh import MESH_SUFFIXES, MeshData, TriangleMesh, read_mesh
from .primitives import Box, Sphere, SurfaceOptions
from .tracking import rotation_from_euler_deg

CONTACT_MODES: tuple[str, ...] = ("orientation", "uniform")
APPROACHES: tuple[str, ...] = ("tactdeform", "ua", "cam")

PHASE2_CENTER_MM = (0.0, -200.0, 450.0)
"""Where Phase 2 objects sit: 45 cm ahead of and 20 cm below the eye (the world origin)."""

BUNNY_FILE = "stanford_bunny.obj"
MESH_DIR_ENV = "TACTDEFORM_HW_MESHES"

OBJECT_TYPES = ("sphere", "box", "cube", "teapot", "bunny", "mesh")
_MESH_TYPES = ("teapot", "bunny", "mesh")


@dataclass(frozen=True)
class RenderOptions:
    """Per-run choices that change what is rendered (and so what has to be built)."""

    contact_mode: str = "orientation"
    approach: str = "tactdeform"

    def __post_init__(self) -> None:
        if self.contact_mode not in CONTACT_MODES:
            raise ConfigurationError(
                f"contact_mode={self.contact_mode!r} must be one of {', '.join(CONTACT_MODES)}"
            )
        if self.approach not in APPROACHES:
            raise ConfigurationError(f"approach={self.approach!r} must be one of {', '.join(APPROACHES)}")


@dataclass(frozen=True)
class SceneNeeds:
    """Which parts of the renderer a scene and its options use."""

    needs_mesh_index: bool
    """A triangle mesh is present: KD-tree, pseudo-normals or winding numbers (scipy, extra ``mesh``)."""
    needs_features: bool
    """Some object is rendered with TactDeform: contacts are classified face / edge / corner."""
    needs_texture: bool
    """Some TactDeform surface is rough or rougher: texture regions and the sliding shift are needed."""
    needs_orientation: bool
    """Orientation-specific contact (θ of eq. 4) under TactDeform; false for uniform contact."""
    needs_contains: bool
    """Some object is rendered with a baseline (UA or CAM): inside tests of the pad or the electrodes."""

    def as_dict(self) -> dict[str, bool]:
        return {
            "needs_mesh_index": self.needs_mesh_index,
            "needs_features": self.needs_features,
            "needs_texture": self.needs_texture,
            "needs_orientation": self.needs_orientation,
            "needs_contains": self.needs_contains,
        }


@dataclass(frozen=True)
class ObjectSpec:
    """One object of a scene description, before it is built."""

    type: str
    name: str
    params: Mapping[str, Any] = field(default_factory=dict)
    texture_level: int = 0
    texture_regions: tuple[TextureRegion, ...] = ()
    approach: str | None = None
    feature_band_mm: float = DEFAULT_FEATURE_BAND_MM

    @property
    def max_texture_level(self) -> int:
        return max([self.texture_level, *(r.level for r in self.texture_regions)])


# --- finding the shared meshes -------------------------------------------------------------------------


def mesh_search_dirs(extra: Iterable[str | os.PathLike[str]] = ()) -> list[Path]:
    """Where a built-in mesh is looked for: given directories, ``$TACTDEFORM_HW_MESHES``, then the
    ``shared/meshes`` folder beside the working directory and beside the source checkout."""
    dirs = [Path(d) for d in extra]
    env = os.environ.get(MESH_DIR_ENV)
    if env:
        dirs.append(Path(env))
    dirs.append(Path.cwd() / ".." / "shared" / "meshes")
    dirs.append(Path(__file__).resolve().parents[2] / ".." / "shared" / "meshes")
    return dirs


def find_mesh_file(filename: str, extra_dirs: Iterable[str | os.PathLike[str]] = ()) -> Path:
    tried = mesh_search_dirs(extra_dirs)
    for d in tried:
        candidate = d / filename
        if candidate.is_file():
            return candidate.resolve()
    where = ", ".join(str(d) for d in tried)
    raise ConfigurationError(
        f"mesh {filename!r} not found (looked in {where}); give its path, e.g. --scene /path/to/{filename}, "
        f"or set {MESH_DIR_ENV}"
    )


_MESH_CACHE: dict[tuple[str, float], MeshData] = {}


def _read_mesh_cached(path: Path) -> MeshData:
    key = (str(path.resolve()), path.stat().st_mtime)
    data = _MESH_CACHE.get(key)
    if data is None:
        data = read_mesh(path)
        _MESH_CACHE.clear()  # keep one file: scenes are rebuilt with other options, not collected
        _MESH_CACHE[key] = data
    return data


# --- the scene -----------------------------------------------------------------------------------------


def compute_needs(specs: Sequence[ObjectSpec], options: RenderOptions) -> SceneNeeds:
    approaches = [s.approach or options.approach for s in specs]
    tactdeform = [a == "tactdeform" for a in approaches]
    return SceneNeeds(
        needs_mesh_index=any(s.type in _MESH_TYPES for s in specs),
        needs_features=any(tactdeform),
        needs_texture=any(t and s.max_texture_level > 0 for s, t in zip(specs, tactdeform)),
        needs_orientation=options.contact_mode == "orientation" and any(tactdeform),
        needs_contains=any(a in ("ua", "cam") for a in approaches),
    )


class Scene:
    """Objects in world millimetres, the run's render options, and what they need.

    Build one with :func:`load_scene` (names, files) or :meth:`from_specs`; a scene made directly from
    objects computes its needs from them.
    """

    def __init__(
        self,
        objects: Sequence[SceneObject],
        *,
        options: RenderOptions | None = None,
        name: str = "scene",
        approaches: Mapping[str, str] | None = None,
        specs: Sequence[ObjectSpec] | None = None,
        base_dir: Path | None = None,
        mesh_dirs: Sequence[str | os.PathLike[str]] = (),
    ) -> None:
        if not objects:
            raise ConfigurationError(f"scene {name!r} has no objects")
        names = [o.name for o in objects]
        dupes = sorted({n for n in names if names.count(n) > 1})
        if dupes:
            raise ConfigurationError(
                f"scene {name!r}: object names must be unique, repeated: {', '.join(dupes)}"
            )
        self.name = name
        self.objects: tuple[SceneObject, ...] = tuple(objects)
        self.options = options or RenderOptions()
        self._approaches = dict(approaches or {})
        for obj_name, approach in self._approaches.items():
            if obj_name not in names:
                raise ConfigurationError(f"scene {name!r}: approach given for unknown object {obj_name!r}")
            if approach not in APPROACHES:
                raise ConfigurationError(
                    f"object {obj_name!r}: approach={approach!r} must be one of {', '.join(APPROACHES)}"
                )
        self.specs = tuple(specs) if specs is not None else None
        self._base_dir = base_dir
        self._mesh_dirs = tuple(mesh_dirs)
        self.needs = self._needs_from_objects()
        self._single = self.objects[0] if len(self.objects) == 1 else None
        self._bounds = [self._object_bounds(o) for o in self.objects]

    @classmethod
    def from_specs(
        cls,
        name: str,
        specs: Sequence[ObjectSpec],
        options: RenderOptions | None = None,
        *,
        base_dir: Path | None = None,
        mesh_dirs: Sequence[str | os.PathLike[str]] = (),
    ) -> Scene:
        opts = options or RenderOptions()
        needs = compute_needs(specs, opts)
        objects = [_build_object(s, opts, needs, base_dir, mesh_dirs) for s in specs]
        approaches = {s.name: s.approach for s in specs if s.approach is not None}
        return cls(
            objects,
            options=opts,
            name=name,
            approaches=approaches,
            specs=specs,
            base_dir=base_dir,
            mesh_dirs=mesh_dirs,
        )

    def _needs_from_objects(self) -> SceneNeeds:
        approaches = [self.approach_for(o.name) for o in self.objects]
        tactdeform = [a == "tactdeform" for a in approaches]
        levels = [getattr(o, "max_texture_level", lambda: 0)() for o in self.objects]
        return SceneNeeds(
            needs_mesh_index=any(isinstance(o, TriangleMesh) for o in self.objects),
            needs_features=any(tactdeform),
            needs_texture=any(t and lv > 0 for t, lv in zip(tactdeform, levels)),
            needs_orientation=self.options.contact_mode == "orientation" and any(tactdeform),
            needs_contains=any(a in ("ua", "cam") for a in approaches),
        )

    # -- derived scenes --------------------------------------------------------------------------------

    def _rebuild(self, specs: Sequence[ObjectSpec], options: RenderOptions) -> Scene:
        return Scene.from_specs(self.name, specs, options, base_dir=self._base_dir, mesh_dirs=self._mesh_dirs)

    def with_options(self, options: RenderOptions) -> Scene:
        """The same objects under other render options (rebuilt, so the needs follow)."""
        if self.specs is None:
            return Scene(self.objects, options=options, name=self.name, approaches=self._approaches)
        return self._rebuild(self.specs, options)

    def with_texture_level(self, level: int, objects: Iterable[str] | None = None) -> Scene:
        """A copy whose objects (all, or the named ones) carry texture ``level`` over their whole surface."""
        level = check_texture_level("texture_level", level)
        if self.specs is None:
            raise ConfigurationError("with_texture_level needs a scene built from a description or a name")
        chosen = set(objects) if objects is not None else {s.name for s in self.specs}
        unknown = chosen - {s.name for s in self.specs}
        if unknown:
            raise ConfigurationError(f"scene {self.name!r} has no object(s) {', '.join(sorted(unknown))}")
        specs = [
            replace(s, texture_level=level, texture_regions=()) if s.name in chosen else s for s in self.specs
        ]
        return self._rebuild(specs, self.options)

    # -- what is built ---------------------------------------------------------------------------------

    def approach_for(self, object_name: str) -> str:
        """The rendering approach of one object: its own, or the run's."""
        return self._approaches.get(object_name, self.options.approach)

    def prepare(self) -> None:
        """Build every lazily built part the run needs now (mesh indexes; their feature tables when
        contacts are classified), so the first frame does not pay for it."""
        for obj in self.objects:
            if isinstance(obj, TriangleMesh):
                obj.prepare(features=self.needs.needs_features)

    def built_parts(self) -> dict[str, Any]:
        """What exists right now: for tests and the cost tool."""
        meshes = [o for o in self.objects if isinstance(o, TriangleMesh)]
        return {
            "mesh_index": [o.name for o in meshes if o.index_built],
            "mesh_features": [o.name for o in meshes if o.features_built],
            "feature_classification": [
                o.name for o in self.objects if getattr(o, "classify_features", False)
            ],
            "texture_lookup": [o.name for o in self.objects if getattr(o, "has_texture_lookup", False)],
            "scipy_imported": "scipy.spatial" in sys.modules,
            "trimesh_imported": "trimesh" in sys.modules,
        }

    @property
    def bounds_mm(self) -> tuple[np.ndarray, np.ndarray]:
        lo = np.min([b[0] for b in self._bounds], axis=0)
        hi = np.max([b[1] for b in self._bounds], axis=0)
        return lo, hi

    @staticmethod
    def _object_bounds(obj: SceneObject) -> tuple[np.ndarray, np.ndarray]:
        bounds = getattr(obj, "bounds_mm", None)
        if bounds is None:
            return np.full(3, -np.inf), np.full(3, np.inf)
        lo, hi = bounds
        return np.asarray(lo, dtype=float), np.asarray(hi, dtype=float)

    def object(self, name: str) -> SceneObject:
        for o in self.objects:
            if o.name == name:
                return o
        raise ConfigurationError(f"scene {self.name!r} has no object {name!r}")

    # -- queries ---------------------------------------------------------------------------------------

    def query(self, point_mm: np.ndarray) -> SurfaceQuery:
        """The nearest surface over all objects (smallest signed distance: inside one object wins)."""
        if self._single is not None:
            return self._single.query(point_mm)
        p = as_point(point_mm)
        px, py, pz = float(p[0]), float(p[1]), float(p[2])
        # Objects whose bounding box is farther than the best answer so far cannot be nearer.
        order = []
        for obj, (lo, hi) in zip(self.objects, self._bounds):
            dx = max(lo[0] - px, 0.0, px - hi[0])
            dy = max(lo[1] - py, 0.0, py - hi[1])
            dz = max(lo[2] - pz, 0.0, pz - hi[2])
            order.append((math.sqrt(dx * dx + dy * dy + dz * dz), obj))
        order.sort(key=lambda item: item[0])
        best: SurfaceQuery | None = None
        for lower, obj in order:
            if best is not None and lower > best.signed_distance_mm:
                break
            q = obj.query(p)
            if best is None or q.signed_distance_mm < best.signed_distance_mm:
                best = q
        assert best is not None
        return best

    @property
    def is_single_object(self) -> bool:
        return self._single is not None

    @property
    def has_plane_test(self) -> bool:
        """Whether an object answers for a plane of points at once (:meth:`contains_on_pad`)."""
        return any(hasattr(o, "contains_on_pad") for o in self.objects)

    def contains_on_pad(self, pad: PadPlane, query: Any = None) -> np.ndarray:
        """(N,) inside any object, for the points of ``pad`` (the pad's electrodes).  Objects that can
        answer for a plane at once (meshes) do; the others get the points.  ``query`` (the scene's answer
        at the centre) saves the nearest object's own query."""
        off, c = pad.offsets_mm, pad.centre_mm
        single = self._single
        if single is not None and hasattr(single, "contains_on_pad"):
            inside = None
            if query is not None and getattr(query, "object_name", None) == single.name:
                inside = float(query.signed_distance_mm) <= 0.0
            result: np.ndarray = single.contains_on_pad(pad, inside)
            return result
        reach = float(np.sqrt((off * off).sum(axis=1).max())) if len(off) else 0.0
        out = np.zeros(len(off), dtype=bool)
        pts: np.ndarray | None = None
        for obj, (lo, hi) in zip(self.objects, self._bounds):
            if np.any(c + reach < lo) or np.any(c - reach > hi):
                continue
            on_pad = getattr(obj, "contains_on_pad", None)
            if on_pad is not None:
                inside = None
                if query is not None and getattr(query, "object_name", None) == obj.name:
                    inside = float(query.signed_distance_mm) <= 0.0
                out |= on_pad(pad, inside)
            else:
                if pts is None:
                    pts = pad.points()
                box = np.all((pts >= lo) & (pts <= hi), axis=1)
                if box.any():
                    out[box] |= obj.contains(pts[box])
        return out

    def contains(self, points_mm: np.ndarray, objects: Iterable[str] | None = None) -> np.ndarray:
        """(N,) inside any object (or any of the named ones) — the baselines' test."""
        pts = as_points(points_mm)
        chosen = self.objects if objects is None else [self.object(n) for n in objects]
        out = np.zeros(len(pts), dtype=bool)
        for obj, (lo, hi) in zip(self.objects, self._bounds):
            if obj not in chosen:
                continue
            box = np.all((pts >= lo) & (pts <= hi), axis=1)
            if box.any():
                out[box] |= obj.contains(pts[box])
        return out


# --- building objects ----------------------------------------------------------------------------------


def _rotation_of(params: Mapping[str, Any], name: str) -> np.ndarray | None:
    rot = params.get("rotation_deg")
    if rot is None:
        return None
    values = _floats(f"{name}.rotation_deg", rot, 3)
    return rotation_from_euler_deg(*values)


def _floats(field_name: str, value: Any, n: int) -> tuple[float, ...]:
    if isinstance(value, (int, float)) and not isinstance(value, bool) and n == 1:
        value = [value]
    if not isinstance(value, (list, tuple)) or len(value) != n:
        raise ConfigurationError(f"{field_name}={value!r} must be a list of {n} numbers")
    out = []
    for v in value:
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(float(v)):
            raise ConfigurationError(f"{field_name}={value!r} must be a list of {n} finite numbers")
        out.append(float(v))
    return tuple(out)


_Z_UP = np.array(((1.0, 0.0, 0.0), (0.0, 0.0, 1.0), (0.0, -1.0, 0.0)))


def _build_object(
    spec: ObjectSpec,
    options: RenderOptions,
    needs: SceneNeeds,
    base_dir: Path | None,
    mesh_dirs: Sequence[str | os.PathLike[str]],
) -> SceneObject:
    approach = spec.approach or options.approach
    classify = approach == "tactdeform"
    # Region look-ups exist only where texture is rendered.
    regions = spec.texture_regions if needs.needs_texture and approach == "tactdeform" else ()
    common = SurfaceOptions(
        texture_level=spec.texture_level,
        texture_regions=regions,
        feature_band_mm=spec.feature_band_mm,
        classify_features=classify,
    )
    p = dict(spec.params)
    center = _floats(f"{spec.name}.center_mm", p.pop("center_mm", PHASE2_CENTER_MM), 3)
    rotation = _rotation_of(p, spec.name)
    p.pop("rotation_deg", None)
    if spec.type == "sphere":
        radius = p.pop("radius_mm", 100.0)
        _no_more(spec, p)
        return Sphere(spec.name, float(radius), center, **common)
    if spec.type in ("box", "cube"):
        size = p.pop("size_mm", 200.0)
        size_v = _floats(f"{spec.name}.size_mm", size, 1 if isinstance(size, (int, float)) else 3)
        _no_more(spec, p)
        return Box(spec.name, size_v if len(size_v) == 3 else size_v[0], center, rotation=rotation, **common)
    mesh_kw = {k: p.pop(k) for k in list(p) if k in _MESH_PARAMS}
    if "scale" in mesh_kw and "fit_mm" not in mesh_kw:
        mesh_kw["fit_mm"] = None  # an explicit scale keeps the file's proportions in its own units
    if mesh_kw.get("fit_mm") is not None:
        mesh_kw["fit_mm"] = float(mesh_kw["fit_mm"])
    if spec.type == "teapot":
        from .teapot import teapot_mesh

        subdivisions = p.pop("subdivisions", 12)
        _no_more(spec, p)
        return teapot_mesh(
            spec.name, center_mm=center, rotation=rotation, subdivisions=subdivisions, **mesh_kw, **common
        )
    up_axis = p.pop("up_axis", "z" if spec.type == "bunny" else "y")
    if up_axis not in ("y", "z"):
        raise ConfigurationError(f"{spec.name}.up_axis={up_axis!r} must be 'y' or 'z'")
    if spec.type == "bunny":
        path_value = p.pop("path", None)
        path = _resolve(path_value, base_dir) if path_value else find_mesh_file(BUNNY_FILE, mesh_dirs)
    else:
        path_value = p.pop("path", None)
        if not path_value:
            raise ConfigurationError(f"object {spec.name!r}: a mesh needs 'path'")
        path = _resolve(path_value, base_dir)
    _no_more(spec, p)
    data = _read_mesh_cached(path)
    r = rotation if rotation is not None else np.eye(3)
    if up_axis == "z":
        r = r @ _Z_UP
    return TriangleMesh(
        spec.name,
        data.vertices,
        data.faces,
        center_mm=center,
        rotation=r,
        source=data.source,
        **mesh_kw,
        **common,
    )


_MESH_PARAMS = (
    "fit_mm",
    "scale",
    "sharp_angle_deg",
    "min_chain_mm",
    "concave_edges",
    "boundary_edges_sharp",
    "corner_turn_deg",
    "sign_method",
    "sample_spacing_mm",
)


def _resolve(value: Any, base_dir: Path | None) -> Path:
    if not isinstance(value, str) or not value:
        raise ConfigurationError(f"mesh path={value!r} must be a non-empty string")
    path = Path(value).expanduser()
    if not path.is_absolute() and base_dir is not None:
        path = base_dir / path
    if not path.is_file():
        raise ConfigurationError(f"mesh file {str(path)!r} does not exist")
    return path


def _no_more(spec: ObjectSpec, rest: Mapping[str, Any]) -> None:
    if rest:
        raise ConfigurationError(
            f"object {spec.name!r} ({spec.type}): unknown key(s) {', '.join(sorted(rest))}"
        )


# --- descriptions --------------------------------------------------------------------------------------

_OBJECT_KEYS = {"type", "name", "texture_level", "texture_regions", "approach", "feature_band_mm"}


def parse_object(entry: Mapping[str, Any], index: int) -> ObjectSpec:
    if not isinstance(entry, Mapping):
        raise ConfigurationError(f"objects[{index}] must be a table/object, got {type(entry).__name__}")
    kind = entry.get("type")
    if kind not in OBJECT_TYPES:
        raise ConfigurationError(f"objects[{index}].type={kind!r} must be one of {', '.join(OBJECT_TYPES)}")
    name = entry.get("name", kind if index == 0 else f"{kind}{index}")
    if not isinstance(name, str) or not name:
        raise ConfigurationError(f"objects[{index}].name={name!r} must be a non-empty string")
    level = check_texture_level(f"{name}.texture_level", entry.get("texture_level", 0))
    regions = []
    raw_regions = entry.get("texture_regions", [])
    if not isinstance(raw_regions, list):
        raise ConfigurationError(f"{name}.texture_regions must be a list of tables")
    for j, r in enumerate(raw_regions):
        if (
            not isinstance(r, Mapping)
            or set(r) - {"lo_mm", "hi_mm", "level", "name"}
            or not {"lo_mm", "hi_mm", "level"} <= set(r)
        ):
            raise ConfigurationError(
                f"{name}.texture_regions[{j}] needs exactly lo_mm, hi_mm, level (and optional name)"
            )
        regions.append(
            TextureRegion(
                _floats(f"{name}.texture_regions[{j}].lo_mm", r["lo_mm"], 3),
                _floats(f"{name}.texture_regions[{j}].hi_mm", r["hi_mm"], 3),
                r["level"],
                str(r.get("name", f"{name}.region{j}")),
            )
        )
    approach = entry.get("approach")
    if approach is not None and approach not in APPROACHES:
        raise ConfigurationError(f"{name}.approach={approach!r} must be one of {', '.join(APPROACHES)}")
    band = check_band_mm(f"{name}.feature_band_mm", entry.get("feature_band_mm", DEFAULT_FEATURE_BAND_MM))
    params = {k: v for k, v in entry.items() if k not in _OBJECT_KEYS}
    return ObjectSpec(kind, name, params, level, tuple(regions), approach, band)


def parse_description(
    data: Mapping[str, Any], *, source: str = "<scene>"
) -> tuple[str, list[ObjectSpec], RenderOptions]:
    if not isinstance(data, Mapping):
        raise ConfigurationError(f"{source}: a scene description is a table/object at the top level")
    unknown = set(data) - {"name", "options", "objects"}
    if unknown:
        raise ConfigurationError(f"{source}: unknown top-level key(s) {', '.join(sorted(unknown))}")
    name = data.get("name", Path(source).stem)
    raw_options = data.get("options", {})
    if not isinstance(raw_options, Mapping) or set(raw_options) - {"contact_mode", "approach"}:
        raise ConfigurationError(f"{source}: options may hold contact_mode and approach only")
    options = RenderOptions(**raw_options)
    objects = data.get("objects")
    if not isinstance(objects, list) or not objects:
        raise ConfigurationError(f"{source}: 'objects' must be a non-empty list")
    specs = [parse_object(o, i) for i, o in enumerate(objects)]
    return str(name), specs, options


def read_description(path: str | os.PathLike[str]) -> dict[str, Any]:
    p = Path(path)
    suffix = p.suffix.lower()
    try:
        raw = p.read_bytes()
    except OSError as exc:
        raise ConfigurationError(f"cannot read scene file {str(p)!r}: {exc.strerror or exc}") from exc
    if suffix == ".json":
        try:
            data = json.loads(raw.decode("utf-8"))
        except (UnicodeDecodeError, json.JSONDecodeError) as exc:
            raise ConfigurationError(f"{p}: not valid JSON: {exc}") from exc
        if not isinstance(data, dict):
            raise ConfigurationError(f"{p}: a scene description is an object at the top level")
        return data
    if suffix == ".toml":
        toml = _toml_module()
        try:
            loaded: dict[str, Any] = toml.loads(raw.decode("utf-8"))
            return loaded
        except (UnicodeDecodeError, toml.TOMLDecodeError) as exc:
            raise ConfigurationError(f"{p}: not valid TOML: {exc}") from exc
    raise ConfigurationError(f"scene file {str(p)!r}: use .toml or .json")


def _toml_module() -> Any:
    if sys.version_info >= (3, 11):
        import tomllib

        return tomllib
    try:  # pragma: no cover - Python 3.10 only
        import tomli

        return tomli
    except ImportError as exc:  # pragma: no cover
        raise ConfigurationError(
            "TOML scene files need Python 3.11 or later (tomllib) or the 'tomli' package; "
            "on Python 3.10 without tomli, write the scene as JSON (same structure)"
        ) from exc


# --- built-in scenes -----------------------------------------------------------------------------------


def _spec(kind: str, name: str, **params: Any) -> ObjectSpec:
    level = params.pop("texture_level", 0)
    return ObjectSpec(kind, name, params, level)


BUILTIN_SCENES: dict[str, str] = {
    "sphere": "Phase 2 sphere, 20 cm across, 45 cm ahead and 20 cm below the eye",
    "cube": "Phase 2 cube, 20 cm sides, same place",
    "teapot": "Phase 2 Utah teapot from its Bézier patches, fitted into 20 cm, same place",
    "bunny": "Phase 2 Stanford bunny (rough texture), fitted into 20 cm; read from ../shared/meshes",
    "task1": "Task 1: a 5 cm cube 45 cm ahead, 20 cm below the eye (faces, edges, corners)",
    "task2": "Task 2: two 20 × 5 × 5 cm bars 40 cm ahead, 20 cm below the eye, 20 cm left and right",
    "task3": "Task 3: two 30 cm wide surfaces, 10 cm (rough) and 25 cm (rougher) below the eye",
}


def builtin_specs(name: str) -> list[ObjectSpec]:
    c = list(PHASE2_CENTER_MM)
    if name == "sphere":
        return [_spec("sphere", "sphere", radius_mm=100.0, center_mm=c)]
    if name == "cube":
        return [_spec("box", "cube", size_mm=200.0, center_mm=c)]
    if name == "teapot":
        return [_spec("teapot", "teapot", center_mm=c)]
    if name == "bunny":
        # The paper's textured Phase 2 object; which level it carried is not reported: rough.
        return [_spec("bunny", "bunny", center_mm=c, texture_level=1)]
    if name == "task1":
        return [_spec("box", "cube", size_mm=50.0, center_mm=[0.0, -200.0, 450.0])]
    if name == "task2":
        return [
            _spec("box", "left", size_mm=[200.0, 50.0, 50.0], center_mm=[-200.0, -200.0, 400.0]),
            _spec("box", "right", size_mm=[200.0, 50.0, 50.0], center_mm=[200.0, -200.0, 400.0]),
        ]
    if name == "task3":
        # Stacked 15 cm apart and offset in depth so that both tops can be stroked from above.
        return [
            _spec(
                "box", "upper", size_mm=[300.0, 20.0, 80.0], center_mm=[0.0, -110.0, 360.0], texture_level=1
            ),
            _spec(
                "box", "lower", size_mm=[300.0, 20.0, 80.0], center_mm=[0.0, -260.0, 460.0], texture_level=2
            ),
        ]
    raise ConfigurationError(f"no built-in scene {name!r}; built-ins: {', '.join(BUILTIN_SCENES)}")


def load_scene(
    name_or_path: str | os.PathLike[str],
    *,
    options: RenderOptions | None = None,
    mesh_dirs: Sequence[str | os.PathLike[str]] = (),
) -> Scene:
    """A scene from a built-in name, a mesh file, or a TOML/JSON description.

    ``options`` (e.g. from the command line) replace the description's own.
    """
    text = str(name_or_path)
    if text in BUILTIN_SCENES:
        return Scene.from_specs(text, builtin_specs(text), options, mesh_dirs=mesh_dirs)
    path = Path(text).expanduser()
    suffix = path.suffix.lower()
    if suffix in MESH_SUFFIXES:
        if not path.is_file():
            raise ConfigurationError(f"mesh file {str(path)!r} does not exist")
        spec = ObjectSpec(
            "mesh", path.stem or "mesh", {"path": str(path.resolve()), "center_mm": list(PHASE2_CENTER_MM)}
        )
        return Scene.from_specs(path.stem or "mesh", [spec], options, mesh_dirs=mesh_dirs)
    if suffix in (".toml", ".json"):
        if not path.is_file():
            raise ConfigurationError(f"scene file {str(path)!r} does not exist")
        scene_name, specs, file_options = parse_description(read_description(path), source=str(path))
        return Scene.from_specs(
            scene_name, specs, options or file_options, base_dir=path.resolve().parent, mesh_dirs=mesh_dirs
        )
    raise ConfigurationError(
        f"scene {text!r} is neither a built-in ({', '.join(BUILTIN_SCENES)}) nor a .toml/.json description "
        f"nor a mesh file ({', '.join(MESH_SUFFIXES)})"
    )
