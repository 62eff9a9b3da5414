"""Triangle meshes as touchable solids: file reading, fitting into the study's box, closest-point queries,
inside/outside, and the local feature (face, edge, corner) under a contact.

What is built, and when
-----------------------
Construction reads the file, places the mesh (rotation, then scaled so its largest extent is ``fit_mm``,
centred on ``center_mm``), welds duplicate vertices and drops degenerate triangles: numpy only.
Everything else is built on first use (or by :meth:`TriangleMesh.prepare`) and only if the run needs it:

* the *index* (needs scipy, extra ``mesh``): long edges split, per-triangle linear maps for the distance
  kernel, vertices in a KD-tree, pseudo-normals (closed meshes) or a winding-number hierarchy (open ones);
* the *features* (only when contacts are classified): dihedral angles, sharp-edge chains, corners.

Closest triangle, exactly
-------------------------
Edges longer than the sample spacing s (default twice the median edge) are split at their midpoints,
conformingly, until none is left: the surface is unchanged, but every point of every triangle now lies
within h (the largest circumradius, or half-edge for obtuse triangles, at most s/√3) of one of that
triangle's vertices.  The KD-tree holds the vertices.  For a query p at true distance D, any point known
to be on the surface at distance U ≥ D (the nearest vertex, or the previous query's closest point when
the finger has moved little) bounds the search: the closest triangle has a vertex within D + h ≤ U + h,
so the triangles around the vertices in that ball contain it.  Their squared distances come from one
matrix product (each triangle stores the 16 quantities of the point–triangle distance that are linear
in p) and a few clamps; the winner's closest point, region and sign are then computed exactly on floats.
Near the surface that is one or two tree look-ups and a kernel over a few dozen triangles; far from it
the ball, and the cost, grow.  Queries keep that coherence hint, so one object should not be queried
from several threads at once.

Sign
----
Closed, consistently oriented meshes (every edge shared by exactly two triangles, in opposite
directions) take the sign from the angle-weighted pseudo-normal of the closest feature (Bærentzen &
Aanæs 2005), which is exact.  Anything else (open boundaries, intersecting parts like the teapot's spout
and handle) uses the generalised winding number (Jacobson et al. 2013) ≥ ½, evaluated exactly for
triangle clusters near the point and by their dipole far away.

Feature under the contact
-------------------------
An edge between two triangles is *sharp* when the angle between their normals is at least
``sharp_angle_deg`` and it is convex (or ``concave_edges`` is set); boundary edges (a thin lip) are sharp
when ``boundary_edges_sharp``.  Scanned meshes fold a few triangles; such noise is dropped by keeping only
chains of sharp edges at least ``min_chain_mm`` long.  A vertex where three or more sharp edges meet (or
two meeting at a turn of at least ``corner_turn_deg``) is a corner, and so is every vertex of a *tip*: a
sharp chain that turns by at least ``corner_turn_deg`` within ``tip_window_mm`` of its length (the pad's
width, 10 mm).  A tip is where the surface bends sharply in several directions under one finger pad —
the teapot's spout opening (a lip of 6 mm radius turns 90° within 10 mm), a blunt cone's point — and
what a finger feels there is concentrated, not a line; a long gently curving crease (the teapot's rim,
10° per 10 mm) stays an edge.  A contact whose closest point is
within ``feature_band_mm`` of a corner reads as a corner, else within the band of a sharp edge as an edge
(with that edge's direction), else as a face.
"""

from __future__ import annotations

import math
import os
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from ..errors import ConfigurationError, MissingDependencyError
from .geometry import (
    PadPlane,
    SurfaceQuery,
    SurfaceSite,
    as_point,
    as_points,
)
from .primitives import PlacedSolid, SurfaceOptions

if TYPE_CHECKING:
    from typing_extensions import Unpack  # typing's own from Python 3.11

DEFAULT_FIT_MM = 200.0
"""Largest extent of a mesh in the studies' Phase 2: every object fits a 20 × 20 × 20 cm box."""

_SENTINEL_COORD = 1.0e15

# Bound ufuncs: the per-query kernel works on a few dozen rows, where numpy's Python-level wrappers
# (np.clip, ndarray.min) cost more than the arithmetic.
_minimum = np.minimum
_maximum = np.maximum
_where = np.where


def _scipy_spatial() -> Any:
    try:
        import scipy.spatial
    except ImportError as exc:  # pragma: no cover - exercised only without the extra
        raise MissingDependencyError("scipy", "mesh", "the triangle-mesh acceleration structure") from exc
    return scipy.spatial


# --- reading ------------------------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class MeshData:
    """Vertices (V, 3) and triangles (F, 3) as read from a file, in the file's units."""

    vertices: np.ndarray
    faces: np.ndarray
    source: str = ""


def read_obj(path: str | os.PathLike[str]) -> MeshData:
    """Vertices and faces of a Wavefront OBJ file (polygons are fanned into triangles; texture and normal
    indices, groups and materials are ignored).  Errors name the line."""
    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8", errors="replace")
    except OSError as exc:
        raise ConfigurationError(f"cannot read mesh file {str(p)!r}: {exc.strerror or exc}") from exc
    vertices: list[tuple[float, float, float]] = []
    faces: list[tuple[int, int, int]] = []
    for lineno, line in enumerate(text.splitlines(), start=1):
        if line.startswith("v "):
            parts = line.split()
            try:
                vertices.append((float(parts[1]), float(parts[2]), float(parts[3])))
            except (IndexError, ValueError):
                raise ConfigurationError(
                    f"{p}: line {lineno}: vertex needs three numbers: {line.strip()!r}"
                ) from None
        elif line.startswith("f "):
            tokens = line.split()[1:]
            if len(tokens) < 3:
                raise ConfigurationError(
                    f"{p}: line {lineno}: face needs at least three vertices: {line.strip()!r}"
                )
            idx = []
            nv = len(vertices)
            for tok in tokens:
                try:
                    i = int(tok.split("/", 1)[0])
                except ValueError:
                    raise ConfigurationError(f"{p}: line {lineno}: bad vertex index {tok!r}") from None
                j = i - 1 if i > 0 else nv + i
                if i == 0 or not 0 <= j < nv:
                    raise ConfigurationError(
                        f"{p}: line {lineno}: vertex index {i} refers to no vertex (there are {nv} so far)"
                    )
                idx.append(j)
            for k in range(1, len(idx) - 1):
                faces.append((idx[0], idx[k], idx[k + 1]))
    if not vertices or not faces:
        raise ConfigurationError(f"{p}: no triangles found (vertices: {len(vertices)}, faces: {len(faces)})")
    v = np.array(vertices, dtype=float)
    if not np.isfinite(v).all():
        raise ConfigurationError(f"{p}: vertex coordinates must be finite")
    return MeshData(v, np.array(faces, dtype=np.int64), str(p))


def _read_with_trimesh(path: Path) -> MeshData:
    try:
        import trimesh
    except ImportError as exc:
        raise MissingDependencyError("trimesh", "mesh", f"reading {path.suffix} meshes") from exc
    try:
        loaded = trimesh.load(str(path), force="mesh", process=True)
    except Exception as exc:  # trimesh raises many types; the file is the problem either way
        raise ConfigurationError(f"cannot read mesh file {str(path)!r}: {exc}") from exc
    v = np.array(getattr(loaded, "vertices", ()), dtype=float)
    f = np.array(getattr(loaded, "faces", ()), dtype=np.int64)
    if v.size == 0 or f.size == 0:
        raise ConfigurationError(f"{path}: no triangles found")
    return MeshData(v, f, str(path))


MESH_SUFFIXES = (".obj", ".stl", ".ply")


def read_mesh(path: str | os.PathLike[str]) -> MeshData:
    """Read OBJ with our own reader, STL and PLY through trimesh (extra ``mesh``)."""
    p = Path(path)
    if not p.is_file():
        raise ConfigurationError(f"mesh file {str(p)!r} does not exist")
    suffix = p.suffix.lower()
    if suffix == ".obj":
        return read_obj(p)
    if suffix in (".stl", ".ply"):
        return _read_with_trimesh(p)
    raise ConfigurationError(
        f"mesh file {str(p)!r}: unsupported format {suffix!r}; use one of {', '.join(MESH_SUFFIXES)}"
    )


# --- cleaning and topology ----------------------------------------------------------------------------


