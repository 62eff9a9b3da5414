"""How long from the owner's death to all-off on the wire.

    python tools/stop_latency.py --trials 50 [--json]
    python tools/stop_latency.py --transport usb --signals KILL --trials 50 [--firmware v1.2|v2|both]

``--transport pty`` (the default): the emulated board is served on a real pseudo-terminal in this
process; an owner process opens it by path (exclusive lock, guardian process, fail-safe), configures it,
drives a pattern at 1 mA and keeps it fed.  Each trial kills the owner — with SIGTERM (its stop handler
switches off) or with SIGKILL (its guardian does) — and measures, on the board's side of the pty, the
time from the signal to the moment the emulated firmware had parsed the bytes that make it safe: no
channel receives current any more (pulse height 0 or no active channel, and sense height 0).  Prints the
median, 95th percentile and maximum of each.  :class:`BoardWatch` is also what the stop tests judge with.

``--transport usb``: the timed board of each firmware is served as its USB device (the server of
``emulate --usb``, in a thread of this process); the owner opens it through pyusb (``usb-emulator://PATH``,
a claim of its own, a USB guardian).  The figure is taken from the board's delivered-pulse record: the
time from the signal to the last pulse that carried current (the guardian can only act once the dead
owner's claim is released, then waits out the owner's queue, as over a pty).
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import statistics
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))

from tactdeform_hw.emulator import Emulator  # noqa: E402
from tactdeform_hw.emulator.pty_server import PtyServer  # noqa: E402
from tactdeform_hw.protocol.constants import PATTERN_BIPHASIC, PATTERN_MONOPHASIC  # noqa: E402


def delivering(state: dict[str, Any]) -> bool:
    """Whether the firmware state delivers current on any channel: a stimulation pulse (pattern value 1
    or 2 at a height above 0) or a sense pulse (any other value, at a sense height above 0)."""
    n = int(state["electrode_num"])
    if n == 0:
        return False
    levels = state["stim_pattern"][:n]
    if state["sense_pulse_height"] > 0:
        return True
    return state["pulse_height"] > 0 and any(v in (PATTERN_MONOPHASIC, PATTERN_BIPHASIC) for v in levels)


class BoardWatch:
    """An emulator whose every parsed chunk is judged: it records when the board started and stopped
    delivering current (monotonic time, taken right after the firmware model parsed the chunk)."""

    def __init__(self, emulator: Emulator | None = None) -> None:
        self.emulator = emulator if emulator is not None else Emulator()
        self.on = False
        self.on_since: float | None = None
        self.safe_since: float | None = None
        self.bytes_in = 0
        self._cond = threading.Condition()

    def feed(self, data: bytes) -> bytes:
        reply = self.emulator.feed(data)
        now = time.monotonic()
        on = delivering(self.emulator.state())
        with self._cond:
            self.bytes_in += len(data)
            if on and not self.on:
                self.on_since = now
            if self.on and not on:
                self.safe_since = now
            self.on = on
            self._cond.notify_all()
        return reply

    def state(self) -> dict[str, Any]:
        return self.emulator.state()

    @property
    def hazards(self) -> list[Any]:
        return self.emulator.hazards

    def wait_seen_on(self, timeout: float = 30.0) -> bool:
        """Wait until the board has delivered current at least once (it may be off again by now)."""
        end = time.monotonic() + timeout
        with self._cond:
            while self.on_since is None:
                left = end - time.monotonic()
                if left <= 0:
                    return False
                self._cond.wait(left)
        return True

    def wait(self, on: bool, timeout: float = 30.0) -> bool:
        """Wait until the board is (``on=True``) or is not delivering current."""
        end = time.monotonic() + timeout
        with self._cond:
            while self.on != on:
                left = end - time.monotonic()
                if left <= 0:
                    return False
                self._cond.wait(left)
        return True


OWNER = """
import sys, time
from tactdeform_hw.device import StimConfig, open_device
from tactdeform_hw.device.failsafe import StopSession
with StopSession(watchdog_s=None):  # only the signal may stop it: what is measured is the stop itself
    dev = open_device(sys.argv[1])
    dev.configure(StimConfig(current_ua=1000))
    dev.send_pattern([1, 0] * 16)
    print("ready", flush=True)
    while True:
        time.sleep(0.01)
        dev.keepalive()
