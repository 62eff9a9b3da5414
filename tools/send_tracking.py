"""Send a recorded (or synthetic) trajectory to ``tactdeform-hw render --tracking udp://HOST:PORT`` as a hand
tracker would: one datagram per sample at the trajectory's own clock.

    tactdeform-hw render --scene cube --tracking udp://127.0.0.1:9870 &
    python tools/send_tracking.py hand.csv --to 127.0.0.1:9870
    python tools/send_tracking.py approach-face --scene cube --to 127.0.0.1:9870 --drop 0.05 --loop 3

A CSV has the header ``t_s,x_mm,y_mm,z_mm,qw,qx,qy,qz`` (what ``render --trajectory`` reads); a name is
one of the synthetic trajectories, planned over ``--scene`` at ``--rate-hz``.
"""

from __future__ import annotations

import argparse
import sys
from dataclasses import replace
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from tactdeform_hw.errors import TactDeformError  # noqa: E402


def poses_of(source: str, scene_name: str, rate_hz: float) -> list[Any]:
    if source.lower().endswith(".csv"):
        from tactdeform_hw.render.tracking import read_pose_csv

        return list(read_pose_csv(source))
    from tactdeform_hw import load_scene, make_trajectory
    from tactdeform_hw.render.trajectories import scene_for_trajectory

    scene = load_scene(scene_name)
    return list(make_trajectory(source, scene_for_trajectory(source, scene), rate_hz=rate_hz))


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("trajectory", metavar="FILE.csv|NAME")
    ap.add_argument("--to", required=True, metavar="HOST:PORT", help="where render --tracking listens")
    ap.add_argument("--scene", default="cube", help="the scene a synthetic trajectory is planned over")
    ap.add_argument("--rate-hz", type=float, default=72.0, help="a synthetic trajectory's rate (default 72)")
    ap.add_argument("--speed", type=float, default=1.0, help="play this many times as fast (default 1)")
    ap.add_argument("--drop", type=float, default=0.0, help="fraction of datagrams left out (default 0)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--loop", type=int, default=1, help="send it this many times, the clock going on")
    ap.add_argument("--header", action="store_true", help="prefix each datagram with the CSV header line")
    args = ap.parse_args(argv)
    host, sep, port = args.to.rpartition(":")
    if not sep or not port.isdigit():
        ap.error(f"--to {args.to!r}: HOST:PORT")
    from tactdeform_hw.render.live import send_samples

    try:
        poses = poses_of(args.trajectory, args.scene, args.rate_hz)
        if not poses:
            ap.error(f"{args.trajectory}: no poses")
        period = poses[-1].t_s - poses[0].t_s + (poses[1].t_s - poses[0].t_s if len(poses) > 1 else 0.0)
        laps = [replace(p, t_s=p.t_s + k * period) for k in range(max(1, args.loop)) for p in poses]
        sent, left_out = send_samples(
            laps, (host or "127.0.0.1", int(port)), drop=args.drop, seed=args.seed, header=args.header,
            speed=args.speed,
        )  # fmt: skip
    except (TactDeformError, OSError) as exc:
        print(f"send_tracking: error: {exc}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        return 130
    print(f"sent {sent} sample(s) to {host or '127.0.0.1'}:{port}; {left_out} left out")
    return 0


if __name__ == "__main__":
    sys.exit(main())
