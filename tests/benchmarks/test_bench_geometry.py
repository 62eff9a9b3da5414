"""Cost of one surface query (and of one 32-point inside test) along realistic finger paths.

The paths are the synthetic study tasks: ``explore`` (touches, strokes over the surface, lifts and
transits) and ``approach-face`` (from 10 cm away into contact).  The renderer's whole pose → pattern
frame must stay under 50 µs on primitives and 250 µs on the bunny, so the query is the part to watch.

    pytest tests/benchmarks/test_bench_geometry.py --benchmark-enable
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from tactdeform_hw.render.geometry import PadPlane
from tactdeform_hw.render.scene import Scene, load_scene
from tactdeform_hw.render.trajectories import make_trajectory

SHARED = Path(__file__).resolve().parents[2] / ".." / "shared"


def path_points(scene: Scene) -> list[np.ndarray]:
    points: list[np.ndarray] = []
    for name in ("explore", "approach-face"):
        points.extend(np.array(p.position_mm) for p in make_trajectory(name, scene))
    return points


class Cycle:
    """Queries the points in order, forever (consecutive queries are neighbours, as when tracking)."""

    def __init__(self, fn, points) -> None:  # type: ignore[no-untyped-def]
        self.fn = fn
        self.points = points
        self.i = 0

    def __call__(self):  # type: ignore[no-untyped-def]
        p = self.points[self.i % len(self.points)]
        self.i += 1
        return self.fn(p)


def _check_queries(scene: Scene, points: list[np.ndarray], last) -> None:  # type: ignore[no-untyped-def]
    """What was timed answered: finite distances, and the paths reach the surface."""
    assert np.isfinite(last.signed_distance_mm)
    answers = [scene.query(p).signed_distance_mm for p in points]
    assert all(np.isfinite(answers)) and min(answers) <= 0.0 < max(answers)


def _note(benchmark, budget_us: float) -> None:  # type: ignore[no-untyped-def]
    benchmark.extra_info["frame_budget_us"] = budget_us
    stats = getattr(benchmark, "stats", None)
    if stats is not None:
        benchmark.extra_info["median_us"] = round(stats.stats.median * 1e6, 2)


@pytest.mark.parametrize("name", ["sphere", "cube", "task2", "task3"])
def test_query_primitives(benchmark, name: str) -> None:  # type: ignore[no-untyped-def]
    scene = load_scene(name)
    points = path_points(scene)
    _check_queries(scene, points, benchmark(Cycle(scene.query, points)))
    _note(benchmark, 50.0)


def test_query_teapot(benchmark) -> None:  # type: ignore[no-untyped-def]
    pytest.importorskip("scipy", reason="the teapot's mesh index needs scipy (extra 'mesh')")
    scene = load_scene("teapot")
    scene.prepare()
    points = path_points(scene)
    _check_queries(scene, points, benchmark(Cycle(scene.query, points)))
    _note(benchmark, 250.0)


@pytest.fixture(scope="module")
def bunny() -> Scene:
    pytest.importorskip("scipy", reason="the bunny's mesh index needs scipy (extra 'mesh')")
    if not (SHARED / "meshes" / "stanford_bunny.obj").is_file():
        pytest.skip(f"the Stanford bunny is not under {SHARED / 'meshes'} (../shared absent)")
    scene = load_scene("bunny", mesh_dirs=[SHARED / "meshes"])
    scene.prepare()
    return scene


def test_query_bunny(benchmark, bunny: Scene) -> None:  # type: ignore[no-untyped-def]
    points = path_points(bunny)
    _check_queries(bunny, points, benchmark(Cycle(bunny.query, points)))
    _note(benchmark, 250.0)


def _electrode_clouds(scene: Scene) -> list[np.ndarray]:
    """32 points on a 2 mm grid around each pad position in contact: what contact-area mapping asks."""
    grid = np.array(
        [(x, y, 0.0) for y in range(6) for x in range(6) if (x, y) not in ((0, 0), (5, 0), (0, 5), (5, 5))]
    )
    grid = (grid - [2.5, 2.5, 0.0]) * 2.0
    clouds = []
    for pose in make_trajectory("approach-face", scene):
        if scene.query(pose.position_mm).signed_distance_mm <= 1.0:
            clouds.append(pose.to_world(grid))
    return clouds


def _check_contains(scene: Scene, clouds: list[np.ndarray], last: np.ndarray) -> None:
    """What was timed answered one flag per electrode, and some clouds lie partly inside."""
    assert np.asarray(last).shape == (32,)
    assert any(bool(np.any(scene.contains(c))) for c in clouds)


def test_contains_32_cube(benchmark) -> None:  # type: ignore[no-untyped-def]
    scene = load_scene("cube")
    clouds = _electrode_clouds(scene)
    _check_contains(scene, clouds, benchmark(Cycle(scene.contains, clouds)))


def test_contains_32_bunny(benchmark, bunny: Scene) -> None:  # type: ignore[no-untyped-def]
    clouds = _electrode_clouds(bunny)
    _check_contains(bunny, clouds, benchmark(Cycle(bunny.contains, clouds)))


def _pad_calls(scene: Scene) -> list[tuple[np.ndarray, np.ndarray, np.ndarray, object]]:
    """The arguments of the pad-plane test along the same poses (centre, axes, its query)."""
    calls = []
    for pose in make_trajectory("approach-face", scene):
        q = scene.query(pose.position_mm)
        if q.signed_distance_mm <= 1.0:
            calls.append((np.asarray(pose.position_mm), pose.x_axis, pose.y_axis, q))
    return calls


@pytest.mark.parametrize("name", ["teapot", "bunny"])
def test_contains_on_pad_meshes(benchmark, name: str, request) -> None:  # type: ignore[no-untyped-def]
    """CAM's 32 electrodes through the mesh index: the pad-plane cross-section (budget: the 250 µs of a
    whole CAM pose, scene query included)."""
    from tactdeform_hw.render.array import ElectrodeArray

    pytest.importorskip("scipy", reason="the mesh index needs scipy (extra 'mesh')")
    if name == "bunny":
        scene = request.getfixturevalue("bunny")
    else:
        scene = load_scene("teapot")
        scene.prepare()
    offsets = ElectrodeArray.tactdeform().world_offsets()
    calls = _pad_calls(scene)
    state = {"i": 0}

    def one():  # type: ignore[no-untyped-def]
        c, x, y, q = calls[state["i"] % len(calls)]
        state["i"] += 1
        return scene.contains_on_pad(PadPlane.of(c, x, y, offsets), q)

    last = benchmark(one)
    assert np.asarray(last).shape == (len(offsets),)
    # the plane's cross-section answers as the points one by one do, over every call timed (a point on
    # the surface itself, to rounding, may go either way)
    for c, x, y, q in calls:
        points = c + offsets[:, :1] * x + offsets[:, 1:] * y
        differ = np.asarray(scene.contains_on_pad(PadPlane.of(c, x, y, offsets), q)) != scene.contains(points)
        assert all(abs(scene.query(p).signed_distance_mm) < 1e-9 for p in points[differ])
    _note(benchmark, 250.0)
