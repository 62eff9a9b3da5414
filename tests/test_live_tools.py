"""The live tools end to end (wall clock, processes, a pty board: slow): ``tools/send_tracking.py`` sends
a recorded CSV sample by sample, and ``tools/live_latency.py`` joins a live ``render``'s latency report
with the board's own record of when each pattern was in force."""

from __future__ import annotations

import json
import subprocess
import sys
import threading
from pathlib import Path

from tactdeform_hw.render.live import UdpTrackingSource, parse_sample
from tactdeform_hw.render.tracking import read_pose_csv, write_pose_csv

REPO = Path(__file__).resolve().parents[1]


def test_send_tracking_sends_a_recorded_csv_sample_by_sample(tmp_path: Path) -> None:
    from tactdeform_hw import load_scene, make_trajectory
    from tactdeform_hw.render.trajectories import scene_for_trajectory

    scene = load_scene("cube")
    csv = tmp_path / "hand.csv"
    write_pose_csv(csv, make_trajectory("approach-face", scene_for_trajectory("approach-face", scene))[:40])
    want = read_pose_csv(csv)
    src = UdpTrackingSource("127.0.0.1", 0)
    got = []
    done = threading.Event()

    def listen() -> None:
        while not done.is_set():
            r = src.receive(0.05)
            if r is not None:
                got.append(parse_sample(r[0], r[1]))

    th = threading.Thread(target=listen, daemon=True)
    th.start()
    out = subprocess.run(
        [sys.executable, str(REPO / "tools" / "send_tracking.py"), str(csv), "--to",
         f"127.0.0.1:{src.address[1]}", "--speed", "4", "--header"],
        capture_output=True, text=True, timeout=30,
    )  # fmt: skip
    done.set()
    th.join(2)
    src.close()
    assert out.returncode == 0, out.stderr
    assert "sent 40 sample(s)" in out.stdout
    assert [s.t_s for s in got if not isinstance(s, str)] == [p.t_s for p in want]


def test_live_latency_joins_the_board_record(tmp_path: Path) -> None:
    out = subprocess.run(
        [sys.executable, str(REPO / "tools" / "live_latency.py"), "--trajectory", "approach-face", "--json",
         "--report", str(tmp_path / "lat.jsonl"), "--drop", "0.05", "--laps", "1"],
        capture_output=True, text=True, timeout=60,
    )  # fmt: skip
    assert out.returncode in (0, 3), out.stderr
    res = json.loads(out.stdout)
    assert res["exit_status"] == 130 and "every channel off" in res["stop_line"]
    assert res["patterns_matched"] > 0 and res["patterns_mismatched"] == 0
    assert res["datagrams_left_out"] > 0 and res["stream"]["lost"] > 0
    st = res["stages"]
    assert set(st) == {
        "received_to_computed",
        "received_to_written",
        "written_to_in_force",
        "received_to_in_force",
    }
    assert st["received_to_in_force"]["n"] > 0
    assert st["received_to_in_force"]["median_ms"] >= st["received_to_written"]["median_ms"]
