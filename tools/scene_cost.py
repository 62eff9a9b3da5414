"""What a scene costs to build, and what it leaves out.

For each scene and render option, a fresh Python process loads the scene and prepares it (everything a
run would build before its first frame), then answers one query.  Reported per configuration:

* ``build_ms``: load + prepare wall time after the package is imported (a separate process without
  tracemalloc, so it is not slowed), including any optional dependency the scene imports;
* ``peak_mib`` / ``held_mib``: tracemalloc peak and retained memory of that build (numpy buffers and
  imported modules included);
* the scene's ``needs`` flags, what was actually built (mesh index, feature tables, texture look-ups,
  feature classification) and whether scipy / trimesh were imported at all.

Primitive scenes show no mesh index and no scipy import; smooth scenes no texture look-up; baselines
(UA, CAM) no feature classification; uniform contact turns ``needs_orientation`` off.

    python tools/scene_cost.py                 # table
    python tools/scene_cost.py --json          # machine-readable
    python tools/scene_cost.py --scenes cube bunny
    python tools/scene_cost.py --scenes two-bars.toml   # files relative to the current directory
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
import tracemalloc
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parents[1]

DEFAULT_SCENES = ("sphere", "cube", "task3", "teapot", "bunny")
CONFIGS = (
    ("tactdeform", "orientation"),
    ("tactdeform", "uniform"),
    ("ua", "orientation"),
    ("cam", "orientation"),
)


def _child(scene_name: str, approach: str, contact_mode: str, measure: str) -> dict[str, Any]:
    # The package itself is imported first: what is measured is the scene's own cost, including the
    # optional dependencies (scipy) that only a mesh scene imports.
    import numpy as np

    from tactdeform_hw.render.scene import RenderOptions, load_scene

    if measure == "memory":
        tracemalloc.start()
    t0 = time.perf_counter()
    scene = load_scene(scene_name, options=RenderOptions(contact_mode=contact_mode, approach=approach))
    scene.prepare()
    build_s = time.perf_counter() - t0
    lo, hi = scene.bounds_mm
    t1 = time.perf_counter()
    scene.query((lo + hi) / 2.0 + np.array([0.0, 0.0, -float(np.max(hi - lo))]))
    first_query_s = time.perf_counter() - t1
    out: dict[str, Any] = {
        "scene": scene_name,
        "approach": approach,
        "contact_mode": contact_mode,
        "needs": scene.needs.as_dict(),
        "built": scene.built_parts(),
        "objects": len(scene.objects),
    }
    if measure == "memory":
        held, peak = tracemalloc.get_traced_memory()
        tracemalloc.stop()
        out["peak_mib"] = peak / 2**20
        out["held_mib"] = held / 2**20
    else:
        out["build_ms"] = build_s * 1e3
        out["first_query_ms"] = first_query_s * 1e3
    return out


def scene_argument(scene: str, cwd: Path | None = None) -> str:
    """What the child gets for ``scene``: a file path made absolute against the caller's working
    directory ``cwd`` (the child runs in the repository), a bare name — a built-in — unchanged."""
    path = Path(scene).expanduser()
    if not path.suffix and len(path.parts) == 1:
        return scene
    return str(((Path.cwd() if cwd is None else cwd) / path).resolve())


def _run(scene: str, approach: str, contact_mode: str, measure: str) -> dict[str, Any]:
    cmd = [sys.executable, __file__, "--child", scene_argument(scene), approach, contact_mode, measure]
    proc = subprocess.run(cmd, capture_output=True, text=True, cwd=REPO)
    if proc.returncode != 0:
        last = (proc.stderr.strip().splitlines() or ["failed"])[-1]
        return {"scene": scene, "approach": approach, "contact_mode": contact_mode, "error": last}
    result: dict[str, Any] = json.loads(proc.stdout.strip().splitlines()[-1])
    result["scene"] = scene  # as the caller named it
    return result


def measure(scenes: list[str]) -> list[dict[str, Any]]:
    rows = []
    for scene in scenes:
        for approach, contact_mode in CONFIGS:
            timing = _run(scene, approach, contact_mode, "time")
            if "error" in timing:
                rows.append(timing)
                continue
            memory = _run(scene, approach, contact_mode, "memory")
            timing.update({k: memory[k] for k in ("peak_mib", "held_mib") if k in memory})
            rows.append(timing)
    return rows


def _flags(row: dict[str, Any]) -> str:
    n = row["needs"]
    return "".join(
        ch if n[key] else "-"
        for ch, key in (
            ("M", "needs_mesh_index"),
            ("F", "needs_features"),
            ("T", "needs_texture"),
            ("O", "needs_orientation"),
            ("C", "needs_contains"),
        )
    )


def print_table(rows: list[dict[str, Any]]) -> None:
    head = (
        f"{'scene':8} {'approach':10} {'contact':11} {'needs':6} {'build ms':>9} {'peak MiB':>9} "
        f"{'held MiB':>9} {'index':>5} {'feat':>5} {'class':>5} {'tex':>4} {'scipy':>5}"
    )
    print(head)
    print("-" * len(head))
    for row in rows:
        if "error" in row:
            print(f"{row['scene']:8} {row['approach']:10} {row['contact_mode']:11} skipped: {row['error']}")
            continue
        b = row["built"]
        print(
            f"{row['scene']:8} {row['approach']:10} {row['contact_mode']:11} {_flags(row):6} "
            f"{row['build_ms']:9.1f} {row.get('peak_mib', float('nan')):9.2f} "
            f"{row.get('held_mib', float('nan')):9.2f} {len(b['mesh_index']):5d} "
            f"{len(b['mesh_features']):5d} {len(b['feature_classification']):5d} "
            f"{len(b['texture_lookup']):4d} {('yes' if b['scipy_imported'] else 'no'):>5}"
        )
    print("\nneeds: M mesh index, F feature classification, T texture, O orientation (θ), C inside tests")
    print("built: index/feat = meshes with a KD-tree / feature tables; class = objects classifying contacts;")
    print("       tex = objects with a texture-region look-up; scipy = imported by the build")


def main(argv: list[str] | None = None) -> int:
    args = sys.argv[1:] if argv is None else argv
    if args and args[0] == "--child":
        print(json.dumps(_child(*args[1:5])))
        return 0
    parser = argparse.ArgumentParser(description="Build time and memory of scenes, and what each leaves out.")
    parser.add_argument(
        "--scenes",
        nargs="+",
        default=list(DEFAULT_SCENES),
        help="built-in names or scene/mesh files (relative to the current directory)",
    )
    parser.add_argument("--json", action="store_true", help="print JSON rows instead of a table")
    ns = parser.parse_args(args)
    rows = measure(ns.scenes)
    if ns.json:
        print(json.dumps(rows, indent=2))
    else:
        print_table(rows)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
