"""What a served board costs in CPU per second of stimulation: a firmware tree's host build or a model.

    python tools/serving_cpu.py --firmware-src DIR [--electrodes 32] [--seconds-s 3] [--json]
    python tools/serving_cpu.py --firmware v1.2 [--electrodes 32]

A served board must keep pace with the wall clock: the driver's proofs wait about one scan period past
the drain of their request.  This serves the board on a pseudo-terminal (as ``emulate --pty`` does),
opens it with ``open_device``, configures ``--electrodes`` electrodes at 1000 µA, sends a pattern of ones
and then only sleeps: the process's CPU time over ``--seconds-s`` is the serving thread's.
"""

from __future__ import annotations

import argparse
import json
import resource
import sys
import time
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from tactdeform_hw.device import StimConfig  # noqa: E402
from tactdeform_hw.device.driver.serial_driver import open_device  # noqa: E402
from tactdeform_hw.emulator.serving.pty_server import PtyServer  # noqa: E402
from tactdeform_hw.emulator.serving.realtime import RealtimeEmulator  # noqa: E402
from tactdeform_hw.errors import TactDeformError  # noqa: E402


def _cpu_s() -> float:
    r = resource.getrusage(resource.RUSAGE_SELF)
    return r.ru_utime + r.ru_stime


def measure(firmware_src: str | None, firmware: str, electrodes: int, seconds_s: float) -> dict[str, Any]:
    """Serve, open, stimulate, and return the CPU seconds spent per second of stimulation."""
    board: Any
    if firmware_src is not None:
        from tactdeform_hw.emulator.hostbuild.timed import realtime_host_build

        board = realtime_host_build(firmware_src)
    else:
        board = RealtimeEmulator(firmware=firmware)
    server = PtyServer(board)
    server.start()
    try:
        dev = open_device(server.path)
        try:
            dev.configure(StimConfig(electrode_count=electrodes, current_ua=1000))
            dev.send_pattern([1] * electrodes)
            cpu0, t0 = _cpu_s(), time.monotonic()
            time.sleep(seconds_s)
            cpu1, t1 = _cpu_s(), time.monotonic()
        finally:
            dev.close()
    finally:
        server.stop()
    return {
        "served": firmware_src or f"model {firmware}",
        "electrodes": electrodes,
        "seconds_s": round(t1 - t0, 3),
        "cpu_s_per_s": round((cpu1 - cpu0) / (t1 - t0), 3),
    }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--firmware-src", help="a firmware's PlatformIO tree, built on this machine")
    ap.add_argument(
        "--firmware", default="v1.2", choices=("v1.2", "v2"), help="the model (no --firmware-src)"
    )
    ap.add_argument("--electrodes", type=int, default=32, help="electrodes configured (1-32, compact board)")
    ap.add_argument("--seconds-s", type=float, default=3.0, help="stimulation measured (default 3)")
    ap.add_argument("--json", action="store_true", help="one JSON object on stdout")
    args = ap.parse_args(argv)
    if not 1 <= args.electrodes <= 32:
        ap.error(f"--electrodes {args.electrodes}: the compact board has 1 to 32")
    if not 0.1 <= args.seconds_s <= 600:
        ap.error(f"--seconds-s {args.seconds_s}: use 0.1 to 600 s")
    try:
        out = measure(args.firmware_src, args.firmware, args.electrodes, args.seconds_s)
    except TactDeformError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1
    if args.json:
        print(json.dumps(out))
    else:
        print(f"{out['served']}: {out['electrodes']} electrodes, {out['cpu_s_per_s']} s of CPU per second")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