def _clean(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Weld coincident vertices, drop triangles that repeat a vertex, have no area, or repeat a triangle."""
    extent = float(np.ptp(vertices, axis=0).max()) or 1.0
    quantum = extent * 1e-9
    keys = np.round(vertices / quantum).astype(np.int64)
    _, first, inverse = np.unique(keys, axis=0, return_index=True, return_inverse=True)
    inverse = inverse.ravel()
    order = np.argsort(first)
    remap = np.empty_like(order)
    remap[order] = np.arange(len(order))
    v = vertices[first[order]]
    f = remap[inverse[faces]]
    ok = (f[:, 0] != f[:, 1]) & (f[:, 1] != f[:, 2]) & (f[:, 2] != f[:, 0])
    f = f[ok]
    a, b, c = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
    area2 = np.linalg.norm(np.cross(b - a, c - a), axis=1)
    f = f[area2 > (extent * 1e-7) ** 2]
    _, keep = np.unique(np.sort(f, axis=1), axis=0, return_index=True)
    f = f[np.sort(keep)]
    used = np.unique(f)
    if len(used) < len(v):
        remap2 = np.full(len(v), -1, dtype=np.int64)
        remap2[used] = np.arange(len(used))
        v = v[used]
        f = remap2[f]
    return v, f.astype(np.int64)


@dataclass(frozen=True, eq=False)
class _Topology:
    edges: np.ndarray  # (E, 2) vertex ids, sorted per row
    face_edges: np.ndarray  # (F, 3) edge id of half-edge k (v_k -> v_{k+1})
    edge_faces: np.ndarray  # (E, 2) the first two faces of each edge, -1 when absent
    edge_count: np.ndarray  # (E,) faces per edge
    consistent: bool  # every two-face edge is used in opposite directions
    watertight: bool


def _topology(faces: np.ndarray, n_vertices: int) -> _Topology:
    n_faces = len(faces)
    he = np.stack((faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]), axis=1).reshape(-1, 2)
    lo = np.minimum(he[:, 0], he[:, 1])
    hi = np.maximum(he[:, 0], he[:, 1])
    key = lo * np.int64(n_vertices) + hi
    uniq, inverse, counts = np.unique(key, return_inverse=True, return_counts=True)
    inverse = inverse.ravel()
    edges = np.stack((uniq // n_vertices, uniq % n_vertices), axis=1)
    order = np.argsort(inverse, kind="stable")
    starts = np.concatenate(([0], np.cumsum(counts)[:-1]))
    first = order[starts]
    second_ok = counts >= 2
    second = np.full(len(uniq), -1, dtype=np.int64)
    second[second_ok] = order[starts[second_ok] + 1]
    edge_faces = np.stack((first // 3, np.where(second >= 0, second // 3, -1)), axis=1)
    two = counts == 2
    consistent = bool(np.all(he[first[two], 0] == he[second[two], 1]))
    watertight = bool(np.all(counts == 2)) and consistent
    return _Topology(edges, inverse.reshape(n_faces, 3), edge_faces, counts, consistent, watertight)


# --- the index: closest triangles ---------------------------------------------------------------------


_Xyz = tuple[float, float, float]


def _corner_region(
    p: _Xyz, a: _Xyz, x: _Xyz, own: _Xyz, other: _Xyz, a_dots: tuple[float, float], regions: tuple[int, int]
) -> tuple[tuple[float, float, float, int] | None, float, float, float]:
    """Ericson's test of a corner X of triangle A, X, Y and of its edge AX: B with edge AB, or C with edge
    AC, the same test with the triangle's two edges from A (``own`` = X − A, ``other`` = Y − A) swapped.

    ``a_dots`` are (own·(p − A), other·(p − A)); ``regions`` the region codes of the corner and the edge.
    Returns the closest point and its region when p lies in either (else ``None``), then own·(p − X),
    other·(p − X) and the barycentric area the face test reads (Ericson's vc for B, vb for C)."""
    (px, py, pz), (ax, ay, az), (xx, xy, xz), (ox, oy, oz), (tx, ty, tz) = p, a, x, own, other
    qx, qy, qz = px - xx, py - xy, pz - xz
    d_own = ox * qx + oy * qy + oz * qz
    d_other = tx * qx + ty * qy + tz * qz
    if d_own >= 0.0 and d_other <= d_own:
        return (xx, xy, xz, regions[0]), d_own, d_other, 0.0
    area = a_dots[0] * d_other - d_own * a_dots[1]
    if area <= 0.0 and a_dots[0] >= 0.0 and d_own <= 0.0:
        v = a_dots[0] / (a_dots[0] - d_own)
        return (ax + v * ox, ay + v * oy, az + v * oz, regions[1]), d_own, d_other, area
    return None, d_own, d_other, area


def _closest_on_triangle(
    px: float, py: float, pz: float, tri: Sequence[Sequence[float]]
) -> tuple[float, float, float, int]:
    """Closest point of a triangle to p, and its region: 0 face, 1/2/3 vertex A/B/C, 4/5/6 edge AB/BC/CA.

    Ericson, Real-Time Collision Detection, 5.1.5, on Python floats: cheaper than numpy for one triangle.
    Its tests of corner B with edge AB and of corner C with edge CA are one (:func:`_corner_region`).
    """
    (ax, ay, az), (bx, by, bz), (cx, cy, cz) = tri
    abx, aby, abz = bx - ax, by - ay, bz - az
    acx, acy, acz = cx - ax, cy - ay, cz - az
    apx, apy, apz = px - ax, py - ay, pz - az
    d1 = abx * apx + aby * apy + abz * apz
    d2 = acx * apx + acy * apy + acz * apz
    if d1 <= 0.0 and d2 <= 0.0:
        return ax, ay, az, 1
    p, a, ab, ac = (px, py, pz), (ax, ay, az), (abx, aby, abz), (acx, acy, acz)
    hit, d3, d4, vc = _corner_region(p, a, (bx, by, bz), ab, ac, (d1, d2), (2, 4))
    if hit is not None:
        return hit
    hit, d6, d5, vb = _corner_region(p, a, (cx, cy, cz), ac, ab, (d2, d1), (3, 6))
    if hit is not None:
        return hit
    va = d3 * d6 - d5 * d4
    if va <= 0.0 and (d4 - d3) >= 0.0 and (d5 - d6) >= 0.0:
        w = (d4 - d3) / ((d4 - d3) + (d5 - d6))
        return bx + w * (cx - bx), by + w * (cy - by), bz + w * (cz - bz), 5
    denom = va + vb + vc
    if denom == 0.0:  # degenerate triangle: fall back to its first vertex
        return ax, ay, az, 1
    v = vb / denom
    w = vc / denom
    return ax + abx * v + acx * w, ay + aby * v + acy * w, az + abz * v + acz * w, 0


class _WindingNumber:
    """Generalised winding number of an (open or self-intersecting) triangle soup, two-level fast version:
    exact solid angles for clusters within ``beta`` cluster radii of the point, dipoles beyond."""

    def __init__(
        self, vertices: np.ndarray, faces: np.ndarray, leaf_size: int = 16, beta: float = 2.0
    ) -> None:
        a, b, c = vertices[faces[:, 0]], vertices[faces[:, 1]], vertices[faces[:, 2]]
        centroids = (a + b + c) / 3.0
        leaves: list[np.ndarray] = []
        stack = [np.arange(len(faces))]
        while stack:
            ids = stack.pop()
            if len(ids) <= leaf_size:
                leaves.append(ids)
                continue
            pts = centroids[ids]
            axis = int(np.argmax(np.ptp(pts, axis=0)))
            order = np.argsort(pts[:, axis], kind="stable")
            half = len(ids) // 2
            stack.append(ids[order[:half]])
            stack.append(ids[order[half:]])
        area_vec = 0.5 * np.cross(b - a, c - a)
        area = np.linalg.norm(area_vec, axis=1)
        n_leaves = len(leaves)
        width = max(len(x) for x in leaves)
        table = np.full((n_leaves, width), len(faces), dtype=np.int64)
        self.centre = np.empty((n_leaves, 3))
        self.radius = np.empty(n_leaves)
        self.dipole = np.empty((n_leaves, 3))
        for i, ids in enumerate(leaves):
            table[i, : len(ids)] = ids
            w = area[ids]
            centre = (centroids[ids] * w[:, None]).sum(0) / max(w.sum(), 1e-300)
            corners = np.concatenate((a[ids], b[ids], c[ids]))
            self.centre[i] = centre
            self.radius[i] = float(np.sqrt(((corners - centre) ** 2).sum(1)).max())
            self.dipole[i] = area_vec[ids].sum(0)
        far = np.full((1, 3), _SENTINEL_COORD)
        self.a = np.concatenate((a, far))
        self.b = np.concatenate((b, far))
        self.c = np.concatenate((c, far))
        self.table = table
        self.width = width
        self.beta = float(beta)

    def __call__(self, points: np.ndarray) -> np.ndarray:
        p = np.atleast_2d(points)
        if len(p) > 8 and float(np.ptp(p, axis=0).max()) > 20.0:
            # Points far apart share few near clusters; evaluate spatially sorted chunks.
            order = np.lexsort((p[:, 2], p[:, 1], p[:, 0]))
            out = np.empty(len(p))
            for start in range(0, len(p), 8):
                chunk = order[start : start + 8]
                out[chunk] = self._evaluate(p[chunk])
            return out
        return self._evaluate(p)

    def _evaluate(self, p: np.ndarray) -> np.ndarray:
        d = p[:, None, :] - self.centre[None, :, :]  # (N, L, 3) from centre to point
        dist = np.sqrt(np.einsum("nlk,nlk->nl", d, d))
        near = dist < self.beta * self.radius[None, :]
        safe = np.where(near, 1.0, dist)
        far_term = -np.einsum("nlk,lk->nl", d, self.dipole) / safe**3
        total = np.where(near, 0.0, far_term).sum(axis=1)
        leaves = np.flatnonzero(near.any(axis=0))
        if leaves.size:
            tris = self.table[leaves].ravel()
            pa = self.a[tris][None, :, :] - p[:, None, :]
            pb = self.b[tris][None, :, :] - p[:, None, :]
            pc = self.c[tris][None, :, :] - p[:, None, :]
            la = np.sqrt(np.einsum("ntk,ntk->nt", pa, pa))
            lb = np.sqrt(np.einsum("ntk,ntk->nt", pb, pb))
            lc = np.sqrt(np.einsum("ntk,ntk->nt", pc, pc))
            num = np.einsum("ntk,ntk->nt", pa, np.cross(pb, pc))
            den = (
                la * lb * lc
                + np.einsum("ntk,ntk->nt", pa, pb) * lc
                + np.einsum("ntk,ntk->nt", pa, pc) * lb
                + np.einsum("ntk,ntk->nt", pb, pc) * la
            )
            omega = 2.0 * np.arctan2(num, den)
            mask = np.repeat(near[:, leaves], self.width, axis=1)
            total = total + np.where(mask, omega, 0.0).sum(axis=1)
        winding: np.ndarray = total / (4.0 * math.pi)
        return winding


def _refine_long_edges(
    vertices: np.ndarray, faces: np.ndarray, max_len: float, rounds: int = 16
) -> tuple[np.ndarray, np.ndarray]:
    """Split every edge longer than ``max_len`` at its midpoint, conformingly (both triangles of an edge are
    split, so a closed mesh stays closed), until none is left.  The surface is unchanged; only its
    triangles get small enough for vertex samples to cover them."""
    v, f = vertices, faces
    for _ in range(rounds):
        n_v = len(v)
        he = np.stack((f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]), axis=1).reshape(-1, 2)
        key = np.minimum(he[:, 0], he[:, 1]) * np.int64(n_v) + np.maximum(he[:, 0], he[:, 1])
        uniq, inverse = np.unique(key, return_inverse=True)
        inverse = inverse.ravel()
        ea, eb = uniq // n_v, uniq % n_v
        long_edge = np.linalg.norm(v[ea] - v[eb], axis=1) > max_len
        if not long_edge.any():
            break
        mid_id = np.full(len(uniq), -1, dtype=np.int64)
        mid_id[long_edge] = n_v + np.arange(int(long_edge.sum()))
        v = np.concatenate((v, (v[ea[long_edge]] + v[eb[long_edge]]) / 2.0))
        m = mid_id[inverse].reshape(-1, 3)  # midpoint of edge k (v_k -> v_k+1), -1 if kept
        split = m >= 0
        n_split = split.sum(axis=1)
        out = [f[n_split == 0]]
        # One split: roll so that it is edge 0, then bisect from the opposite vertex.
        sel = np.flatnonzero(n_split == 1)
        if sel.size:
            k = np.argmax(split[sel], axis=1)
            rows = np.arange(3)[None, :]
            idx = (rows + k[:, None]) % 3
            fv = np.take_along_axis(f[sel], idx, axis=1)
            mm = np.take_along_axis(m[sel], idx, axis=1)[:, 0]
            out.append(np.stack((fv[:, 0], mm, fv[:, 2]), axis=1))
            out.append(np.stack((mm, fv[:, 1], fv[:, 2]), axis=1))
        # Two splits: roll so that the kept edge is edge 2.
        sel = np.flatnonzero(n_split == 2)
        if sel.size:
            kept = np.argmin(split[sel], axis=1)
            idx = (np.arange(3)[None, :] + (kept[:, None] + 1)) % 3
            fv = np.take_along_axis(f[sel], idx, axis=1)
            mm = np.take_along_axis(m[sel], idx, axis=1)
            m0, m1 = mm[:, 0], mm[:, 1]
            out.append(np.stack((m0, fv[:, 1], m1), axis=1))
            out.append(np.stack((fv[:, 0], m0, m1), axis=1))
            out.append(np.stack((fv[:, 0], m1, fv[:, 2]), axis=1))
        # Three splits: four similar triangles.
        sel = np.flatnonzero(n_split == 3)
        if sel.size:
            fv, mm = f[sel], m[sel]
            out.append(np.stack((fv[:, 0], mm[:, 0], mm[:, 2]), axis=1))
            out.append(np.stack((mm[:, 0], fv[:, 1], mm[:, 1]), axis=1))
            out.append(np.stack((mm[:, 2], mm[:, 1], fv[:, 2]), axis=1))
            out.append(np.stack((mm[:, 0], mm[:, 1], mm[:, 2]), axis=1))
        f = np.concatenate(out)
    return v, f


# Rows of the per-triangle linear map r = G @ (p, 1) used by the distance kernel.
_R_SQ = slice(0, 3)  # |p - S_k|^2 - |p|^2 for the edge starts A, B, C
_R_T = slice(3, 6)  # edge parameter t_k of p's projection on edge k, unclamped
_R_S2 = slice(6, 9)  # 2 (p - S_k) . D_k
_R_L2 = slice(9, 12)  # |D_k|^2 (constant rows)
_R_BARY = slice(12, 15)  # barycentric (u, v, w) of p's projection on the plane
_R_PD = 15  # signed distance of p to the plane
_N_ROWS = 16


def _sign_method_for(topo: _Topology, sign_method: str) -> str:
    """``auto`` → pseudonormals on a closed mesh, the winding number otherwise; refuse what cannot work."""
    if sign_method == "auto":
        sign_method = "pseudonormal" if topo.watertight else "winding"
    if sign_method not in ("pseudonormal", "winding"):
        raise ConfigurationError(f"sign_method={sign_method!r} must be 'auto', 'pseudonormal' or 'winding'")
    if sign_method == "pseudonormal" and not topo.watertight:
        raise ConfigurationError(
            "sign_method='pseudonormal' needs a closed, consistently oriented mesh; use 'winding' or 'auto'"
        )
    return sign_method


def _sample_spacing(vertices: np.ndarray, topo: _Topology, sample_spacing_mm: float | None) -> float:
    """The longest edge the index keeps (longer ones are split): twice the median edge unless given."""
    if sample_spacing_mm is None:
        edge_len = np.linalg.norm(vertices[topo.edges[:, 0]] - vertices[topo.edges[:, 1]], axis=1)
        return 2.0 * float(np.median(edge_len))
    spacing = float(sample_spacing_mm)
    if not math.isfinite(spacing) or spacing <= 0:
        raise ConfigurationError(f"sample_spacing_mm={sample_spacing_mm!r} must be a positive length")
    return spacing


def _kernel_rows(a: np.ndarray, b: np.ndarray, c: np.ndarray, face_normals: np.ndarray) -> np.ndarray:
    """The distance kernel's rows per triangle (see ``_R_*``): every quantity but the clamping is linear
    in the query point.  One extra sentinel triangle, far away, pads the vertex-to-triangle table."""
    n_faces = len(a)
    e1, e2 = b - a, c - a
    starts = np.stack((a, b, c), axis=1)  # (F, 3, 3)
    dirs = np.stack((b - a, c - b, a - c), axis=1)
    l2 = np.einsum("fkj,fkj->fk", dirs, dirs)
    rows = np.zeros((n_faces + 1, _N_ROWS, 4))  # the last row is the sentinel
    g = rows[:n_faces]
    g[:, _R_SQ, 0:3] = -2.0 * starts
    g[:, _R_SQ, 3] = np.einsum("fkj,fkj->fk", starts, starts)
    g[:, _R_T, 0:3] = dirs / l2[:, :, None]
    g[:, _R_T, 3] = -np.einsum("fkj,fkj->fk", starts, dirs) / l2
    g[:, _R_S2, 0:3] = 2.0 * dirs
    g[:, _R_S2, 3] = -2.0 * np.einsum("fkj,fkj->fk", starts, dirs)
    g[:, _R_L2, 3] = l2
    g11 = np.einsum("ij,ij->i", e1, e1)
    g12 = np.einsum("ij,ij->i", e1, e2)
    g22 = np.einsum("ij,ij->i", e2, e2)
    det = g11 * g22 - g12 * g12
    mu = (g22[:, None] * e1 - g12[:, None] * e2) / det[:, None]
    mv = (g11[:, None] * e2 - g12[:, None] * e1) / det[:, None]
    g[:, 12, 0:3], g[:, 12, 3] = mu, -np.einsum("ij,ij->i", mu, a)
    g[:, 13, 0:3], g[:, 13, 3] = mv, -np.einsum("ij,ij->i", mv, a)
    g[:, 14, 0:3] = -(mu + mv)
    g[:, 14, 3] = 1.0 - g[:, 12, 3] - g[:, 13, 3]
    g[:, _R_PD, 0:3] = face_normals
    g[:, _R_PD, 3] = -np.einsum("ij,ij->i", face_normals, a)
    rows[n_faces, _R_SQ, 3] = _SENTINEL_COORD
    rows[n_faces, _R_L2, 3] = 1.0
    rows[n_faces, _R_BARY, 3] = -1.0
    return rows


def _triangle_bounds(
    a: np.ndarray, b: np.ndarray, c: np.ndarray, cross: np.ndarray, face_normals: np.ndarray
) -> tuple[float, np.ndarray]:
    """The largest vertex-covering radius, and per triangle (plus the sentinel) its bounding sphere and
    plane, for pruning candidate pairs in batched tests: columns centre (3), radius, normal (3), offset."""
    # Every point of a triangle lies within its vertex-covering radius (circumradius when acute,
    # half the longest edge otherwise) of one of its vertices.
    dirs = np.stack((b - a, c - b, a - c), axis=1)
    l2 = np.einsum("fkj,fkj->fk", dirs, dirs)  # as the kernel rows compute it, to the last bit
    la, lb, lc = (np.sqrt(l2[:, k]) for k in range(3))
    area2 = np.linalg.norm(cross, axis=1)
    circum = la * lb * lc / np.maximum(2.0 * area2, 1e-300)
    longest = np.maximum(np.maximum(la, lb), lc)
    obtuse = 2.0 * longest**2 >= la**2 + lb**2 + lc**2
    cover = np.where(obtuse, longest / 2.0, circum)
    centre = (a + b + c) / 3.0
    radius = np.sqrt(
        np.maximum(
            np.maximum(((a - centre) ** 2).sum(1), ((b - centre) ** 2).sum(1)), ((c - centre) ** 2).sum(1)
        )
    )
    far = np.zeros((1, 8))
    far[0, 0:3] = _SENTINEL_COORD  # the sentinel triangle: never within reach
    own = np.concatenate(
        (centre, radius[:, None], face_normals, np.einsum("ij,ij->i", face_normals, a)[:, None]), axis=1
    )
    return float(cover.max()), np.concatenate((own, far))


def _vertex_samples(v: np.ndarray, f: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The samples and their triangle table: the vertices, each standing for its incident triangles
    (vertices with many get several samples so that the table stays narrow); padding is the sentinel."""
    n_faces = len(f)
    corner_vertex = f.ravel()
    corner_face = np.repeat(np.arange(n_faces), 3)
    order = np.argsort(corner_vertex, kind="stable")
    counts = np.bincount(corner_vertex, minlength=len(v))
    width = int(min(max(int(np.percentile(counts, 99)), 4), 16))
    rows_per_vertex = np.maximum(1, -(-counts // width))
    sample_vertex = np.repeat(np.arange(len(v)), rows_per_vertex)
    table = np.full((len(sample_vertex), width), n_faces, dtype=np.int64)
    first_row = np.concatenate(([0], np.cumsum(rows_per_vertex)[:-1]))
    vstart = np.concatenate(([0], np.cumsum(counts)[:-1]))
    rank = np.arange(len(corner_vertex)) - vstart[corner_vertex[order]]
    table_row = first_row[corner_vertex[order]] + rank // width
    table[table_row, rank % width] = corner_face[order]
    return table, v[sample_vertex]


def _pseudonormals(
    v: np.ndarray,
    f: np.ndarray,
    a: np.ndarray,
    b: np.ndarray,
    c: np.ndarray,
    face_normals: np.ndarray,
    topo: _Topology,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Edge and angle-weighted vertex pseudonormals (the sign of a closed mesh), and each face's edges."""
    ef = topo.edge_faces
    edge_pn = face_normals[ef[:, 0]] + face_normals[ef[:, 1]]
    angles = np.empty((len(f), 3))
    for k, (u, w) in enumerate(((b - a, c - a), (c - b, a - b), (a - c, b - c))):
        cosang = np.einsum("ij,ij->i", u, w) / (np.linalg.norm(u, axis=1) * np.linalg.norm(w, axis=1))
        angles[:, k] = np.arccos(np.clip(cosang, -1.0, 1.0))
    vpn = np.zeros((len(v), 3))
    for k in range(3):
        for axis in range(3):
            vpn[:, axis] += np.bincount(
                f[:, k], weights=angles[:, k] * face_normals[:, axis], minlength=len(v)
            )
    return edge_pn, topo.face_edges, vpn


class _Index:
    """Everything a closest-triangle query needs, built once per mesh (in coordinates centred on the
    mesh, so the expanded squared distances keep their precision)."""

    def __init__(
        self,
        vertices: np.ndarray,
        faces: np.ndarray,
        topo: _Topology,
        sample_spacing_mm: float | None,
        sign_method: str,
    ) -> None:
        spatial = _scipy_spatial()
        self.sign_method = sign_method = _sign_method_for(topo, sign_method)
        self.origin = (vertices.min(axis=0) + vertices.max(axis=0)) / 2.0
        self.spacing_mm = spacing = _sample_spacing(vertices, topo, sample_spacing_mm)
        v, f = _refine_long_edges(vertices - self.origin, faces, spacing)
        self.vertices = v  # local (centred) coordinates
        self.faces = f
        self.original_triangles = len(faces)
        n_faces = len(f)
        a, b, c = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
        cross = np.cross(b - a, c - a)
        self.face_normals = cross / np.linalg.norm(cross, axis=1)[:, None]
        self.rows = _kernel_rows(a, b, c, self.face_normals)
        self.sentinel = n_faces
        self._stamp = np.zeros(n_faces + 1, dtype=np.int32)
        self.cover_mm, self.tri_bounds = _triangle_bounds(a, b, c, cross, self.face_normals)
        self.table, self.samples = _vertex_samples(v, f)
        self.tree = spatial.cKDTree(self.samples)

        self.winding: _WindingNumber | None = None
        self.topology = rtopo = _topology(f, len(v))
        if sign_method == "pseudonormal":
            self.edge_pn, self.face_edges, self.vertex_pn = _pseudonormals(
                v, f, a, b, c, self.face_normals, rtopo
            )
        else:
            self.winding = _WindingNumber(v, f)
        # Vertices on the border of a hole (open meshes only): near them inside and outside are the
        # winding number's call, not a matter of crossing the surface.
        open_vertices = np.unique(rtopo.edges[rtopo.edge_count == 1].ravel())
        self.hole_tree = spatial.cKDTree(v[open_vertices]) if open_vertices.size else None

        # Coherence hint: the closest point of the previous query (on the surface, so an upper bound).
        self._hint_point: np.ndarray | None = None
        self._hint_closest: np.ndarray | None = None
        self._hint_distance = 0.0
        self._sign_point: np.ndarray | None = None
        self._sign_inside = False
        self._sign_radius = 0.0

    @property
    def n_triangles(self) -> int:
        return len(self.faces)

    def _upper_bound(self, p: np.ndarray) -> float:
        """A distance from p (local coordinates) to a point on the surface: at least the true distance."""
        if self._hint_point is not None:
            moved = p - self._hint_point
            step = math.sqrt(float(moved @ moved))
            gap_p = p - self._hint_closest
            upper = math.sqrt(float(gap_p @ gap_p))  # the old closest point is on the surface
            lower = self._hint_distance - step  # the distance is 1-Lipschitz
            if upper - lower <= 2.0 * self.cover_mm:
                return upper * (1.0 + 1e-9) + 1e-9
        d1, _ = self.tree.query(p)
        return float(d1) * (1.0 + 1e-9) + 1e-9

    def closest_triangle(self, p: np.ndarray) -> int:
        """The triangle closest to p (local coordinates), exactly."""
        upper = self._upper_bound(p)
        ids = self.tree.query_ball_point(p, upper + self.cover_mm)
        tris = self.table[ids].ravel()
        if len(tris) > 96:
            tris = self.dedupe(tris)
            # Far from the surface the ball holds many triangles; drop those whose bounding sphere
            # stays beyond the upper bound before the full kernel.
            b = self.tri_bounds[tris]
            d = b[:, 0:3] - p
            reach = upper + b[:, 3]
            tris = tris[(d * d).sum(axis=1) <= reach * reach]
        r = self.rows[tris] @ np.array((p[0], p[1], p[2], 1.0))
        t = _maximum(_minimum(r[:, _R_T], 1.0), 0.0)
        d2e = (t * r[:, _R_L2] - r[:, _R_S2]) * t + r[:, _R_SQ]
        bary = r[:, _R_BARY]
        inside = _minimum(_minimum(bary[:, 0], bary[:, 1]), bary[:, 2]) >= 0.0
        pd = r[:, _R_PD]
        d2 = _where(inside, pd * pd - float(p @ p), _minimum(_minimum(d2e[:, 0], d2e[:, 1]), d2e[:, 2]))
        return int(tris[d2.argmin()])

    def dedupe(self, tris: np.ndarray) -> np.ndarray:
        """Distinct triangles of a candidate list (order free): scatter positions, keep the winners.
        Cheaper than np.unique's sort for the few thousand candidates of a far query."""
        stamp = self._stamp
        positions = np.arange(len(tris), dtype=np.int32)
        stamp[tris] = positions
        unique: np.ndarray = tris[stamp[tris] == positions]
        return unique

    def closest_triangles(self, points: np.ndarray) -> np.ndarray:
        """Vectorised over points (local coordinates): one kernel pass over all their candidates."""
        d1, _ = self.tree.query(points)
        balls = self.tree.query_ball_point(points, d1 * (1.0 + 1e-9) + self.cover_mm + 1e-9)
        sizes = np.fromiter((len(b) for b in balls), dtype=np.int64, count=len(balls))
        ids = np.fromiter((i for b in balls for i in b), dtype=np.int64, count=int(sizes.sum()))
        tris = self.table[ids].ravel()
        owner = np.repeat(np.arange(len(points)), sizes * self.table.shape[1])
        ph = np.concatenate((points, np.ones((len(points), 1))), axis=1)
        r = np.einsum("mij,mj->mi", self.rows[tris], ph[owner])
        t = np.clip(r[:, _R_T], 0.0, 1.0)
        d2e = (t * r[:, _R_L2] - r[:, _R_S2]) * t + r[:, _R_SQ]
        pd = r[:, _R_PD]
        pp = np.einsum("ij,ij->i", points, points)[owner]
        d2 = np.where(r[:, _R_BARY].min(axis=1) >= 0.0, pd * pd - pp, d2e.min(axis=1))
        order = np.lexsort((d2, owner))
        first = np.concatenate(([0], np.flatnonzero(np.diff(owner[order])) + 1))
        return tris[order[first]]

    def finish(
        self, p: np.ndarray, tri: int, remember: bool = True
    ) -> tuple[float, np.ndarray, np.ndarray, int]:
        """Signed distance, closest point (local), outward normal and region code for the closest triangle."""
        px, py, pz = float(p[0]), float(p[1]), float(p[2])
        qx, qy, qz, region = _closest_on_triangle(px, py, pz, self.vertices[self.faces[tri]].tolist())
        dx, dy, dz = px - qx, py - qy, pz - qz
        dist = math.sqrt(dx * dx + dy * dy + dz * dz)
        if self.winding is None:
            pn = self._pseudo_normal(tri, region)
            inside = dx * pn[0] + dy * pn[1] + dz * pn[2] < 0.0
        else:
            pn = self.face_normals[tri]
            inside = self._winding_inside(p)
        if dist > 1e-9:
            s = -1.0 if inside else 1.0
            normal = np.array((s * dx / dist, s * dy / dist, s * dz / dist))
        else:
            normal = pn / math.sqrt(float(pn @ pn))
        closest = np.array((qx, qy, qz))
        if remember:
            self._hint_point = p.copy()
            self._hint_closest = closest
            self._hint_distance = dist
            if (
                self.winding is not None
                and self._sign_point is not None
                and np.array_equal(self._sign_point, p)
            ):
                self._sign_radius = dist
        return (-dist if inside else dist), closest, normal, region

    def _winding_inside(self, p: np.ndarray) -> bool:
        """Winding-number inside test, skipped when the previous answer still holds: a point that moved
        less than its previous distance to the surface cannot have crossed it (the distance is
        1-Lipschitz), so it keeps the previous side."""
        if self._sign_point is not None:
            moved = p - self._sign_point
            if math.sqrt(float(moved @ moved)) < self._sign_radius:
                return self._sign_inside
        assert self.winding is not None
        inside = bool(self.winding(p)[0] >= 0.5)
        self._sign_point = p.copy()
        self._sign_inside = inside
        self._sign_radius = 0.0
        return inside

    def _pseudo_normal(self, tri: int, region: int) -> np.ndarray:
        pn: np.ndarray
        if region == 0:
            pn = self.face_normals[tri]
        elif region <= 3:
            pn = self.vertex_pn[self.faces[tri, region - 1]]
        else:
            pn = self.edge_pn[self.face_edges[tri, region - 4]]
        return pn

    def inside(self, points: np.ndarray) -> np.ndarray:
        """Inside test for many points (local coordinates): on or inside the surface is inside."""
        if self.winding is not None:
            out: np.ndarray = self.winding(points) >= 0.5
            return out
        n = len(points)
        d1, _ = self.tree.query(points)
        centre = points.mean(axis=0)
        spread = float(np.sqrt(((points - centre) ** 2).sum(axis=1).max()))
        # Every point is at least d1 - cover from the surface.  If that exceeds the cloud's diameter, no
        # surface runs between the points: they all lie on the side of the first one.
        if float(d1.min()) - self.cover_mm > 2.0 * spread:
            sd = self.finish(points[0], self.closest_triangle(points[0]), remember=False)[0]
            return np.full(n, sd <= 0.0)
        radius = spread + float(d1.max()) + self.cover_mm + 1e-9
        ids = self.tree.query_ball_point(centre, radius)
        if n * len(ids) > 40_000:  # a cloud spread over much of the mesh: point by point
            return self._inside_each(points)
        shared = self.dedupe(self.table[ids].ravel())
        shared = shared[shared != self.sentinel]
        bounds = self.tri_bounds[shared]
        m, rho, nrm, off = bounds[:, 0:3], bounds[:, 3], bounds[:, 4:7], bounds[:, 7]
        pp = (points * points).sum(axis=1)
        centre_d2 = pp[:, None] - 2.0 * (points @ m.T) + (m * m).sum(axis=1)[None, :]
        # An upper bound close to the answer: the exact distance to the triangle whose centre is nearest.
        nearest = shared[np.argmin(centre_d2, axis=1)]
        ph = np.concatenate((points, np.ones((n, 1))), axis=1)
        upper = np.sqrt(np.maximum(self._pair_sq_distances(self.rows[nearest], ph, pp), 0.0)) + 1e-9
        # Keep pairs whose lower bounds (bounding sphere, plane) do not exceed it.
        reach = upper[:, None] + rho[None, :]
        plane = points @ nrm.T - off[None, :]
        owner, col = np.nonzero((centre_d2 <= reach * reach) & (np.abs(plane) <= upper[:, None]))
        tris = shared[col]
        r = np.einsum("mij,mj->mi", self.rows[tris], ph[owner])
        t = _maximum(_minimum(r[:, _R_T], 1.0), 0.0)
        d2e = (t * r[:, _R_L2] - r[:, _R_S2]) * t + r[:, _R_SQ]
        bary = r[:, _R_BARY]
        face = bary.min(axis=1) >= 0.0
        d2 = np.where(face, r[:, _R_PD] ** 2 - pp[owner], d2e.min(axis=1))
        order = np.lexsort((d2, owner))
        first = order[np.concatenate(([0], np.flatnonzero(np.diff(owner[order])) + 1))]
        # Closest feature of each point's closest triangle, and the side of its pseudo-normal.
        best = tris[first]
        k = np.argmin(d2e[first], axis=1)
        tk = t[first, k]
        on_face = face[first]
        corner = np.where(tk <= 0.0, k, (k + 1) % 3)
        at_vertex = ~on_face & ((tk <= 0.0) | (tk >= 1.0))
        tri_v = self.vertices[self.faces[best]]  # (n, 3, 3)
        start = tri_v[np.arange(n), k]
        end = tri_v[np.arange(n), (k + 1) % 3]
        q_edge = start + tk[:, None] * (end - start)
        q_face = points - r[first, _R_PD][:, None] * self.face_normals[best]
        q = np.where(on_face[:, None], q_face, q_edge)
        pn = np.where(
            on_face[:, None],
            self.face_normals[best],
            np.where(
                at_vertex[:, None],
                self.vertex_pn[self.faces[best, corner]],
                self.edge_pn[self.face_edges[best, k]],
            ),
        )
        inside: np.ndarray = ((points - q) * pn).sum(axis=1) <= 0.0
        return inside

    @staticmethod
    def _pair_sq_distances(rows: np.ndarray, ph: np.ndarray, pp: np.ndarray) -> np.ndarray:
        """Squared distances of point i (homogeneous ``ph[i]``, ``pp[i] = |p|²``) to triangle ``rows[i]``."""
        r = np.einsum("mij,mj->mi", rows, ph)
        t = _maximum(_minimum(r[:, _R_T], 1.0), 0.0)
        d2e = ((t * r[:, _R_L2] - r[:, _R_S2]) * t + r[:, _R_SQ]).min(axis=1)
        face = r[:, _R_BARY].min(axis=1) >= 0.0
        out: np.ndarray = np.where(face, r[:, _R_PD] ** 2, d2e + pp)
        return out

    def _inside_each(self, points: np.ndarray) -> np.ndarray:
        tris = self.closest_triangles(points)
        out = np.empty(len(points), dtype=bool)
        for i, (p, tri) in enumerate(zip(points.tolist(), tris.tolist())):
            qx, qy, qz, region = _closest_on_triangle(
                p[0], p[1], p[2], self.vertices[self.faces[tri]].tolist()
            )
            pn = self._pseudo_normal(tri, region)
            out[i] = (p[0] - qx) * pn[0] + (p[1] - qy) * pn[1] + (p[2] - qz) * pn[2] <= 0.0
        return out


# --- features -----------------------------------------------------------------------------------------


class _Features:
    """Sharp edges and corners of a mesh, and the search for the nearest of them."""

    def __init__(
        self,
        vertices: np.ndarray,
        faces: np.ndarray,
        topo: _Topology,
        face_normals: np.ndarray,
        *,
        sharp_angle_deg: float,
        min_chain_mm: float,
        concave_edges: bool,
        boundary_edges_sharp: bool,
        corner_turn_deg: float,
        tip_window_mm: float = 10.0,
    ) -> None:
        edges, ef, counts = topo.edges, topo.edge_faces, topo.edge_count
        two = counts == 2
        n1 = face_normals[ef[:, 0]]
        n2 = face_normals[np.where(ef[:, 1] >= 0, ef[:, 1], ef[:, 0])]
        dihedral = np.degrees(np.arccos(np.clip(np.einsum("ij,ij->i", n1, n2), -1.0, 1.0)))
        # Convex when the far vertex of the second face lies below the first face's plane.
        f2 = faces[np.where(ef[:, 1] >= 0, ef[:, 1], ef[:, 0])]
        far = np.where(
            (f2[:, 0] != edges[:, 0]) & (f2[:, 0] != edges[:, 1]),
            f2[:, 0],
            np.where((f2[:, 1] != edges[:, 0]) & (f2[:, 1] != edges[:, 1]), f2[:, 1], f2[:, 2]),
        )
        convex = np.einsum("ij,ij->i", n1, vertices[far] - vertices[edges[:, 0]]) < 0.0
        sharp = two & (dihedral >= sharp_angle_deg) & (convex | bool(concave_edges))
        if boundary_edges_sharp:
            sharp |= counts == 1
        self.dihedral_deg = np.where(two, dihedral, np.nan)
        cand = np.flatnonzero(sharp)
        kept = cand
        if cand.size and min_chain_mm > 0:
            kept = self._long_chains(vertices, edges, cand, min_chain_mm, len(vertices))
        self.sharp_edges = kept
        seg = edges[kept]
        self.seg_a = vertices[seg[:, 0]] if kept.size else np.empty((0, 3))
        d = vertices[seg[:, 1]] - vertices[seg[:, 0]] if kept.size else np.empty((0, 3))
        length = np.linalg.norm(d, axis=1)
        self.seg_d = d
        self.seg_inv_len2 = 1.0 / np.maximum(length * length, 1e-300)
        self.seg_dir = d / np.maximum(length, 1e-300)[:, None]
        seg_normals = n1[kept] + np.where(two[kept, None], n2[kept], 0.0) if kept.size else np.empty((0, 3))
        norms = np.linalg.norm(seg_normals, axis=1)
        self.seg_normal = seg_normals / np.where(norms > 0, norms, 1.0)[:, None]
        valence = (
            np.bincount(seg.ravel(), minlength=len(vertices)) if kept.size else np.zeros(len(vertices), int)
        )
        corners = valence >= 3
        two_v = np.flatnonzero(valence == 2)
        if two_v.size:
            self._bent_corners(seg, d, length, two_v, corners, corner_turn_deg, tip_window_mm)
        self.valence = valence
        self.corner_vertices = np.flatnonzero(corners)
        self.corner_points = vertices[self.corner_vertices]

    @staticmethod
    def _bent_corners(
        seg: np.ndarray,
        d: np.ndarray,
        length: np.ndarray,
        two_v: np.ndarray,
        corners: np.ndarray,
        corner_turn_deg: float,
        tip_window_mm: float,
    ) -> None:
        """Mark in ``corners`` the vertices where a chain of two sharp edges bends by ``corner_turn_deg``,
        or turns that much in all within ``tip_window_mm`` along the chain (a rounded tip)."""
        # Turning angle where a chain of two sharp edges bends.
        inc: dict[int, list[np.ndarray]] = {int(v): [] for v in two_v}
        nbrs: dict[int, list[tuple[int, float]]] = {int(v): [] for v in two_v}
        for (va, vb), dvec, ln in zip(seg.tolist(), d, length.tolist()):
            if va in inc:
                inc[va].append(dvec)
                nbrs[va].append((vb, ln))
            if vb in inc:
                inc[vb].append(-dvec)
                nbrs[vb].append((va, ln))
        turns: dict[int, float] = {}
        for v, vecs in inc.items():
            u, w = vecs[0], vecs[1]
            cosang = float(np.dot(u, w) / (np.linalg.norm(u) * np.linalg.norm(w)))
            turn = 180.0 - math.degrees(math.acos(max(-1.0, min(1.0, cosang))))
            turns[v] = turn
            if turn >= corner_turn_deg:
                corners[v] = True
        # Tips: the turning summed along the chain within half the window on each side.
        half = tip_window_mm / 2.0
        if half > 0:
            for v in turns:
                total = turns[v]
                for first, step in nbrs[v]:
                    prev, cur, dist = v, first, step
                    while dist <= half and cur in turns and cur != v:
                        total += turns[cur]
                        a_, b_ = nbrs[cur]
                        nxt, ln = a_ if a_[0] != prev else b_
                        prev, cur, dist = cur, nxt, dist + ln
                if total >= corner_turn_deg:
                    corners[v] = True

    @staticmethod
    def _long_chains(
        vertices: np.ndarray, edges: np.ndarray, cand: np.ndarray, min_len: float, n_vertices: int
    ) -> np.ndarray:
        sparse = _scipy_sparse()
        seg = edges[cand]
        graph = sparse.coo_matrix(
            (np.ones(len(cand)), (seg[:, 0], seg[:, 1])), shape=(n_vertices, n_vertices)
        ).tocsr()
        _, labels = sparse.csgraph.connected_components(graph, directed=False)
        comp = labels[seg[:, 0]]
        lengths = np.linalg.norm(vertices[seg[:, 1]] - vertices[seg[:, 0]], axis=1)
        total = np.bincount(comp, weights=lengths)
        kept: np.ndarray = cand[total[comp] >= min_len]
        return kept

    def build_lookup(self, band_mm: float) -> None:
        """Hash the corners and sharp edges into cubic cells so that a contact far from every feature
        (the usual case) is recognised as a face by one dictionary look-up."""
        cell = max(2.0 * band_mm, 1.0)
        grid: dict[tuple[int, int, int], tuple[list[int], list[int]]] = {}

        def cells(lo: np.ndarray, hi: np.ndarray) -> list[tuple[int, int, int]]:
            a = np.floor(lo / cell).astype(int)
            b = np.floor(hi / cell).astype(int)
            return [
                (i, j, k)
                for i in range(a[0], b[0] + 1)
                for j in range(a[1], b[1] + 1)
                for k in range(a[2], b[2] + 1)
            ]

        for i, point in enumerate(self.corner_points):
            for key in cells(point - band_mm, point + band_mm):
                grid.setdefault(key, ([], []))[0].append(i)
        ends = self.seg_a + self.seg_d
        for i in range(len(self.seg_a)):
            lo = np.minimum(self.seg_a[i], ends[i]) - band_mm
            hi = np.maximum(self.seg_a[i], ends[i]) + band_mm
            for key in cells(lo, hi):
                grid.setdefault(key, ([], []))[1].append(i)
        self._grid = {
            key: (np.array(c, dtype=np.int64), np.array(e, dtype=np.int64)) for key, (c, e) in grid.items()
        }
        self._cell = cell
        self._band = band_mm

    def nearest(self, q: np.ndarray, band_mm: float) -> tuple[str, np.ndarray | None]:
        """Feature at a surface point ``q``: corner / edge (with direction) within ``band_mm``, else face."""
        if getattr(self, "_band", None) != band_mm:
            self.build_lookup(band_mm)
        cell = self._cell
        hit = self._grid.get((math.floor(q[0] / cell), math.floor(q[1] / cell), math.floor(q[2] / cell)))
        if hit is None:
            return "face", None
        corners, segs = hit
        band2 = band_mm * band_mm
        if corners.size:
            dc = self.corner_points[corners] - q
            if float(np.einsum("ij,ij->i", dc, dc).min()) <= band2:
                return "corner", None
        if segs.size:
            a, d = self.seg_a[segs], self.seg_d[segs]
            w = q - a
            t = np.clip(np.einsum("ij,ij->i", w, d) * self.seg_inv_len2[segs], 0.0, 1.0)
            diff = w - t[:, None] * d
            d2 = np.einsum("ij,ij->i", diff, diff)
            i = int(np.argmin(d2))
            if float(d2[i]) <= band2:
                return "edge", self.seg_dir[segs[i]].copy()
        return "face", None


def _scipy_sparse() -> Any:
    try:
        import scipy.sparse
        import scipy.sparse.csgraph
    except ImportError as exc:  # pragma: no cover
        raise MissingDependencyError("scipy", "mesh", "finding sharp-edge chains on a mesh") from exc
    return scipy.sparse


# --- the object ---------------------------------------------------------------------------------------


#: On an open mesh, how close to a hole's border the pad-plane test hands over to the winding number:
#: the winding number drifts from 1 to 0 across a hole over about its size, so a point a few millimetres
#: from a border can be "outside" without any surface between it and an "inside" pad centre.
HOLE_MARGIN_MM = 6.0


def _mesh_arrays(name: str, vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The vertices as a finite (V, 3) float array (V ≥ 3) and the faces as an integer (F, 3) array of
    indices into them; anything else is refused naming the mesh."""
    v = np.asarray(vertices, dtype=float)
    f = np.asarray(faces)
    if v.ndim != 2 or v.shape[1] != 3 or len(v) < 3 or not np.isfinite(v).all():
        raise ConfigurationError(f"{name}: vertices must be a finite (V, 3) array with V ≥ 3")
    if f.ndim != 2 or f.shape[1] != 3 or len(f) < 1 or not np.issubdtype(f.dtype, np.integer):
        raise ConfigurationError(f"{name}: faces must be an integer (F, 3) array")
    if f.min() < 0 or f.max() >= len(v):
        raise ConfigurationError(f"{name}: face indices must lie in [0, {len(v) - 1}]")
    return v, f


def _fit_factor(name: str, extent: float, fit_mm: float | None, scale: float) -> float:
    """The scale that fits the mesh's largest extent into ``fit_mm``, else ``scale``; both positive."""
    if fit_mm is not None:
        fit = float(fit_mm)
        if not math.isfinite(fit) or fit <= 0:
            raise ConfigurationError(f"{name}.fit_mm={fit_mm!r} must be a positive length")
        return fit / extent
    factor = float(scale)
    if not math.isfinite(factor) or factor <= 0:
        raise ConfigurationError(f"{name}.scale={scale!r} must be a positive number")
    return factor


class TriangleMesh(PlacedSolid):
    """A solid bounded by a triangle mesh, placed in the world and fitted into a box.  ``surface``:
    :class:`~.primitives.SurfaceOptions`."""

    kind = "mesh"

    def __init__(
        self,
        name: str,
        vertices: np.ndarray,
        faces: np.ndarray,
        *,
        center_mm: Sequence[float] = (0.0, 0.0, 0.0),
        rotation: object | None = None,
        fit_mm: float | None = DEFAULT_FIT_MM,
        scale: float = 1.0,
        sharp_angle_deg: float = 40.0,
        min_chain_mm: float = 10.0,
        concave_edges: bool = False,
        boundary_edges_sharp: bool = True,
        corner_turn_deg: float = 60.0,
        tip_window_mm: float = 10.0,
        sign_method: str = "auto",
        sample_spacing_mm: float | None = None,
        source: str = "",
        **surface: Unpack[SurfaceOptions],
    ) -> None:
        super().__init__(name, center_mm, rotation, **surface)
        v, f = _mesh_arrays(name, vertices, faces)
        if sign_method not in ("auto", "pseudonormal", "winding"):
            raise ConfigurationError(
                f"{name}: sign_method={sign_method!r} must be 'auto', 'pseudonormal' or 'winding'"
            )
        if self.rotation is not None:
            v = v @ self.rotation.T
        lo, hi = v.min(axis=0), v.max(axis=0)
        extent = float((hi - lo).max())
        if extent <= 0:
            raise ConfigurationError(f"{name}: the mesh has no extent")
        factor = _fit_factor(name, extent, fit_mm, scale)
        v = (v - (lo + hi) / 2.0) * factor + self.center_mm
        v, f = _clean(v, f.astype(np.int64))
        if len(f) == 0:
            raise ConfigurationError(f"{name}: no triangle with a non-zero area")
        self.scale_factor = factor
        self.source = source
        self.sign_method = sign_method
        self.sample_spacing_mm = sample_spacing_mm
        self._feature_params: dict[str, Any] = dict(
            sharp_angle_deg=float(sharp_angle_deg),
            min_chain_mm=float(min_chain_mm),
            concave_edges=bool(concave_edges),
            boundary_edges_sharp=bool(boundary_edges_sharp),
            corner_turn_deg=float(corner_turn_deg),
            tip_window_mm=float(tip_window_mm),
        )
        self._topo: _Topology | None = None
        # Closed meshes wound inside-out are turned right way out.
        topo = self._topology_of(v, f)
        if topo.watertight and _signed_volume(v, f) < 0:
            f = f[:, ::-1].copy()
            self._topo = None
        self.vertices_mm = v
        self.faces = f
        self._index: _Index | None = None
        self._pad_reach: dict[int, tuple[np.ndarray, float]] = {}
        self._features: _Features | None = None
        self._bounds = (v.min(axis=0), v.max(axis=0))

    def _topology_of(self, v: np.ndarray, f: np.ndarray) -> _Topology:
        self._topo = _topology(f, len(v))
        return self._topo

    # -- what is built ------------------------------------------------------------------------------

    @property
    def topology(self) -> _Topology:
        if self._topo is None:
            self._topo = _topology(self.faces, len(self.vertices_mm))
        return self._topo

    @property
    def is_watertight(self) -> bool:
        return self.topology.watertight

    @property
    def n_triangles(self) -> int:
        return len(self.faces)

    @property
    def index_built(self) -> bool:
        return self._index is not None

    @property
    def features_built(self) -> bool:
        return self._features is not None

    @property
    def bounds_mm(self) -> tuple[np.ndarray, np.ndarray]:
        return self._bounds

    def prepare(self, *, features: bool | None = None) -> None:
        """Build the index now (and the feature tables when contacts are classified) instead of on the
        first query, so the first rendered frame does not pay for it."""
        self._ensure_index()
        if self.classify_features if features is None else features:
            self._ensure_features()

    def _ensure_index(self) -> _Index:
        if self._index is None:
            self._index = _Index(
                self.vertices_mm, self.faces, self.topology, self.sample_spacing_mm, self.sign_method
            )
        return self._index

    def _ensure_features(self) -> _Features:
        if self._features is None:
            index = self._ensure_index()
            features = _Features(
                index.vertices, index.faces, index.topology, index.face_normals, **self._feature_params
            )
            features.build_lookup(self.feature_band_mm)
            self._features = features
        return self._features

    @property
    def index(self) -> _Index:
        return self._ensure_index()

    @property
    def features(self) -> _Features:
        return self._ensure_features()

    # -- queries ------------------------------------------------------------------------------------

    def query(self, point_mm: np.ndarray) -> SurfaceQuery:
        p = as_point(point_mm)
        index = self._index if self._index is not None else self._ensure_index()
        local = p - index.origin
        tri = index.closest_triangle(local)
        sd, closest_local, normal, _ = index.finish(local, tri)
        feature, edge_dir = "face", None
        if self.classify_features:
            feats = self._features if self._features is not None else self._ensure_features()
            feature, edge_dir = feats.nearest(closest_local, self.feature_band_mm)
        closest = closest_local + index.origin
        level, region = self._texture_at(closest)
        return SurfaceQuery(self.name, sd, closest, normal, feature, edge_dir, level, region)

    def closest_points(self, points_mm: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Signed distances (N,) and closest points (N, 3) of many points."""
        index = self._ensure_index()
        local = as_points(points_mm) - index.origin
        tris = index.closest_triangles(local)
        sd = np.empty(len(local))
        cp = np.empty((len(local), 3))
        for i, (p, tri) in enumerate(zip(local, tris.tolist())):
            sd[i], cp[i], _, _ = index.finish(p, tri, remember=False)
        return sd, cp + index.origin

    def contains_on_pad(self, pad: PadPlane, centre_inside: bool | None = None) -> np.ndarray:
        """Which of many points of one plane are inside: the contact-area mapping's 32 electrodes.

        The points are ``centre + u·x_axis + v·y_axis`` for the rows (u, v) of the pad's offsets.  Exact for
        a closed mesh, and cheap because it stays local: the mesh's cross-section by the pad plane is
        taken from the triangles near the pad only (the index's samples within the points' reach plus the
        triangles' covering radius hold every triangle that can meet the disc), and a point is inside
        when the segment from the centre to it crosses that cross-section an odd number of times and the
        centre is outside, or an even number and the centre is inside.  The centre's own side comes from
        ``centre_inside`` (the caller's query at the pad centre) or from one query here.  A vertex exactly
        on the plane counts on its positive side and a cross-section vertex exactly on a segment's line
        on its non-negative side, so shared vertices are counted once.  On an open mesh, points within
        :data:`HOLE_MARGIN_MM` of a hole's border are tested one by one with the winding number instead,
        so the answer is always :meth:`contains`'s."""
        index = self._ensure_index()
        c = as_point(pad.centre_mm, "centre_mm")
        off = pad.offsets_mm
        if centre_inside is None:
            centre_inside = self.query(c).signed_distance_mm <= 0.0
        x0, x1, x2 = (float(v) for v in pad.x_axis)
        y0, y1, y2 = (float(v) for v in pad.y_axis)
        frame = np.array(
            ((x0, y0, x1 * y2 - x2 * y1), (x1, y1, x2 * y0 - x0 * y2), (x2, y2, x0 * y1 - x1 * y0))
        )
        local = c - index.origin
        reach = self._pad_reach.get(id(off))
        if reach is None or reach[0] is not off:
            reach = (off, float(np.sqrt((off * off).sum(axis=1).max())) if len(off) else 0.0)
            self._pad_reach = {id(off): reach}
        out = np.full(len(off), bool(centre_inside))
        by_winding: np.ndarray | None = None
        if index.hole_tree is not None:
            gap, _ = index.hole_tree.query(local, distance_upper_bound=reach[1] + HOLE_MARGIN_MM)
            if math.isfinite(float(gap)):
                # Near a hole of an open mesh: the points close to its border by the winding number,
                # as contains() does; the others by crossings.
                pts = local + off[:, 0:1] * frame[:, 0] + off[:, 1:2] * frame[:, 1]
                return index.inside(pts)
        ids = index.tree.query_ball_point(local, reach[1] + index.cover_mm + 1e-9)
        if not ids and by_winding is None:
            return out
        tris = index.dedupe(index.table[ids].ravel()) if ids else np.empty(0, dtype=np.int64)
        # Triangle corners in pad coordinates: (u, v, height above the pad plane).
        pc = (index.vertices[index.faces[tris[tris != index.sentinel]]] - local) @ frame
        pos = pc[:, :, 2] >= 0.0
        npos = pos.sum(axis=1)
        cut = (npos == 1) | (npos == 2)
        pc, pos = pc[cut], pos[cut]
        # The corner alone on its side, and the two edges from it that cross the plane.
        k = np.argmax(pos == (npos[cut] == 1)[:, None], axis=1)
        rows = np.arange(len(k))
        lone = pc[rows, k]
        a_ = pc[rows, (k + 1) % 3]
        b_ = pc[rows, (k + 2) % 3]
        wa = (lone[:, 2] / (lone[:, 2] - a_[:, 2]))[:, None]
        wb = (lone[:, 2] / (lone[:, 2] - b_[:, 2]))[:, None]
        ea = lone[:, 0:2] + wa * (a_[:, 0:2] - lone[:, 0:2])
        eb = lone[:, 0:2] + wb * (b_[:, 0:2] - lone[:, 0:2])
        ax, ay, bx, by = ea[:, 0], ea[:, 1], eb[:, 0], eb[:, 1]
        px, py = off[:, 0:1], off[:, 1:2]  # segment from the centre (the origin) to each point
        sa = px * ay - py * ax  # side of each section end relative to the line through 0 and the point
        sb = px * by - py * bx
        straddle = (sa >= 0.0) != (sb >= 0.0)
        t = sa / np.where(straddle, sa - sb, 1.0)
        pp = px * px + py * py
        u = ((ax + t * (bx - ax)) * px + (ay + t * (by - ay)) * py) / np.where(pp > 0.0, pp, np.inf)
        odd = ((straddle & (u >= 0.0) & (u < 1.0)).sum(axis=1) % 2).astype(bool)
        result: np.ndarray = out ^ odd
        if by_winding is not None and by_winding.any():
            pts = local + off[by_winding, 0:1] * frame[:, 0] + off[by_winding, 1:2] * frame[:, 1]
            result[by_winding] = index.inside(pts)
        return result

    def contains(self, points_mm: np.ndarray) -> np.ndarray:
        pts = as_points(points_mm)
        lo, hi = self._bounds
        out = np.zeros(len(pts), dtype=bool)
        box = np.all((pts >= lo) & (pts <= hi), axis=1)
        if box.any():
            index = self._ensure_index()
            out[box] = index.inside(pts[box] - index.origin)
        return out

    # -- sites for trajectories ------------------------------------------------------------------------

    def sites(self, feature: str, toward: np.ndarray | None = None, limit: int = 16) -> list[SurfaceSite]:
        """Representative places for a feature, best first: those whose normal points most along
        ``toward`` (default: at the eye, the world origin), at least 20 mm apart.  Faces: vertices that
        read as faces from just outside; edges: midpoints of sharp edges away from corners; corners:
        corner vertices."""
        index = self._ensure_index()
        origin = index.origin
        if feature == "face":
            # Triangle centres on locally flat patches: pressed 3 mm in, the pad still finds the same
            # triangle, so a finger frame built on the site's normal is the one measured in contact.
            centres = index.vertices[index.faces].mean(axis=1) + origin
            normals = index.face_normals
            score = self._toward_score(centres, normals, toward)
            out: list[SurfaceSite] = []
            for tri in np.argsort(-score)[:20000].tolist():
                point = centres[tri]
                n = normals[tri]
                if any(np.linalg.norm(point - s.point_mm) < 20.0 for s in out):
                    continue
                q_out = self.query(point + 2.0 * n)
                if q_out.feature != "face" or float(np.dot(q_out.normal, n)) < 0.999:
                    continue
                q_in = self.query(point - 3.0 * n)
                if (
                    float(np.dot(q_in.normal, n)) < 0.999
                    or np.linalg.norm(q_in.closest_point_mm - point) > 0.05
                ):
                    continue
                out.append(SurfaceSite(self.name, "face", point, n.copy(), None, q_out.texture_level))
                if len(out) >= limit:
                    break
            return out
        if feature not in ("edge", "corner"):
            return []
        feats = self._ensure_features()
        if feature == "edge":
            corner_set = feats.corner_points + origin
            mids = feats.seg_a + 0.5 * feats.seg_d + origin
            score = self._toward_score(mids, feats.seg_normal, toward)
            out = []
            for i in np.argsort(-score).tolist():
                mid = mids[i]
                if (
                    corner_set.shape[0]
                    and np.min(np.linalg.norm(corner_set - mid, axis=1)) <= 2 * self.feature_band_mm
                ):
                    continue
                if any(np.linalg.norm(mid - s.point_mm) < 20.0 for s in out):
                    continue
                level = self._texture_at(mid)[0]
                out.append(
                    SurfaceSite(self.name, "edge", mid, feats.seg_normal[i], feats.seg_dir[i].copy(), level)
                )
                if len(out) >= limit:
                    break
            return out
        normals = self._vertex_normals(refined=True)
        points = index.vertices[feats.corner_vertices] + origin
        cn = normals[feats.corner_vertices]
        order: list[int] = np.argsort(-self._toward_score(points, cn, toward)).tolist() if len(points) else []
        return [
            SurfaceSite(self.name, "corner", points[i], cn[i], None, self._texture_at(points[i])[0])
            for i in order[:limit]
        ]

    @staticmethod
    def _toward_score(points: np.ndarray, normals: np.ndarray, toward: np.ndarray | None) -> np.ndarray:
        score: np.ndarray
        if toward is not None:
            score = normals @ np.asarray(toward, dtype=float)
        else:
            to_eye = -points / np.maximum(np.linalg.norm(points, axis=1), 1e-9)[:, None]
            score = np.einsum("ij,ij->i", normals, to_eye)
        return score

    def _vertex_normals(self, refined: bool = False) -> np.ndarray:
        """Unit vertex normals (angle-weighted on closed meshes); the first vertices of the refined mesh
        are the original ones, in the same order."""
        index = self._ensure_index()
        if index.winding is None:
            vpn = index.vertex_pn
        else:
            vpn = np.zeros_like(index.vertices)
            for k in range(3):
                np.add.at(vpn, index.faces[:, k], index.face_normals)
        if not refined:
            vpn = vpn[: len(self.vertices_mm)]
        norms = np.linalg.norm(vpn, axis=1)
        return vpn / np.where(norms > 0, norms, 1.0)[:, None]


def _signed_volume(v: np.ndarray, f: np.ndarray) -> float:
    a, b, c = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
    return float(np.einsum("ij,ij->i", a, np.cross(b, c)).sum() / 6.0)
