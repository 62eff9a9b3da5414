"""How well the real-time emulator keeps up with the wall clock, and what a pattern costs through a pty.

Serves the timed board on a real pseudo-terminal (:class:`tactdeform_hw.emulator.serving.pty_server.PtyServer`
with a :class:`tactdeform_hw.emulator.serving.realtime.RealtimeEmulator`), configures it over the pty the way
a
host does (the TactDeform setting by default: 32 electrodes, 200 µs pulses, 45 µs discharge, 125 Hz),
then measures two phases:

* **idle** — nothing is written; the loop wakes for every scan;
* **stream** — a client writes a 32-electrode pattern ``--rate`` times a second (72 Hz: the renderer's
  frame rate) through pyserial.

For each phase: the lag of the loop's wake-ups behind the events they were for (median / p99 / max),
how often it fell behind by more than 1 ms, and the serving thread's CPU time per second of wall time.
For the stream: the latency from each host write (the client's clock) to the first pulse with the new
pattern (the model's report of that command, on the same clock), against the timed model's prediction
for the same configuration and link (:func:`tactdeform_hw.emulator.timed.model_v1_2.pattern_latency`, no pty).

``--firmware-src DIR`` serves a firmware tree built on this machine instead of the Python model (the same
pty server, the USB build's link and timing): the lag and CPU of its serving loop.  The firmware keeps no
record of the commands it completed, so the write-to-pulse latency is measured on the Python model only.

Usage::

    python tools/realtime_lag.py                     # 5 s idle, 10 s stream at 72 Hz
    python tools/realtime_lag.py --idle 2 --stream 5 --json
    python tools/realtime_lag.py --firmware-src ~/eTactileKit/2_Firmware/platform_io_project
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from collections import Counter
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from tactdeform_hw.emulator.firmware.scan import ScanConfig  # noqa: E402
from tactdeform_hw.emulator.serving.realtime import LagRecorder, RealtimeEmulator  # noqa: E402
from tactdeform_hw.emulator.timed.model_v1_2 import configuration_bytes, pattern_latency  # noqa: E402
from tactdeform_hw.protocol import commands as c  # noqa: E402
from tactdeform_hw.protocol import firmware_math as fm  # noqa: E402
from tactdeform_hw.protocol.decoder import decode  # noqa: E402


def tactdeform_config(
    electrodes: int, width_us: int, discharge_us: int, rate_hz: int, height: int
) -> ScanConfig:
    return ScanConfig(
        electrode_num=electrodes,
        polarity=1,
        pulse_height=height,
        pulse_width=width_us,
        sense_pulse_height=0,
        sense_pulse_width=0,
        discharge_time=discharge_us,
        alarm_ticks=fm.alarm_ticks(fm.period_us_from_rate(rate_hz)),
        pattern=bytes([1] * electrodes),
        hv513_num=4,
    )


def configure(port: Any, cfg: ScanConfig, rate_hz: int) -> None:
    """Write the configuration one command per 5 ms (slower than the parser reads: nothing is lost)."""
    for cmd in decode(configuration_bytes(cfg, rate_hz), electrode_num=0):
        port.write(cmd.raw)
        time.sleep(0.005)
    time.sleep(0.05)


def phase(server: Any, seconds: float, stream: tuple[Any, bytes, float] | None) -> dict[str, Any]:
    board: RealtimeEmulator = server.board
    board.lag = LagRecorder(board.lag.limit_us)
    cpu0, wall0 = server.cpu_s, time.monotonic()
    writes: list[float] = []
    if stream is None:
        time.sleep(seconds)
    else:
        port, data, rate = stream
        n = int(seconds * rate)
        for i in range(n):
            due = wall0 + i / rate
            delay = due - time.monotonic()
            if delay > 0:
                time.sleep(delay)
            writes.append(time.monotonic())
            port.write(data)
        time.sleep(0.1)
    wall = time.monotonic() - wall0
    st = board.lag.stats()
    return {
        "seconds": wall,
        "lag_median_ms": st["median_us"] / 1000,
        "lag_p99_ms": st["p99_us"] / 1000,
        "lag_max_ms": st["max_us"] / 1000,
        "wakeups": st["wakeups"],
        "fell_behind": st["behind"],
        "cpu_percent": 100 * (server.cpu_s - cpu0) / wall,
        "writes": writes,
    }


def _stats(xs: list[float]) -> dict[str, float]:
    return {
        "min_us": min(xs),
        "median_us": statistics.median(xs),
        "mean_us": statistics.fmean(xs),
        "max_us": max(xs),
    }


def measured_latency(board: RealtimeEmulator, writes: list[float]) -> dict[str, Any]:
    """Per write, in µs: host write (client clock) → first pulse with the new pattern (model); the
    transport's share (host write → the server's arrival stamp); the model's share (stamp → pulse)."""
    with board.lock:
        reps = [r for r in board.timed.commands if r.name == "PATTERN" and r.sent_us is not None]
    reps = [r for r in reps if r.sent_us is not None and r.sent_us >= (writes[0] - board.t0) * 1e6 - 1]
    total, transport, model = [], [], []
    for w, r in zip(writes, reps):
        if r.first_pulse_us is not None and r.sent_us is not None:
            at = (w - board.t0) * 1e6
            total.append(r.first_pulse_us - at)
            transport.append(r.sent_us - at)
            model.append(r.first_pulse_us - r.sent_us)
    if not total:
        return {"n": 0, "writes": len(writes)}
    return {
        "n": len(total),
        "writes": len(writes),
        **_stats(total),
        "transport": _stats(transport),
        "model": _stats(model),
    }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--idle", type=float, default=5.0, help="seconds of the idle phase (default 5)")
    ap.add_argument("--stream", type=float, default=10.0, help="seconds of the streaming phase (default 10)")
    ap.add_argument("--rate", type=float, default=72.0, help="patterns per second in the stream (default 72)")
    ap.add_argument("--electrodes", type=int, default=32)
    ap.add_argument("--frequency", type=int, default=125, help="stimulation rate, Hz (default 125)")
    ap.add_argument(
        "--firmware-src",
        metavar="DIR",
        help="serve this firmware tree built on the host (needs a C++ compiler) instead of the Python model",
    )
    ap.add_argument("--json", action="store_true", help="print the figures as JSON")
    args = ap.parse_args(argv)
    for name in ("idle", "stream", "rate"):
        if getattr(args, name) <= 0:
            ap.error(f"--{name} must be positive, not {getattr(args, name)}")
    if not 1 <= args.electrodes <= 255:
        ap.error(f"--electrodes must be 1..255, not {args.electrodes}")
    import serial

    from tactdeform_hw.emulator.serving.pty_server import PtyServer

    cfg = tactdeform_config(args.electrodes, 200, 45, args.frequency, 100)
    board = RealtimeEmulator()
    if args.firmware_src is not None:
        from tactdeform_hw.emulator.hostbuild.timed import realtime_host_build
        from tactdeform_hw.errors import TactDeformError

        try:
            board = realtime_host_build(args.firmware_src)
        except TactDeformError as e:
            print(f"realtime_lag.py: --firmware-src {args.firmware_src}: {e}", file=sys.stderr)
            return 3
    server = PtyServer(board).start()
    try:
        port = serial.Serial(server.path, 921600, timeout=0.5)
        configure(port, cfg, args.frequency)
        idle = phase(server, args.idle, None)
        data = c.encode_pattern(cfg.pattern)
        stream = phase(server, args.stream, (port, data, args.rate))
        latency = measured_latency(server.board, stream.pop("writes"))
        idle.pop("writes")
        state = server.board.state()
        port.close()
    finally:
        server.stop()
    pred = pattern_latency(cfg, "usb", phases=64)["first_channel_us"]
    out = {
        "served": args.firmware_src or "model v1.2",
        "config": {"electrodes": args.electrodes, "frequency_hz": args.frequency, "stream_hz": args.rate},
        "idle": idle,
        "stream": stream,
        "pattern_latency_pty": latency,
        "pattern_latency_model": {k: pred[k] for k in ("min", "mean", "max")},
        "hazards": len(server.board.hazards),
        "configured": state.electrode_num == args.electrodes,
        "hazard_kinds": dict(Counter(h.kind.value for h in server.board.hazards)),
    }
    if args.json:
        json.dump(out, sys.stdout, indent=2)
        sys.stdout.write("\n")
        return 0
    where = out["served"]
    print(f"real-time emulator on a pty ({where}): {args.electrodes} electrodes at {args.frequency} Hz")
    print(f"{'phase':<8} {'lag median':>11} {'p99':>9} {'max':>9} {'wake-ups':>9} {'> 1 ms':>7} {'CPU':>7}")
    for name, ph in (("idle", idle), (f"{args.rate:g} Hz", stream)):
        print(
            f"{name:<8} {ph['lag_median_ms']:>8.3f} ms {ph['lag_p99_ms']:>6.3f} ms {ph['lag_max_ms']:>6.3f} "
            f"ms {ph['wakeups']:>9} {ph['fell_behind']:>7} {ph['cpu_percent']:>6.1f}%"
        )
    if latency.get("n"):
        print(
            f"write → first pulse with the new pattern ({latency['n']} of {latency['writes']} writes), "
            "min / median / max:"
        )
        for label, st in (
            ("through the pty", latency),
            ("  the pty and the loop's wake-up", latency["transport"]),
            ("  the timed model (arrival → pulse)", latency["model"]),
        ):
            print(
                f"  {label:<38} {st['min_us'] / 1000:6.2f} / {st['median_us'] / 1000:6.2f} / "
                f"{st['max_us'] / 1000:6.2f} ms"
            )
    if latency.get("n"):  # the prediction beside what was measured (a host build keeps no command records)
        print(
            f"  {'prediction (pattern_latency, USB, 64 phases)':<40} {pred['min'] / 1000:6.2f} / "
            f"{pred['mean'] / 1000:6.2f} (mean) / {pred['max'] / 1000:6.2f} ms"
        )
    kinds = ", ".join(f"{k} {n}" for k, n in out["hazard_kinds"].items())
    print(f"hazards recorded: {out['hazards']}" + (f" ({kinds})" if kinds else ""))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