"""


def spawn_owner(path: str) -> subprocess.Popen[str]:
    env = dict(os.environ, PYTHONPATH=str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    return subprocess.Popen(
        [sys.executable, "-c", OWNER, path],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env=env,
        start_new_session=True,
    )


def one_trial(server: PtyServer, watch: BoardWatch, sig: int, timeout: float = 30.0) -> float:
    """Seconds from ``sig`` to the board safe."""
    proc = spawn_owner(server.path)
    try:
        line = proc.stdout.readline() if proc.stdout else ""
        if line.strip() != "ready":
            raise RuntimeError(f"owner did not start: {line!r} {proc.stderr.read() if proc.stderr else ''}")
        if not watch.wait(True, timeout):
            raise RuntimeError("the board never delivered current")
        time.sleep(0.05)
        t0 = time.monotonic()
        os.kill(proc.pid, sig)
        if not watch.wait(False, timeout):
            raise RuntimeError(
                f"the board still delivers current {timeout} s after {signal.Signals(sig).name}"
            )
        if watch.safe_since is None or watch.safe_since < t0:
            raise RuntimeError("the board went off before the signal: nothing to measure")
        dt = watch.safe_since - t0
        proc.wait(timeout=timeout)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        if proc.stdout:
            proc.stdout.close()
        if proc.stderr:
            proc.stderr.close()
    _wait_port_free(server.path, timeout)
    return dt


def _wait_port_free(path: str, timeout: float) -> None:
    """The guardian holds the port (and its lock) until it is done: wait for it, so the next owner opens."""
    from tactdeform_hw.device.serial_driver import find_holders

    end = time.monotonic() + timeout
    me = os.getpid()
    while time.monotonic() < end:
        if not [pid for pid, _ in find_holders(path) if pid != me]:
            return
        time.sleep(0.01)


def usb_trial(server: Any, sig: int, timeout: float = 30.0, after_s: float = 0.5) -> float:
    """Seconds from ``sig`` to the last pulse with current, on a board served as a USB device."""
    proc = spawn_owner(server.name)
    try:
        line = proc.stdout.readline() if proc.stdout else ""
        if line.strip() != "ready":
            raise RuntimeError(f"owner did not start: {line!r} {proc.stderr.read() if proc.stderr else ''}")
        end = time.monotonic() + timeout
        t0_board = server.board_status(float("inf"))["t0"]
        while True:  # only the last 50 ms of the record: polling must not load the server it measures
            st = server.board_status((time.monotonic() - t0_board) * 1e6 - 50e3)
            if st["last_current_pulse_us"] is not None and st["now_us"] - st["last_current_pulse_us"] < 20e3:
                break
            if time.monotonic() > end:
                raise RuntimeError("the board never delivered current")
            time.sleep(0.01)
        time.sleep(0.05)
        t0 = time.monotonic()
        os.kill(proc.pid, sig)
        kill_us = (t0 - st["t0"]) * 1e6
        proc.wait(timeout=timeout)
        while server.device.claims or server.board_status(float("inf"))["now_us"] < kill_us + after_s * 1e6:
            if time.monotonic() > end + timeout:
                raise RuntimeError(f"the board is still claimed {timeout} s after {signal.Signals(sig).name}")
            time.sleep(0.01)
        last = server.board_status(kill_us - 20e3)["last_current_pulse_us"]
        if last is None:
            raise RuntimeError("the board went off before the signal: nothing to measure")
        if last > kill_us + after_s * 1e6 - 20e3:
            raise RuntimeError(
                f"the board still delivers current {after_s} s after {signal.Signals(sig).name}"
            )
        return max(0.0, (last - kill_us) / 1e6)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        if proc.stdout:
            proc.stdout.close()
        if proc.stderr:
            proc.stderr.close()


def run_usb(
    firmwares: list[str], signals: list[str], trials: int, results: dict[str, Any], quiet: bool
) -> None:
    from tactdeform_hw.emulator.usb_server import UsbServer

    results["board"] = "timed emulator served as a USB device (emulate --usb), owner through pyusb"
    for fw in firmwares:
        server = UsbServer(firmware=fw).start()
        try:
            for name in signals:
                sig = getattr(signal, "SIG" + name)
                samples = [usb_trial(server, sig) for _ in range(trials)]
                key = f"{fw} SIG{name}"
                results[key] = summary(samples)
                if not quiet:
                    s = results[key]
                    print(
                        f"{fw:4s} SIG{name:4s} → last pulse with current: median {s['median_ms']} ms, p95 "
                        f"{s['p95_ms']} ms, max {s['max_ms']} ms over {s['trials']} trials",
                        flush=True,
                    )
        finally:
            server.stop()


def summary(samples: list[float]) -> dict[str, float]:
    ms = sorted(1000 * s for s in samples)
    p95 = ms[min(len(ms) - 1, int(round(0.95 * (len(ms) - 1))))]
    return {
        "trials": len(ms),
        "median_ms": round(statistics.median(ms), 2),
        "p95_ms": round(p95, 2),
        "max_ms": round(ms[-1], 2),
        "min_ms": round(ms[0], 2),
    }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--trials", type=int, default=50, help="trials per signal (default 50)")
    ap.add_argument("--signals", default="TERM,KILL", help="comma-separated signal names (default TERM,KILL)")
    ap.add_argument("--json", action="store_true")
    ap.add_argument(
        "--transport",
        choices=("pty", "usb"),
        default="pty",
        help="how the owner reaches the board (default pty)",
    )
    ap.add_argument(
        "--firmware",
        choices=("v1.2", "v2", "both"),
        default="both",
        help="with --transport usb: the firmware the board runs (default both)",
    )
    a = ap.parse_args(argv)
    if a.trials < 1:
        ap.error(f"--trials={a.trials}: at least 1")
    if a.transport == "usb":
        usb_results: dict[str, Any] = {"python": sys.version.split()[0]}
        firmwares = ["v1.2", "v2"] if a.firmware == "both" else [a.firmware]
        signals = [n.strip().upper() for n in a.signals.split(",")]
        run_usb(firmwares, signals, a.trials, usb_results, a.json)
        if a.json:
            print(json.dumps(usb_results, indent=2))
        return 0
    if a.firmware != "both":
        ap.error("--firmware: the pty board runs the untimed v1.2 model; use it with --transport usb")
    watch = BoardWatch()
    server = PtyServer(watch).start()  # type: ignore[arg-type]  # any object with feed() and state()
    results: dict[str, Any] = {
        "board": "emulator on a pty (untimed firmware model)",
        "python": sys.version.split()[0],
    }
    try:
        for name in a.signals.split(","):
            sig = getattr(signal, "SIG" + name.strip().upper())
            samples = [one_trial(server, watch, sig) for _ in range(a.trials)]
            results["SIG" + name.strip().upper()] = summary(samples)
            if not a.json:
                s = results["SIG" + name.strip().upper()]
                print(
                    f"SIG{name.upper():4s} → all-off parsed: median {s['median_ms']} ms, p95 {s['p95_ms']} "
                    f"ms, max {s['max_ms']} ms over {s['trials']} trials",
                    flush=True,
                )
    finally:
        server.stop()
    if a.json:
        print(json.dumps(results, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
