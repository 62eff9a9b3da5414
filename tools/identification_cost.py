"""What identifying the firmware costs when a board is opened, per firmware and transport.

    python tools/identification_cost.py [--trials 5] [--json]

Each trial opens a freshly served emulated board with ``open_device`` (firmware ``auto``), as a program
does, and closes it.  It reports the wall time of the open (identification included: the wait that lets
v2's 2 s command timeout pass, the off bytes, the signature and its reply, then the driver's own proof)
and the identification's own share — its wait, attempts and bytes — from the device's record.  Boards:

* ``url``: the real-time board in this process (``etactile://?firmware=…``): it declares that it has
  received no byte yet, so nothing is waited out;
* ``pty``: the real-time board on a pseudo-terminal (as ``emulate --pty`` serves it), opened by path;
* ``tcp``: the Wi-Fi board on loopback TCP (as ``emulate --tcp``), opened as ``socket://``;
* ``usb``: the board served as its USB device (as ``emulate --usb``), opened through pyusb.
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from tactdeform_hw.device.driver.serial_driver import open_device  # noqa: E402

FIRMWARES = ("v1.2", "v2")


@contextmanager
def _url(fw: str) -> Iterator[str]:
    yield f"etactile://?firmware={fw}"


# each board server starts on entering its ``with`` and stops on leaving it


@contextmanager
def _pty(fw: str) -> Iterator[str]:
    from tactdeform_hw.emulator.serving.pty_server import PtyServer

    with PtyServer(firmware=fw) as server:
        yield server.path


@contextmanager
def _tcp(fw: str) -> Iterator[str]:
    from tactdeform_hw.emulator.serving.realtime import WIFI_TCP, RealtimeEmulator
    from tactdeform_hw.emulator.serving.tcp_server import TcpServer

    with TcpServer(RealtimeEmulator(rules=WIFI_TCP, firmware=fw), port=0, rules=WIFI_TCP) as server:
        yield server.url


@contextmanager
def _usb(fw: str) -> Iterator[str]:
    from tactdeform_hw.emulator.serving.usb_server import UsbServer

    with UsbServer(firmware=fw) as server:
        yield server.name


TRANSPORTS: dict[str, Callable[[str], Any]] = {"url": _url, "pty": _pty, "tcp": _tcp, "usb": _usb}


def trial(transport: str, fw: str) -> dict[str, float]:
    with TRANSPORTS[transport](fw) as name:
        t0 = time.perf_counter()
        dev = open_device(name)
        opened_s = time.perf_counter() - t0
        try:
            if dev.firmware != fw:
                raise RuntimeError(f"{name}: identified as {dev.firmware}, served {fw}")
            det = dev.identification
            return {
                "open_s": opened_s,
                "settle_s": det.settle_s,
                "attempts": float(det.attempts),
                "bytes": float(det.bytes_sent),
            }
        finally:
            dev.close()


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--trials", type=int, default=5, help="opens per firmware and transport (default 5)")
    ap.add_argument(
        "--transports", default="url,pty,tcp,usb", help="comma-separated (default url,pty,tcp,usb)"
    )
    ap.add_argument("--json", action="store_true")
    a = ap.parse_args(argv)
    if a.trials < 1:
        ap.error(f"--trials={a.trials}: at least 1")
    chosen = [t.strip() for t in a.transports.split(",")]
    for t in chosen:
        if t not in TRANSPORTS:
            ap.error(f"--transports={a.transports}: {t!r} is not one of {', '.join(TRANSPORTS)}")
    out: dict[str, Any] = {}
    for t in chosen:
        for fw in FIRMWARES:
            runs = [trial(t, fw) for _ in range(a.trials)]
            row = {
                "open_median_s": round(statistics.median(r["open_s"] for r in runs), 3),
                "open_max_s": round(max(r["open_s"] for r in runs), 3),
                "settle_s": runs[0]["settle_s"],
                "attempts_max": int(max(r["attempts"] for r in runs)),
                "bytes": int(runs[0]["bytes"]),
                "trials": a.trials,
            }
            out[f"{t} {fw}"] = row
            if not a.json:
                print(
                    f"{t:4s} {fw:5s} open {row['open_median_s']:.3f} s median, {row['open_max_s']:.3f} s max "
                    f"(of which waited {row['settle_s']:.1f} s; {row['attempts_max']} attempt(s), "
                    f"{row['bytes']} bytes)",
                    flush=True,
                )
    if a.json:
        print(json.dumps(out, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
