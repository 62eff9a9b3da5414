"""How late is a live pose?  A trajectory streamed over UDP into ``tactdeform-hw render --tracking``, against
an emulated board on a pty, stage by stage against the paper's 14 ms.

    python tools/live_latency.py          # 72 Hz, the TactDeform setting (32 electrodes, 125 Hz)
    python tools/live_latency.py --rate-hz 120 --drop 0.05 --json

The board is the timed real-time model (v1.2 by default) served on a pty by this process
(:class:`~tactdeform_hw.emulator.serving.pty_server.PtyServer`, in its own thread); the renderer is
``tactdeform-hw render`` in a process of its own, opening the pty as any serial port.  This process sends
the samples at the trajectory's clock (``--drop``: a fraction of datagrams left out, seeded), then ends the
renderer with SIGINT as a user would.  The renderer writes its ``--latency-report`` (``time.monotonic()``
when each sample was received, its pattern computed and its bytes written); the board's own command
reports give, on the same monotonic clock (its ``t0``), when each pattern command took effect and when the
pattern was in force: its first pulse, or for an all-off pattern the start of the first scan after it took
effect.  Patterns are joined in order (the n-th pattern the renderer wrote is the n-th pattern command the
board completed after the renderer's configuration).

Stages (ms, median / p99 / max): received → computed, received → written, written → in force, received →
in force (the paper's "parameter change to pattern update": ≤ 14 ms at 72 Hz, one 8 ms scan period
included).  Also the stream's loss, jitter and rate as the renderer saw them, and the renderer process's
CPU time.  Run it alone on an idle machine: it measures wall-clock latency.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from tactdeform_hw.render.live import send_samples, stage_stats  # noqa: E402

PAPER_MS = 14.0
#: Approaches to a face, edges and a corner, a rough slide and a free exploration: 36 s at 72 Hz and 43
#: pattern changes of every kind (expansion frames, contact patterns, texture shifts, all-off) per lap.
DEFAULT_TRAJECTORIES = "approach-face,approach-edge-h,approach-corner,slide-rough,explore,approach-edge-d1"


def _poses(args: argparse.Namespace) -> list[Any]:
    """The trajectories named (comma-separated), one after the other, ``--laps`` times, on one clock."""
    from dataclasses import replace

    from tactdeform_hw import load_scene, make_trajectory
    from tactdeform_hw.render.tracking import read_pose_csv
    from tactdeform_hw.render.trajectories import scene_for_trajectory

    scene = load_scene(args.scene)
    parts = []
    for name in args.trajectory.split(","):
        if name.lower().endswith(".csv"):
            parts.append(list(read_pose_csv(name)))
        else:
            parts.append(list(make_trajectory(name, scene_for_trajectory(name, scene), rate_hz=args.rate_hz)))
    out: list[Any] = []
    gap = 1.0 / args.rate_hz
    for _ in range(args.laps):
        for rows in parts:
            shift = 0.0 if not out else out[-1].t_s + gap - rows[0].t_s
            out += [replace(p, t_s=p.t_s + shift) for p in rows]
    return out


class BoardLog:
    """The board's completed pattern commands, collected while the run lasts (the model keeps 10 s)."""

    def __init__(self, server: Any) -> None:
        self.server = server
        self.board = server.board
        self.seen: dict[tuple[int, float], dict[str, Any]] = {}
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._poll, daemon=True)

    def start(self) -> None:
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(5)
        self.collect()

    def _poll(self) -> None:
        while not self._stop.wait(0.5):
            self.collect()

    def collect(self) -> None:
        b = self.board
        with b.lock:
            b.state()  # up to now
            t0 = b.t0
            runs = list(b.timed.runs)
            cmds = [c for c in b.timed.commands if c.name == "PATTERN" and c.effect_us is not None]
        for c in cmds:
            key = (c.device_offset, c.effect_us)
            if key in self.seen and self.seen[key]["in_force_s"] is not None:
                continue
            if c.first_pulse_us is not None:
                in_force_us: float | None = c.first_pulse_us
            else:
                in_force_us = _first_scan_after(runs, c.effect_us)
            self.seen[key] = {
                "sent_s": None if c.sent_us is None else t0 + c.sent_us / 1e6,
                "effect_s": t0 + c.effect_us / 1e6,
                "in_force_s": None if in_force_us is None else t0 + in_force_us / 1e6,
                "on": sum(1 for v in (c.value or b"") if v),
            }

    def patterns(self) -> list[dict[str, Any]]:
        return sorted(self.seen.values(), key=lambda d: d["effect_s"])


