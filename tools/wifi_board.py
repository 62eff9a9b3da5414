"""The v2 board in real time over a pty and over TCP: how well it keeps up, and what a pattern costs.

Serves the timed v2 model (:class:`tactdeform_hw.emulator.serving.realtime.RealtimeEmulator` with
``firmware="v2"``) on a real pseudo-terminal (the serial build: USB link, 1024-byte queue) and on a
loopback TCP port (the Wi-Fi build: TCP flow control), configures it the way the upstream hosts do (the
TactDeform setting by default: 32 electrodes, mode 0, 200 µs pulses, 45 µs discharge, 125 Hz), then
measures two phases on each transport:

* **idle** — nothing is written; the loop wakes for every scan;
* **stream** — a client writes a frame of per-electrode heights (0xFE + 32 × u16) ``--rate`` times a
  second, either whole (one write) or as the upstream Python and Unity APIs do (``--chunking upstream``:
  8-byte chunks with 3 ms after each, so a 65-byte frame takes at least 27 ms and the rate is capped).

For each phase: the lag of the loop's wake-ups behind the events they were for (median / p99 / max), how
often it fell behind by more than 1 ms, and the serving thread's CPU per second of wall time.  For the
stream: per frame, host write (the client's clock, before its first byte) → the parser stored it
("applied") and → the first pulse at the new heights ("in force"), against the offline model's prediction
for the same link and chunking (:func:`tactdeform_hw.emulator.timed.model_v2.pattern_in_force_v2`).

Usage::

    python tools/wifi_board.py                       # 3 s idle, 6 s stream at 72 Hz, pty and TCP
    python tools/wifi_board.py --transport tcp --chunking upstream --json
"""

from __future__ import annotations

import argparse
import json
import socket
import statistics
import sys
import time
from collections import Counter
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from tactdeform_hw.emulator.serving.realtime import (  # noqa: E402
    SERIAL_USB,
    WIFI_TCP,
    LagRecorder,
    RealtimeEmulator,
    TcpLink,
)
from tactdeform_hw.emulator.timed.model_v2 import pattern_in_force_v2  # noqa: E402
from tactdeform_hw.protocol.commands import V2_COMMANDS as v2  # noqa: E402
from tactdeform_hw.protocol.firmware import OpcodeV2  # noqa: E402

CHUNK_BYTES, CHUNK_GAP_S = 8, 0.003  # upstream's write_byte_array / SerialHandler.Write


def frame(k: int, n: int) -> list[int]:
    """Frame ``k``: heights that differ from the previous frame's on every channel."""
    return [200 + 10 * (k % 64) + ch for ch in range(n)]


class Client:
    """A host on one transport: ``write`` as a whole or as upstream chunks; ``read``."""

    def __init__(self, transport: str, where: Any, chunking: str) -> None:
        self.chunking = chunking
        if transport == "pty":
            import serial

            self.port: Any = serial.Serial(where, 921600, timeout=1.0)
            self._write = self.port.write
            self.read = self.port.read
        else:
            self.sock = socket.create_connection(where, timeout=5)
            self.sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            self._write = self.sock.sendall
            self.read = self._sock_read

    def _sock_read(self, n: int) -> bytes:
        out = b""
        try:
            while len(out) < n:
                got = self.sock.recv(n - len(out))
                if not got:
                    break
                out += got
        except TimeoutError:
            pass
        return out

    def write(self, data: bytes) -> None:
        if self.chunking == "whole":
            self._write(data)
            return
        for i in range(0, len(data), CHUNK_BYTES):
            self._write(data[i : i + CHUNK_BYTES])
            time.sleep(CHUNK_GAP_S)

    def close(self) -> None:
        (self.port if hasattr(self, "port") else self.sock).close()


def _stats(xs: list[float]) -> dict[str, float]:
    return {
        "min_us": min(xs),
        "median_us": statistics.median(xs),
        "mean_us": statistics.fmean(xs),
        "max_us": max(xs),
    }


def phase(server: Any, client: Client | None, seconds: float, rate: float, n: int) -> dict[str, Any]:
    board: RealtimeEmulator = server.board
    with board.lock:
        board.lag = LagRecorder(board.lag.limit_us)
    cpu0, wall0 = server.cpu_s, time.monotonic()
    writes: list[float] = []
    if client is None:
        time.sleep(seconds)
    else:
        k = 0
        while (now := time.monotonic()) < wall0 + seconds:
            due = wall0 + k / rate
            if due > now:
                time.sleep(due - now)
            writes.append(time.monotonic())
            client.write(v2.encode_pattern(frame(k, n)))
            k += 1
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
        "achieved_hz": len(writes) / seconds if writes else 0.0,
    }


def in_force(board: RealtimeEmulator, writes: list[float], n: int) -> dict[str, Any]:
    """Per frame written, µs from the host write: stored by the parser, first pulse at the new heights."""
    with board.lock:
        timed: Any = board.timed
        applied = [(t, v) for t, op, v in timed.applied if op == OpcodeV2.PATTERN]
        scans = list(timed.scans)
    stored, first = [], []
    for k, w in enumerate(writes):
        heights = frame(k, n)
        at = (w - board.t0) * 1e6
        hit = next((t for t, v in applied if list(v) == heights and t / 1000 >= at), None)  # type: ignore[call-overload]
        if hit is None:
            continue
        stored.append(hit / 1000 - at)
        scan = next((s for s in scans if s.start_ns >= hit), None)
        if scan is not None:
            first.append((scan.start_ns + scan.onset_ns[0]) / 1000 - at)
    out: dict[str, Any] = {"writes": len(writes), "applied": len(stored)}
    if stored:
        out["applied_us"] = _stats(stored)
    if first:
        out["first_pulse_us"] = _stats(first)
    return out


