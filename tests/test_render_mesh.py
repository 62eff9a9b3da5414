"""Triangle meshes: reading, exact closest points, sign, features; the bunny when ../shared is present."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

from tactdeform_hw.errors import ConfigurationError, MissingDependencyError
from tactdeform_hw.render.mesh import TriangleMesh, read_mesh, read_obj
from tactdeform_hw.render.primitives import Box
from tactdeform_hw.render.scene import load_scene
from tactdeform_hw.render.tracking import quat_to_matrix

SHARED = Path(__file__).resolve().parents[1] / ".." / "shared"
BUNNY = SHARED / "meshes" / "stanford_bunny.obj"
needs_bunny = pytest.mark.skipif(
    not BUNNY.is_file(), reason=f"the Stanford bunny is not at {BUNNY} (../shared absent)"
)


def cube_mesh(half: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    v = np.array([[x, y, z] for x in (-half, half) for y in (-half, half) for z in (-half, half)])
    quads = [[0, 1, 3, 2], [4, 6, 7, 5], [0, 4, 5, 1], [2, 3, 7, 6], [0, 2, 6, 4], [1, 5, 7, 3]]
    f = [[q[0], q[1], q[2]] for q in quads] + [[q[0], q[2], q[3]] for q in quads]
    return v, np.array(f)


def brute_distance(p: np.ndarray, v: np.ndarray, f: np.ndarray) -> float:
    """Reference point–mesh distance over every triangle, written independently of the index."""
    a, b, c = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
    best = np.full(len(f), np.inf)
    for s, e in ((a, b), (b, c), (c, a)):
        d, w = e - s, p - s
        t = np.clip(np.einsum("ij,ij->i", w, d) / np.einsum("ij,ij->i", d, d), 0.0, 1.0)
        diff = w - t[:, None] * d
        best = np.minimum(best, np.einsum("ij,ij->i", diff, diff))
    n = np.cross(b - a, c - a)
    n /= np.linalg.norm(n, axis=1)[:, None]
    pd = np.einsum("ij,ij->i", p - a, n)
    q = p - pd[:, None] * n

    def side(x: np.ndarray, y: np.ndarray) -> np.ndarray:
        return np.einsum("ij,ij->i", np.cross(y - x, q - x), n)

    inside = (side(a, b) >= 0) & (side(b, c) >= 0) & (side(c, a) >= 0)
    return float(np.sqrt(np.where(inside, pd * pd, best).min()))


# --- reading -------------------------------------------------------------------------------------------


def test_obj_reader_fans_polygons_and_resolves_negative_indices(tmp_path: Path) -> None:
    path = tmp_path / "quad.obj"
    path.write_text(
        "# a square and a triangle\nv 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nvn 0 0 1\n"
        "f 1//1 2//1 3//1 4//1\nv 2 0 0\nf -1 2 3\n"
    )
    data = read_obj(path)
    assert data.vertices.shape == (5, 3)
    assert data.faces.tolist() == [[0, 1, 2], [0, 2, 3], [4, 1, 2]]


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("v 0 0\n", "line 1"),
        ("v 0 0 0\nv 1 0 0\nf 1 2\n", "line 3"),
        ("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 9\n", "refers to no vertex"),
        ("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 x 3\n", "bad vertex index"),
        ("# nothing\n", "no triangles"),
    ],
)
def test_obj_errors_name_the_line(tmp_path: Path, text: str, message: str) -> None:
    path = tmp_path / "bad.obj"
    path.write_text(text)
    with pytest.raises(ConfigurationError, match=message):
        read_obj(path)


def test_unknown_formats_and_missing_files(tmp_path: Path) -> None:
    with pytest.raises(ConfigurationError, match="does not exist"):
        read_mesh(tmp_path / "none.obj")
    (tmp_path / "x.3ds").write_text("")
    with pytest.raises(ConfigurationError, match="unsupported format"):
        read_mesh(tmp_path / "x.3ds")


def test_stl_and_ply_read_through_trimesh(tmp_path: Path) -> None:
    trimesh = pytest.importorskip("trimesh")
    v, f = cube_mesh(5.0)
    for suffix in (".stl", ".ply"):
        path = tmp_path / f"cube{suffix}"
        trimesh.Trimesh(v, f, process=False).export(path)
        scene = load_scene(path)
        mesh = scene.objects[0]
        assert isinstance(mesh, TriangleMesh) and mesh.is_watertight
        lo, hi = mesh.bounds_mm
        np.testing.assert_allclose(hi - lo, [200.0, 200.0, 200.0])


# --- exactness on a mesh with a known answer: a cube -------------------------------------------------------


@pytest.fixture(scope="module")
def mesh_and_box() -> tuple[TriangleMesh, Box]:
    v, f = cube_mesh()
    mesh = TriangleMesh("m", v, f, center_mm=(10.0, 20.0, 30.0), fit_mm=100.0, sample_spacing_mm=20.0)
    box = Box("b", 100.0, (10.0, 20.0, 30.0))
    return mesh, box


def test_cube_mesh_matches_the_analytic_cube(mesh_and_box: tuple[TriangleMesh, Box]) -> None:
    mesh, box = mesh_and_box
    rng = np.random.default_rng(7)
    pts = np.array([10.0, 20.0, 30.0]) + rng.uniform(-80.0, 80.0, size=(600, 3))
    # Points right on and just around the surface, where sign and feature are hardest.
    on = np.array([10.0, 20.0, 30.0]) + np.clip(rng.uniform(-60, 60, size=(200, 3)), -50, 50)
    pts = np.concatenate((pts, on, on + rng.normal(scale=0.01, size=on.shape)))
    for p in pts:
        qm, qb = mesh.query(p), box.query(p)
        assert qm.signed_distance_mm == pytest.approx(qb.signed_distance_mm, abs=1e-7)
        np.testing.assert_allclose(qm.closest_point_mm, qb.closest_point_mm, atol=1e-6)
        assert qm.feature == qb.feature, p
        if qb.feature == "edge":
            assert abs(float(np.dot(qm.edge_direction, qb.edge_direction))) == pytest.approx(1.0)
        if abs(qb.signed_distance_mm) > 1e-6:
            np.testing.assert_allclose(qm.normal, qb.normal, atol=1e-6)
    np.testing.assert_array_equal(mesh.contains(pts), box.contains(pts))
    sd, cp = mesh.closest_points(pts[:50])
    np.testing.assert_allclose(sd, [box.query(p).signed_distance_mm for p in pts[:50]], atol=1e-7)


def test_electrode_clouds_match_the_analytic_cube(mesh_and_box: tuple[TriangleMesh, Box]) -> None:
    """Clustered points (the 32 electrodes of a pad) take the batched inside test; it must be exact."""
    mesh, box = mesh_and_box
    rng = np.random.default_rng(8)
    grid = np.array(
        [(x, y, 0.0) for y in range(6) for x in range(6) if (x, y) not in ((0, 0), (5, 0), (0, 5), (5, 5))]
    )
    grid = (grid - [2.5, 2.5, 0.0]) * 2.0
    for _ in range(60):
        centre = np.array([10.0, 20.0, 30.0]) + np.clip(rng.uniform(-60, 60, 3), -52, 52)
        q = rng.normal(size=4)
        cloud = centre + grid @ quat_to_matrix(q / np.linalg.norm(q)).T
        np.testing.assert_array_equal(mesh.contains(cloud), box.contains(cloud))


def test_refinement_keeps_the_surface_closed() -> None:
    v, f = cube_mesh()
    mesh = TriangleMesh("m", v, f, fit_mm=100.0, sample_spacing_mm=7.0)
    index = mesh.index
    assert index.n_triangles > 12 and index.topology.watertight
    lengths = np.linalg.norm(
        index.vertices[index.topology.edges[:, 0]] - index.vertices[index.topology.edges[:, 1]], axis=1
    )
    assert lengths.max() <= 7.0 + 1e-9
    area = (
        0.5
        * np.linalg.norm(
            np.cross(
                index.vertices[index.faces[:, 1]] - index.vertices[index.faces[:, 0]],
                index.vertices[index.faces[:, 2]] - index.vertices[index.faces[:, 0]],
            ),
            axis=1,
        ).sum()
    )
    assert area == pytest.approx(6 * 100.0**2)
    assert index.cover_mm <= 7.0 / np.sqrt(3.0) + 1e-9


def test_feature_tables_are_built_only_for_tactdeform() -> None:
    from tactdeform_hw.render.scene import RenderOptions

    ua = load_scene("teapot", options=RenderOptions(approach="ua"))
    ua.prepare()
    assert ua.built_parts()["mesh_index"] == ["teapot"] and ua.built_parts()["mesh_features"] == []
    ua.query(np.array([0.0, 0.0, 0.0]))
    assert ua.built_parts()["mesh_features"] == []
    td = load_scene("teapot")
    assert td.built_parts()["mesh_index"] == []  # lazy until prepared or queried
    td.prepare()
    assert td.built_parts()["mesh_features"] == ["teapot"]


def test_cube_mesh_features(mesh_and_box: tuple[TriangleMesh, Box]) -> None:
    mesh, _ = mesh_and_box
    feats = mesh.features
    assert feats.corner_points.shape[0] == 8
    assert set(feats.valence[feats.corner_vertices].tolist()) == {3}
    # The triangulation's diagonals are flat and not sharp.
    dihedral = feats.dihedral_deg[~np.isnan(feats.dihedral_deg)]
    assert set(np.round(dihedral).astype(int).tolist()) <= {0, 90}


def test_inside_out_closed_mesh_is_turned_right_way_out() -> None:
    v, f = cube_mesh()
    mesh = TriangleMesh("m", v, f[:, ::-1], fit_mm=2.0)
    assert mesh.query(np.zeros(3)).signed_distance_mm == pytest.approx(-1.0)
    assert mesh.query(np.array([0.0, 0.0, 3.0])).signed_distance_mm == pytest.approx(2.0)


def test_open_mesh_uses_the_winding_number() -> None:
    v, f = cube_mesh()
    open_box = TriangleMesh("open", v, f[:-1], fit_mm=2.0)  # one triangle of one face missing
    assert not open_box.is_watertight
    assert open_box.index.sign_method == "winding"
    assert open_box.query(np.zeros(3)).signed_distance_mm == pytest.approx(-1.0)
    assert open_box.query(np.array([0.0, 3.0, 0.0])).signed_distance_mm == pytest.approx(2.0)
    with pytest.raises(ConfigurationError, match="closed"):
        TriangleMesh("open", v, f[:-1], fit_mm=2.0, sign_method="pseudonormal").prepare()


def test_fit_and_scale() -> None:
    v, f = cube_mesh(3.0)
    fitted = TriangleMesh("a", v, f, center_mm=(1.0, 2.0, 3.0), fit_mm=50.0)
    lo, hi = fitted.bounds_mm
    np.testing.assert_allclose(lo, [-24.0, -23.0, -22.0])
    np.testing.assert_allclose(hi, [26.0, 27.0, 28.0])
    scaled = TriangleMesh("b", v, f, fit_mm=None, scale=10.0)
    np.testing.assert_allclose(scaled.bounds_mm[1], [30.0, 30.0, 30.0])


def test_degenerate_input_is_refused() -> None:
    v, f = cube_mesh()
    with pytest.raises(ConfigurationError, match="face indices"):
        TriangleMesh("m", v, f + 100)
    with pytest.raises(ConfigurationError, match="non-zero area"):
        TriangleMesh("m", np.array([[0.0, 0, 0], [1, 0, 0], [2, 0, 0]]), np.array([[0, 1, 2]]))
    with pytest.raises(ConfigurationError, match="vertices"):
        TriangleMesh("m", np.full((3, 3), np.nan), np.array([[0, 1, 2]]))


def test_missing_scipy_names_the_extra(monkeypatch: pytest.MonkeyPatch) -> None:
    v, f = cube_mesh()
    mesh = TriangleMesh("m", v, f)
    monkeypatch.setitem(sys.modules, "scipy", None)
    monkeypatch.setitem(sys.modules, "scipy.spatial", None)
    with pytest.raises(MissingDependencyError, match=r"\[mesh\]'"):
        mesh.query(np.zeros(3))


def test_teapot_distances_are_exact() -> None:
    from tactdeform_hw.render.teapot import teapot_mesh

    pot = teapot_mesh(subdivisions=8)
    pot.prepare()
    v, f = pot.index.vertices + pot.index.origin, pot.index.faces
    rng = np.random.default_rng(3)
    lo, hi = pot.bounds_mm
    pts = lo - 20 + rng.random((40, 3)) * (hi - lo + 40)
    for p in pts:
        assert abs(pot.query(p).signed_distance_mm) == pytest.approx(brute_distance(p, v, f), abs=1e-7)


def test_teapot_edges_come_from_its_open_lips() -> None:
    from tactdeform_hw.render.teapot import teapot_mesh

    pot = teapot_mesh(subdivisions=8)
    feats = pot.features
    assert len(feats.sharp_edges) > 0
    sharp_no_boundary = teapot_mesh(subdivisions=8, boundary_edges_sharp=False).features
    assert len(sharp_no_boundary.sharp_edges) < len(feats.sharp_edges)


# --- the bunny ---------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def bunny() -> TriangleMesh:
    if not BUNNY.is_file():
        pytest.skip(f"the Stanford bunny is not at {BUNNY} (../shared absent)")
    scene = load_scene("bunny", mesh_dirs=[SHARED / "meshes"])
    scene.prepare()
    mesh = scene.objects[0]
    assert isinstance(mesh, TriangleMesh)
    return mesh


@needs_bunny
def test_bunny_loads_closed_and_fitted(bunny: TriangleMesh) -> None:
    assert bunny.n_triangles == 86632
    assert bunny.is_watertight and bunny.index.sign_method == "pseudonormal"
    lo, hi = bunny.bounds_mm
    assert float(np.max(hi - lo)) == pytest.approx(200.0)
    # z-up file turned y-up: the bunny is taller (y) than it is deep (z).
    assert (hi - lo)[1] > (hi - lo)[2]
    assert bunny.texture_level == 1


@needs_bunny
def test_bunny_queries_match_brute_force(bunny: TriangleMesh) -> None:
    v, f = bunny.vertices_mm, bunny.faces
    rng = np.random.default_rng(11)
    idx = rng.integers(0, len(v), 12)
    normals = bunny._vertex_normals()
    offsets = rng.uniform(-4.0, 60.0, size=12)
    pts = v[idx] + offsets[:, None] * normals[idx]
    for p in pts:
        q = bunny.query(p)
        assert abs(q.signed_distance_mm) == pytest.approx(brute_distance(p, v, f), abs=1e-7)
    centre = (bunny.bounds_mm[0] + bunny.bounds_mm[1]) / 2.0
    assert bunny.query(centre).signed_distance_mm < 0  # the body is solid
    assert bunny.query(centre + np.array([0.0, 0.0, 300.0])).signed_distance_mm > 0


@needs_bunny
def test_bunny_contains_agrees_with_query_sign(bunny: TriangleMesh) -> None:
    rng = np.random.default_rng(5)
    lo, hi = bunny.bounds_mm
    pts = lo + rng.random((64, 3)) * (hi - lo)
    inside = bunny.contains(pts)
    assert inside.any() and not inside.all()
    assert inside.tolist() == [bunny.query(p).signed_distance_mm <= 0 for p in pts]


@needs_bunny
def test_bunny_faces_read_as_faces(bunny: TriangleMesh) -> None:
    sites = bunny.sites("face")
    assert len(sites) >= 4
    for site in sites:
        q = bunny.query(site.point_mm + 2.0 * site.normal)
        assert q.feature == "face" and q.signed_distance_mm == pytest.approx(2.0, abs=1e-6)


def test_bunny_missing_gives_a_clear_error(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    import tactdeform_hw.render.scene as scene_module

    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr(scene_module, "__file__", str(tmp_path / "a" / "b" / "c" / "scene.py"))
    monkeypatch.delenv(scene_module.MESH_DIR_ENV, raising=False)
    with pytest.raises(ConfigurationError, match="stanford_bunny.obj.*not found"):
        load_scene("bunny")