def _first_scan_after(runs: list[Any], at_us: float) -> float | None:
    at_ns = at_us * 1000.0
    best: float | None = None
    for r in runs:
        if r.end_ns < at_ns:
            continue
        k = max(0, int(-(-(at_ns - r.start_ns) // r.stride_ns))) if r.stride_ns else 0
        if k < r.count:
            start = r.start_ns + k * r.stride_ns
            best = start if best is None else min(best, start)
    return None if best is None else best / 1000.0


def _free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def measure(args: argparse.Namespace) -> dict[str, Any]:
    from tactdeform_hw.emulator.serving.pty_server import PtyServer

    poses = _poses(args)
    port = _free_udp_port()
    report = Path(args.report)
    server = PtyServer(firmware=args.firmware).start()
    log = BoardLog(server)
    env = dict(os.environ, PYTHONPATH=str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    cmd = [
        sys.executable, "-m", "tactdeform_hw", "render", "--scene", args.scene,
        "--tracking", f"udp://127.0.0.1:{port}", "--device", server.path, "--firmware", args.firmware,
        "--current-ua", str(args.current_ua), "--latency-report", str(report), "--json",
    ]  # fmt: skip
    usage0 = resource.getrusage(resource.RUSAGE_CHILDREN)
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
    try:
        assert proc.stderr is not None
        while True:  # the renderer says when it listens (after the board was identified and configured)
            lineno = proc.stderr.readline()
            if not lineno:
                raise RuntimeError("the renderer ended before it listened: " + (proc.stderr.read() or ""))
            if "live from" in lineno:
                break
        time.sleep(0.2)
        log.start()
        sent, dropped = send_samples(poses, ("127.0.0.1", port), drop=args.drop, seed=args.seed)
        time.sleep(0.3)
        proc.send_signal(signal.SIGINT)
        out, err = proc.communicate(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        log.stop()
        server.stop()
    usage1 = resource.getrusage(resource.RUSAGE_CHILDREN)
    summary = json.loads(out)
    rows = [json.loads(x) for x in report.read_text().splitlines()]
    return _join(args, rows, log.patterns(), summary, sent, dropped, proc.returncode, usage0, usage1, err)


def _join(
    args: argparse.Namespace,
    rows: list[dict[str, Any]],
    board: list[dict[str, Any]],
    summary: dict[str, Any],
    sent: int,
    dropped: int,
    code: int,
    usage0: Any,
    usage1: Any,
    err: str,
) -> dict[str, Any]:
    written = [r for r in rows if r["written_s"] is not None]
    first_written = written[0]["computed_s"] if written else float("inf")
    # the pattern commands the renderer sent (its configuration's all-off and the last all-off come
    # before and after): from the first one after the first frame was handed to the device
    cmds = [b for b in board if b["sent_s"] is not None and b["sent_s"] >= first_written - 0.001]
    in_force: list[float] = []
    w_to_f: list[float] = []
    matched = mismatched = 0
    i = 0
    for r in written:
        for pattern in r["patterns"]:
            if i >= len(cmds):
                break
            c = cmds[i]
            i += 1
            if c["on"] != sum(1 for v in pattern if v):
                mismatched += 1
                continue
            matched += 1
            if pattern is r["patterns"][-1] and c["in_force_s"] is not None:
                in_force.append((c["in_force_s"] - r["received_s"]) * 1e3)
                w_to_f.append((c["in_force_s"] - r["written_s"]) * 1e3)
    cpu_s = (usage1.ru_utime - usage0.ru_utime) + (usage1.ru_stime - usage0.ru_stime)
    wall_s = (rows[-1]["received_s"] - rows[0]["received_s"]) if len(rows) > 1 else 0.0
    stages = {
        "received_to_computed": stage_stats([(r["computed_s"] - r["received_s"]) * 1e3 for r in rows]),
        "received_to_written": stage_stats([(r["written_s"] - r["received_s"]) * 1e3 for r in written]),
        "written_to_in_force": stage_stats(w_to_f),
        "received_to_in_force": stage_stats(in_force),
    }
    p99 = stages["received_to_in_force"]["p99_ms"]
    return {
        "rate_hz": args.rate_hz,
        "drop": args.drop,
        "firmware": args.firmware,
        "trajectory": args.trajectory,
        "samples": len(rows),
        "datagrams_sent": sent,
        "datagrams_left_out": dropped,
        "stages": stages,
        "paper_ms": PAPER_MS,
        "verdict": None if p99 is None else ("WITHIN" if p99 <= PAPER_MS else "OVER"),
        "patterns_matched": matched,
        "patterns_mismatched": mismatched,
        "stream": summary.get("live"),
        "renderer_cpu_s": round(cpu_s, 3),
        "renderer_cpu_pct_of_stream": round(100.0 * cpu_s / wall_s, 1) if wall_s else None,
        "exit_status": code,
        "stop_line": err.strip().splitlines()[-1] if err.strip() else "",
        "loadavg": os.getloadavg(),
    }


def _print(res: dict[str, Any]) -> None:
    print(
        f"{res['samples']} samples at {res['rate_hz']:g} Hz "
        f"({res['datagrams_left_out']} datagram(s) left out), "
        f"firmware {res['firmware']}, {res['patterns_matched']} patterns joined with the board's"
    )
    print(f"{'stage':<24}{'n':>6}{'median ms':>12}{'p99 ms':>10}{'max ms':>10}")
    for name, d in res["stages"].items():
        print(f"{name:<24}{d['n']:>6}{d['median_ms']!s:>12}{d['p99_ms']!s:>10}{d['max_ms']!s:>10}")
    s = res["stream"] or {}
    print(
        f"stream: lost {s.get('lost')} ({s.get('loss_pct')} %), jitter {s.get('jitter_ms')} ms, "
        f"rate {s.get('rate_hz')} Hz, bad {s.get('bad_total')}"
    )
    print(
        f"renderer CPU {res['renderer_cpu_s']} s ({res['renderer_cpu_pct_of_stream']} % of the stream's time)"
    )
    print(
        f"verdict: received → in force p99 {res['stages']['received_to_in_force']['p99_ms']} ms against "
        f"{res['paper_ms']:g} ms: {res['verdict']}; load average {res['loadavg'][0]:.2f}"
    )


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--rate-hz", type=float, default=72.0, help="tracking rate (default 72, the VR loop)")
    ap.add_argument("--drop", type=float, default=0.0, help="fraction of datagrams left out (default 0)")
    ap.add_argument(
        "--trajectory",
        default=DEFAULT_TRAJECTORIES,
        help="synthetic trajectories or FILE.csv, comma-separated, streamed one after the other "
        f"(default {DEFAULT_TRAJECTORIES})",
    )
    ap.add_argument("--scene", default="cube")
    ap.add_argument("--laps", type=int, default=2, help="times the trajectories are streamed (default 2)")
    ap.add_argument("--firmware", choices=("v1.2", "v2"), default="v1.2")
    ap.add_argument("--current-ua", type=int, default=1000)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument(
        "--report",
        default=None,
        help="keep the renderer's --latency-report as FILE (default: a temporary file, removed)",
    )
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args(argv)
    if not 0.0 <= args.drop < 1.0:
        ap.error(f"--drop {args.drop}: a fraction in [0, 1)")
    if not args.rate_hz > 0:
        ap.error(f"--rate-hz {args.rate_hz}: > 0")
    if args.report is None:
        import tempfile

        with tempfile.TemporaryDirectory() as tmp:
            args.report = str(Path(tmp) / "latency.jsonl")
            res = measure(args)
    else:
        res = measure(args)
    if args.json:
        print(json.dumps(res, indent=2))
    else:
        _print(res)
    return 0 if res["verdict"] == "WITHIN" else 3


if __name__ == "__main__":
    sys.exit(main())