def run_transport(transport: str, args: argparse.Namespace) -> dict[str, Any]:
    n = args.electrodes
    rules = SERIAL_USB if transport == "pty" else WIFI_TCP
    board = RealtimeEmulator(rules=rules, firmware="v2", history_us=600e6)
    server: Any
    if transport == "pty":
        from tactdeform_hw.emulator.serving.pty_server import PtyServer

        server = PtyServer(board).start()
        where: Any = server.path
    else:
        from tactdeform_hw.emulator.serving.tcp_server import TcpServer

        server = TcpServer(board, port=0, rules=rules).start()
        where = server.address
    try:
        client = Client(transport, where, args.chunking)
        setup = (
            v2.encode_electrode_num(n)
            + v2.encode_stim_mode(0)
            + v2.encode_pulse_width(200)
            + v2.encode_discharge(45)
            + v2.encode_frequency(args.frequency)
            + v2.encode_pattern([0] * n)
        )
        client.write(setup + b"\xf4")
        configured = client.read(1) == bytes([n])
        idle = phase(server, None, args.idle, args.rate, n)
        stream = phase(server, client, args.stream, args.rate, n)
        latency = in_force(board, stream.pop("writes"), n)
        idle.pop("writes")
        client.close()
        hazards = dict(Counter(h.kind.value for h in board.hazards))
    finally:
        server.stop()
    link: Any = "usb" if transport == "pty" else TcpLink()
    pred = pattern_in_force_v2(
        frame(1, n), link=link, rate_hz=args.frequency, chunking=args.chunking, phases=32
    )
    return {
        "configured": configured,
        "idle": idle,
        "stream": stream,
        "latency": latency,
        "prediction": {k: pred[k] for k in ("applied_us", "first_channel_us")},
        "hazards": hazards,
    }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--idle", type=float, default=3.0, help="seconds of the idle phase (default 3)")
    ap.add_argument("--stream", type=float, default=6.0, help="seconds of the streaming phase (default 6)")
    ap.add_argument("--rate", type=float, default=72.0, help="frames per second in the stream (default 72)")
    ap.add_argument("--electrodes", type=int, default=32)
    ap.add_argument("--frequency", type=int, default=125, help="stimulation rate, Hz (default 125)")
    ap.add_argument("--transport", choices=("pty", "tcp", "both"), default="both")
    ap.add_argument(
        "--chunking",
        choices=("whole", "upstream"),
        default="whole",
        help="whole frames, or upstream's 8-byte chunks 3 ms apart",
    )
    ap.add_argument("--json", action="store_true", help="print the figures as JSON")
    args = ap.parse_args(argv)
    for name in ("idle", "stream", "rate"):
        if getattr(args, name) <= 0:
            ap.error(f"--{name} must be positive, not {getattr(args, name)}")
    if not 1 <= args.electrodes <= 255:
        ap.error(f"--electrodes must be 1..255, not {args.electrodes}")
    transports = ("pty", "tcp") if args.transport == "both" else (args.transport,)
    out = {
        "config": {
            "electrodes": args.electrodes,
            "frequency_hz": args.frequency,
            "stream_hz": args.rate,
            "chunking": args.chunking,
        },
        **{t: run_transport(t, args) for t in transports},
    }
    if args.json:
        json.dump(out, sys.stdout, indent=2)
        sys.stdout.write("\n")
        return 0
    print(
        f"real-time v2 board: {args.electrodes} electrodes at {args.frequency} Hz, frames at {args.rate:g} "
        f"Hz ({args.chunking} writes)"
    )
    print(
        f"{'transport':<10} {'phase':<8} {'lag median':>11} {'p99':>9} {'max':>9} {'wake-ups':>9} "
        f"{'> 1 ms':>7} {'CPU':>7}"
    )
    for t in transports:
        r = out[t]
        for name in ("idle", "stream"):
            ph = r[name]
            label = name if name == "idle" else f"{ph['achieved_hz']:.0f} Hz"
            print(
                f"{t:<10} {label:<8} {ph['lag_median_ms']:>8.3f} ms {ph['lag_p99_ms']:>6.3f} ms "
                f"{ph['lag_max_ms']:>6.3f} ms {ph['wakeups']:>9} {ph['fell_behind']:>7} "
                f"{ph['cpu_percent']:>6.1f}%"
            )
    print("host write → pattern in force (ms, min / median / max; prediction min / mean / max):")
    for t in transports:
        r = out[t]
        lat, pred = r["latency"], r["prediction"]
        for key, pkey, what in (
            ("applied_us", "applied_us", "stored"),
            ("first_pulse_us", "first_channel_us", "first pulse"),
        ):
            if key in lat:
                s, p = lat[key], pred[pkey]
                print(
                    f"  {t:<4} {what:<12} {s['min_us'] / 1000:6.2f} / {s['median_us'] / 1000:6.2f} / "
                    f"{s['max_us'] / 1000:6.2f}   model {p['min'] / 1000:6.2f} / {p['mean'] / 1000:6.2f} / "
                    f"{p['max'] / 1000:6.2f}  ({lat['applied']} of {lat['writes']} frames)"
                )
        kinds = ", ".join(f"{k} {n}" for k, n in r["hazards"].items())
        print(f"  {t:<4} configured: {r['configured']}; hazards: {kinds or 'none'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
