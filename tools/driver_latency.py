"""Host write → pattern in force for one 32-electrode frame *through the device layer*, firmware v1.2
and v2 side by side, on the timed models (USB link, simulated time).

The TactDeform setting (200 µs, 45 µs discharge, 125 Hz); the driver alternates two frames (the front and
the back half of the array active, 1000 µA) at ``--frames`` write moments spread over the period.  For each
frame: from the moment ``send_pattern`` is called to the start of the first scan that delivers exactly the
new frame (every active channel at its height, every other channel without current), and to its last
channel's pulse.  v1.2 carries the frame as levels under one pulse height; v2 as 32 heights.

    python tools/driver_latency.py [--frames 64] [--json]
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from tactdeform_hw.device.driver.config import StimConfig  # noqa: E402
from tactdeform_hw.device.driver.serial_driver import EtactileKitDevice  # noqa: E402
from tactdeform_hw.emulator.faults import TimedPort  # noqa: E402
from tactdeform_hw.emulator.timed.model_v1_2 import TimedEmulator  # noqa: E402
from tactdeform_hw.emulator.timed.model_v2 import TimedEmulatorV2  # noqa: E402

N = 32
CURRENT_UA = 1000
FRONT = [1] * (N // 2) + [0] * (N // 2)
BACK = [0] * (N // 2) + [1] * (N // 2)


class _V2Board(TimedEmulatorV2):
    """The timed v2 model with the host-side reply buffer the timed port reads from."""

    def __init__(self) -> None:
        super().__init__()
        self._host = bytearray()

    def read_tx(self, size: int | None = None) -> bytes:  # type: ignore[override]
        self._host += super().read_tx()
        n = len(self._host) if size is None else min(size, len(self._host))
        out = bytes(self._host[:n])
        del self._host[:n]
        return out

    @property
    def in_waiting(self) -> int:
        self._host += super().read_tx()
        return len(self._host)

    def reset(self, why: str = "reset") -> None:
        self.emulator.reset()


def _scans_v12(board: TimedEmulator, since_us: float) -> list[tuple[float, float, frozenset[int]]]:
    """(start µs, last pulse µs, channels with current) of every scan from ``since_us``."""
    t = board.reports.pulse_table(since_us)
    rows: dict[int, list[tuple[float, int, float]]] = {}
    for cyc, ch, start_us, ua in zip(t["cycle"], t["channel"], t["start_us"], t["current_ua"], strict=True):
        rows.setdefault(int(cyc), []).append((float(start_us), int(ch), float(ua)))
    out = []
    for cyc in sorted(rows):
        r = rows[cyc]
        out.append((min(x[0] for x in r), max(x[0] for x in r), frozenset(ch for _, ch, ua in r if ua > 0)))
    return out


def _scans_v2(board: _V2Board, since_us: float) -> list[tuple[float, float, frozenset[int]]]:
    out = []
    for s in board.scans:
        if s.start_ns / 1000 < since_us or not s.pulses:
            continue
        start = s.start_ns / 1000
        last = max((s.start_ns + onset) / 1000 for _, onset, _, _, _ in s.pulses)
        out.append((start, last, frozenset(ch for ch, _, code, _, _ in s.pulses if code > 0)))
    return out


def measure(firmware: str, frames: int) -> dict[str, Any]:
    board: Any = _V2Board() if firmware == "v2" else TimedEmulator()
    port = TimedPort(board, robust_encoding=False)
    dev = EtactileKitDevice(port, firmware=firmware)
    cfg = StimConfig(electrode_count=N, current_ua=CURRENT_UA)
    dev.configure(cfg)
    dev.send_pattern(BACK)
    port.advance(0.05)
    period_s = 1 / cfg.rate_hz
    in_force: list[float] = []
    last: list[float] = []
    host: list[float] = []
    for i in range(frames):
        # a write moment spread over the period (golden-ratio steps), after the previous frame settled
        port.advance(0.03 + period_s * ((i * 0.6180339887498949) % 1.0))
        levels = FRONT if i % 2 == 0 else BACK
        want = frozenset(k for k, v in enumerate(levels) if v)
        t0 = port.now_s
        dev.send_pattern(levels)
        host.append((port.now_s - t0) * 1e3)
        port.advance(0.06)
        scans = _scans_v2(board, t0 * 1e6) if firmware == "v2" else _scans_v12(board, t0 * 1e6)
        hit = next((s for s in scans if s[2] == want), None)
        if hit is None:
            raise RuntimeError(f"{firmware}: frame {i} never in force")
        in_force.append(hit[0] / 1e3 - t0 * 1e3)
        last.append(hit[1] / 1e3 - t0 * 1e3)
    dev.close()

    def stats(v: list[float]) -> dict[str, float]:
        return {"min": round(min(v), 3), "median": round(statistics.median(v), 3), "max": round(max(v), 3)}

    return {
        "firmware": firmware,
        "frames": frames,
        "host_call_ms": stats(host),
        "in_force_ms": stats(in_force),
        "last_channel_ms": stats(last),
    }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=64, help="frames measured per version (default 64)")
    ap.add_argument("--json", action="store_true", help="print JSON")
    args = ap.parse_args(argv)
    if args.frames < 1:
        ap.error(f"--frames {args.frames}: at least 1")
    rows = [measure(fw, args.frames) for fw in ("v1.2", "v2")]
    if args.json:
        print(json.dumps(rows, indent=2))
        return 0
    print(
        f"host write -> 32-electrode frame in force through the driver ({args.frames} frames, USB, 125 "
        "Hz, ms)"
    )
    print(
        f"{'firmware':<9} {'call min/med/max':>22} {'in force min/med/max':>24} "
        f"{'last channel min/med/max':>28}"
    )
    for r in rows:

        def f(k: str, r: dict[str, Any] = r) -> str:
            return f"{r[k]['min']:.2f}/{r[k]['median']:.2f}/{r[k]['max']:.2f}"

        print(f"{r['firmware']:<9} {f('host_call_ms'):>22} {f('in_force_ms'):>24} {f('last_channel_ms'):>28}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
