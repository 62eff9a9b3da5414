"""The Utah teapot, generated from Martin Newell's published Bézier patch data (public domain).

32 bicubic patches over 306 control points: rim (4), body (8), handle (4), spout (4), lid (8) and
bottom (4).  Each patch is evaluated on a regular (u, v) grid, split into triangles, and the patches are
welded along their shared borders.  The result is not a closed solid — the lid sits in the rim with a
gap, the spout and handle are open tubes pushed into the body — which is why :class:`~.mesh.TriangleMesh`
takes its inside/outside from the generalised winding number for it.

The data is in Newell's units with z up (height 3.15, spout along +x); :func:`teapot_mesh` turns z up
into the world's y up and fits the pot into the study's 20 cm box.
"""

from __future__ import annotations

from collections.abc import Sequence
from importlib import resources
from typing import Any

import numpy as np

from ..errors import ConfigurationError
from .mesh import DEFAULT_FIT_MM, TriangleMesh

#: The data files beside this module (shipped through pyproject's package-data, so a wheel has them).
_DATA = resources.files(__package__ or __name__).joinpath("data")


def _table(name: str) -> list[str]:
    """The numbers of the data file ``name`` in ``data/``, comment lines (``#``) left out: Newell's
    tables are data, kept out of the code and read once, at import."""
    text = _DATA.joinpath(name).read_text(encoding="utf-8")
    return [word for line in text.splitlines() if not line.startswith("#") for word in line.split()]


# 1-based control-point indices, 16 per patch, row-major (4 rows along u, 4 columns along v).
_PATCHES = _table("teapot_patches.txt")

# The 306 control points (x, y, z), z up.
_POINTS = _table("teapot_points.txt")

PATCH_GROUPS: dict[str, range] = {
    "rim": range(0, 4),
    "body": range(4, 12),
    "handle": range(12, 16),
    "spout": range(16, 20),
    "lid": range(20, 28),
    "bottom": range(28, 32),
}


def control_points() -> np.ndarray:
    """The 306 control points, (306, 3), z up."""
    pts = np.array(_POINTS, dtype=float).reshape(-1, 3)
    assert pts.shape == (306, 3)
    return pts


def patches() -> np.ndarray:
    """The 32 patches as 0-based control-point indices, (32, 4, 4) with [row along u, column along v]."""
    idx = np.array(_PATCHES, dtype=np.int64).reshape(32, 4, 4) - 1
    return idx


def _bernstein(t: np.ndarray) -> np.ndarray:
    s = 1.0 - t
    return np.stack((s**3, 3 * s * s * t, 3 * s * t * t, t**3), axis=1)


def teapot_triangles(
    subdivisions: int = 12, groups: Sequence[str] | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Vertices (z up, Newell's units) and triangles of the tessellated teapot.

    Each patch becomes a ``subdivisions`` × ``subdivisions`` grid of quads, two triangles each, wound so
    that their normals point out of the pot (−∂P/∂u × ∂P/∂v for this data set).  Coincident border
    vertices are merged and collapsed triangles (at the lid's and bottom's poles) dropped by the mesh.
    """
    if isinstance(subdivisions, bool) or not isinstance(subdivisions, int) or not 1 <= subdivisions <= 64:
        raise ConfigurationError(f"teapot subdivisions={subdivisions!r} must be an integer from 1 to 64")
    chosen = list(PATCH_GROUPS) if groups is None else list(groups)
    unknown = [g for g in chosen if g not in PATCH_GROUPS]
    if unknown:
        raise ConfigurationError(f"teapot groups {unknown} are not among {list(PATCH_GROUPS)}")
    cp = control_points()
    idx = patches()
    n = subdivisions
    basis = _bernstein(np.linspace(0.0, 1.0, n + 1))  # (n+1, 4)
    verts = []
    faces = []
    offset = 0
    grid = np.arange((n + 1) * (n + 1)).reshape(n + 1, n + 1)
    q00, q01 = grid[:-1, :-1].ravel(), grid[:-1, 1:].ravel()
    q10, q11 = grid[1:, :-1].ravel(), grid[1:, 1:].ravel()
    quad_tris = np.concatenate((np.stack((q00, q11, q10), axis=1), np.stack((q00, q01, q11), axis=1)))
    for group in chosen:
        for p in PATCH_GROUPS[group]:
            ctrl = cp[idx[p]]  # (4, 4, 3)
            surface = np.einsum("ur,vc,rck->uvk", basis, basis, ctrl).reshape(-1, 3)
            verts.append(surface)
            faces.append(quad_tris + offset)
            offset += len(surface)
    return np.concatenate(verts), np.concatenate(faces)


_Z_UP_TO_Y_UP = np.array(((1.0, 0.0, 0.0), (0.0, 0.0, 1.0), (0.0, -1.0, 0.0)))
"""Rotation by −90° about x: Newell's z (up) becomes the world's y (up); the spout stays along +x."""


def teapot_mesh(
    name: str = "teapot",
    *,
    center_mm: Sequence[float] = (0.0, 0.0, 0.0),
    rotation: np.ndarray | None = None,
    fit_mm: float | None = DEFAULT_FIT_MM,
    subdivisions: int = 12,
    **kwargs: Any,
) -> TriangleMesh:
    """The teapot as a touchable mesh: y up, spout toward +x, fitted into ``fit_mm``.  ``rotation`` is
    applied after the z-up → y-up turn."""
    v, f = teapot_triangles(subdivisions)
    r = _Z_UP_TO_Y_UP if rotation is None else np.asarray(rotation, dtype=float) @ _Z_UP_TO_Y_UP
    return TriangleMesh(
        name, v, f, center_mm=center_mm, rotation=r, fit_mm=fit_mm, source="utah-teapot", **kwargs
    )
