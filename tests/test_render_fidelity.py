"""Recorded tracking through ``render --trajectory FILE.csv``, the strip and GIF pictures of a run, and
the fidelity report's smoke run (small sweep; the README's table comes from the full run)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from tactdeform_hw.render.tracking import Pose, write_pose_csv

from .conftest import REPO


def press_csv(path: Path, depth_mm: float = 12.0, speed: float = 20.0, rate: float = 72.0) -> Path:
    """A recorded press onto the top face of the built-in cube (centre (0, -200, 450), 200 mm sides):
    the pad faces down (its z axis, out of the pad, is world -y)."""
    top = -200.0 + 100.0
    q = (0.7071067811865476, 0.7071067811865476, 0.0, 0.0)  # finger z → world -y, finger y → world +z
    poses = []
    n = int((10.0 + depth_mm) / speed * rate) + int(0.3 * rate)  # the press, then a short rest
    for i in range(n + 1):
        y = top + 10.0 - speed * i / rate
        poses.append(Pose(i / rate, np.array([0.0, max(y, top - depth_mm), 450.0]), np.array(q)))
    write_pose_csv(path, poses)
    return path


def cli(argv: list[str]) -> int:
    from tactdeform_hw.cli import main

    return main(argv)


def test_recorded_trajectory_replays_over_a_scene(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    pytest.importorskip("matplotlib", reason="the strip picture needs the plot extra")
    csv_path = press_csv(tmp_path / "press.csv")
    frames, strip = tmp_path / "f.jsonl", tmp_path / "strip.png"
    code = cli(
        [
            "render",
            "--scene",
            "cube",
            "--trajectory",
            str(csv_path),
            "--device",
            "emulator",
            "--frames",
            str(frames),
            "--strip",
            str(strip),
            "--json",
            "--quiet",
        ]
    )
    assert code == 0
    out = json.loads(capsys.readouterr().out)
    lines = [json.loads(s) for s in frames.read_text().splitlines()]
    approaching = [ln for ln in lines if ln["sent"] and ln["state"] == "approaching"]
    # 12 mm at one frame per 2 mm: frames 0..6, the face's rings 0, 1, 2, 0, 1, 2, 0 in turn.
    assert len(approaching) == 7
    sizes = [sum(ln["electrodes"]) for ln in approaching]
    assert sizes == [4, 12, 16, 4, 12, 16, 4]
    ts = [ln["t"] for ln in approaching]
    assert np.allclose(np.diff(ts), 2.0 / 20.0, atol=1.5 / 72.0)  # 2 mm at 20 mm/s
    assert out["strip"]["panels"] >= 7 and strip.stat().st_size > 1000


@pytest.mark.parametrize(
    ("row", "message"),
    [
        ("0.1,0,abc,450,1,0,0,0", r"line 3, row 2, column 'y_mm': 'abc' is not a number"),
        ("0.1,0,0,450,1,0,0", r"line 3, row 2, column 'qz': missing value"),
        ("0.1,0,0,nan,1,0,0,0", r"line 3, row 2, column 'z_mm'"),
        ("0.0,0,0,450,1,0,0,0", r"line 3, row 2, column 't_s'"),
    ],
)
def test_a_bad_row_names_its_line_and_column(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], row: str, message: str
) -> None:
    import re

    bad = tmp_path / "bad.csv"
    bad.write_text("t_s,x_mm,y_mm,z_mm,qw,qx,qy,qz\n0.0,0,0,450,1,0,0,0\n" + row + "\n")
    code = cli(["render", "--scene", "cube", "--trajectory", str(bad), "--device", "emulator", "--quiet"])
    err = capsys.readouterr().err
    assert code != 0 and re.search(message, err), err
    assert "Traceback" not in err


def test_recorded_trajectory_refuses_synthetic_options(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    csv_path = press_csv(tmp_path / "p.csv")
    assert cli(["render", "--scene", "cube", "--trajectory", str(csv_path), "--speed", "20", "--quiet"]) != 0
    assert "--speed" in capsys.readouterr().err
    assert cli(["render", "--scene", "cube", "--trajectory", "no-such-name", "--quiet"]) != 0
    assert "--trajectory" in capsys.readouterr().err


def test_gif_holds_each_frame_long_enough_with_its_real_time(tmp_path: Path) -> None:
    pytest.importorskip("matplotlib", reason="the GIF needs the plot extra")
    from tactdeform_hw.render.array import ElectrodeArray
    from tactdeform_hw.viz.array_picture import MIN_DISPLAY_MS, draw_frames_gif

    recs = [
        {
            "t": k / 72.0,
            "state": "approaching",
            "feature": "face",
            "texture": "smooth",
            "electrodes": [1 if i == k else 0 for i in range(32)],
            "sent": True,
        }
        for k in range(5)
    ]
    info = draw_frames_gif(ElectrodeArray.tactdeform(), recs, tmp_path / "a.gif", size_px=(320, 300))
    assert info.frames == 5 and min(info.durations_ms) >= MIN_DISPLAY_MS >= 200
    assert any("250 ms" in n for n in info.notes)


def test_fidelity_report_quick() -> None:
    proc = subprocess.run(
        [sys.executable, "tools/render_fidelity.py", "--quick", "--json"],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert proc.returncode == 0, proc.stderr[-2000:] + proc.stdout[-2000:]
    out = json.loads(proc.stdout)
    names = " ".join(r["requirement"] for r in out["rows"])
    for req in (
        "eq. 1–3",
        "eq. 4",
        "eq. 5",
        "eq. 7",
        "8 directions",
        "onset",
        "Interacting",
        "lost tracking",
        "UA",
        "CAM",
    ):
        assert req in names
    assert out["passed"] == out["total"]
