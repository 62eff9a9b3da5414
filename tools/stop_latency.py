"""How long from the owner's death to all-off on the wire.

    python tools/stop_latency.py --trials 50 [--json]
    python tools/stop_latency.py --transport tcp --firmware v1.2,v2 --trials 50 [--json]
    python tools/stop_latency.py --transport usb --signals KILL --trials 50 [--json]

``--transport`` selects how the board is served and how the owner names it:

* ``pty`` (the default): the emulated board (the untimed firmware model, v1.2) on a real pseudo-terminal in
  this process; the owner opens it by path (exclusive lock, guardian process, fail-safe).  The figure is
  the time from the signal to the moment the firmware model had parsed the bytes that make it safe: no
  channel receives current any more (pulse height 0 or no active channel, and sense height 0).
* ``tcp``: the real-time Wi-Fi board (the timed model of ``--firmware``, TCP flow control, one client at
  a time) on a loopback TCP port in this process; the owner opens ``socket://127.0.0.1:PORT`` (guardian
  process sharing the connection, fail-safe).  The figure is judged on the pulses the board delivered:
  from the signal to the end of the last pulse that carried current (0 when none started after the
  signal), so it moves in steps of the scans (8 ms at 125 Hz).
* ``usb``: the timed board of ``--firmware`` served as its USB device (the server of ``emulate --usb``, in
  a thread of this process); the owner opens it through pyusb (``usb-emulator://PATH``, a claim of its
  own, a USB guardian).  Judged on the delivered pulses as over TCP (the guardian can act only once the
  dead owner's claim is released, then waits out the owner's queue).

The owner configures the board, drives a pattern at 1 mA and keeps it fed, its watchdog off so that only
the stop itself is timed.  Each trial kills it — with SIGTERM (its stop handler switches off) or with
SIGKILL (its guardian does).  Prints the median, 95th percentile and maximum of each; with one firmware
the JSON has one object per signal (``SIGTERM``, ``SIGKILL``), with several one such object per firmware.
:class:`BoardWatch` is also what the stop tests judge with.
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
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))

from tactdeform_hw.emulator import Emulator  # noqa: E402
from tactdeform_hw.emulator.serving.pty_server import PtyServer  # noqa: E402
from tactdeform_hw.emulator.serving.realtime import WIFI_TCP, RealtimeEmulator  # noqa: E402
from tactdeform_hw.emulator.serving.tcp_server import TcpServer  # noqa: E402
from tactdeform_hw.protocol.constants import PATTERN_BIPHASIC, PATTERN_MONOPHASIC  # noqa: E402
from tactdeform_hw.protocol.state import BoardState  # noqa: E402


def delivering(state: BoardState) -> bool:
    """Whether the firmware state delivers current on any channel: a stimulation pulse (pattern value 1
    or 2 at a height above 0) or a sense pulse (any other value, at a sense height above 0)."""
    n = state.electrode_num
    if n == 0:
        return False
    levels = state.stim_pattern[:n]
    if state.sense_pulse_height > 0:
        return True
    return (state.pulse_height or 0) > 0 and any(v in (PATTERN_MONOPHASIC, PATTERN_BIPHASIC) for v in levels)


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

    def state(self) -> BoardState:
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
from tactdeform_hw.device.safety.failsafe import StopSession
with StopSession(watchdog_s=None):  # only the signal may stop it: what is measured is the stop itself
    dev = open_device(sys.argv[1], **({"firmware": sys.argv[2]} if len(sys.argv) > 2 else {}))
    dev.configure(StimConfig(current_ua=1000))
    dev.send_pattern([1, 0] * 16)
    print("ready", flush=True)
    while True:
        time.sleep(0.01)
        dev.keepalive()
"""


def spawn_owner(path: str, firmware: str | None = None) -> subprocess.Popen[str]:
    env = dict(os.environ, PYTHONPATH=str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    return subprocess.Popen(
        [sys.executable, "-c", OWNER, path, *([firmware] if firmware else [])],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env=env,
        start_new_session=True,
    )


@contextmanager
def running_owner(path: str, firmware: str | None = None) -> Iterator[subprocess.Popen[str]]:
    """An owner of ``path`` that has opened the board and drives it (it printed ``ready``); on leaving,
    whatever the trial did, it is killed if still alive and its pipes are closed, so no trial leaves a
    process holding the board for the next one."""
    proc = spawn_owner(path, firmware)
    try:
        line = proc.stdout.readline() if proc.stdout else ""
        if line.strip() != "ready":
            raise RuntimeError(f"owner did not start: {line!r} {proc.stderr.read() if proc.stderr else ''}")
        yield proc
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        if proc.stdout:
            proc.stdout.close()
        if proc.stderr:
            proc.stderr.close()


def one_trial(server: PtyServer, watch: BoardWatch, sig: int, timeout: float = 30.0) -> float:
    """Seconds from ``sig`` to the board safe."""
    with running_owner(server.path) as proc:
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
    _wait_port_free(server.path, timeout)
    return dt


def _until(cond: Any, timeout: float, what: str) -> None:
    end = time.monotonic() + timeout
    while not cond():
        if time.monotonic() > end:
            raise RuntimeError(what)
        time.sleep(0.002)


def current_pulse_ends_us(board: RealtimeEmulator, since_us: float) -> list[float]:
    """End times (device µs) of the pulses the real-time board delivered with current from ``since_us``."""
    with board.lock:
        board.state()  # the model brought up to the wall clock
        table = board.timed.reports.pulse_table(since_us)
    on = table["current_ua"] > 0
    return [float(t) for t in (table["start_us"] + table["width_us"])[on]]


def tcp_trial(server: TcpServer, sig: int, timeout: float = 30.0) -> float:
    """Seconds from ``sig`` to the end of the last pulse with current, on the real-time Wi-Fi board."""
    board = server.board
    start_us = board.device_us()
    with running_owner(server.url, board.firmware.name) as proc:
        _until(lambda: bool(current_pulse_ends_us(board, start_us)), timeout, "the board never delivered")
        time.sleep(0.05)
        t0 = time.monotonic()
        os.kill(proc.pid, sig)
        kill_us = board.device_us(t0)
        proc.wait(timeout=timeout)
        # owner and guardian gone: the connection closes, the board serves the next client
        _until(
            lambda: not server.connected,
            timeout,
            f"the connection stays open after {signal.Signals(sig).name}",
        )
        time.sleep(0.1)  # scans go on: a board still on would deliver here
        ends = current_pulse_ends_us(board, kill_us - 20_000)
    last = max(ends, default=kill_us)
    if current_pulse_ends_us(board, board.device_us() - 50_000):
        raise RuntimeError(f"the board still delivers current after {signal.Signals(sig).name}")
    return float(max(0.0, last - kill_us) / 1e6)


class PtyBench:
    """The untimed v1.2 firmware model on a pseudo-terminal, judged on the parsed state."""

    firmwares = ("v1.2",)

    def __init__(self, firmware: str) -> None:
        self.watch = BoardWatch()
        self.server = PtyServer(self.watch)  # any object with feed() and state()
        self.server.start()
        self.board = "emulator on a pty (untimed firmware model)"

    def trial(self, sig: int) -> float:
        return one_trial(self.server, self.watch, sig)

    def stop(self) -> None:
        self.server.stop()


class TcpBench:
    """The real-time Wi-Fi board on loopback TCP, judged on the delivered pulses."""

    firmwares = ("v1.2", "v2")

    def __init__(self, firmware: str) -> None:
        self.server = TcpServer(RealtimeEmulator(rules=WIFI_TCP, firmware=firmware), port=0, rules=WIFI_TCP)
        self.server.start()
        self.board = f"real-time Wi-Fi board, firmware {firmware}, on loopback TCP (socket://)"

    def trial(self, sig: int) -> float:
        return tcp_trial(self.server, sig)

    def stop(self) -> None:
        self.server.stop()


class UsbBench:
    """The timed board served as its USB device (``emulate --usb``), judged on the delivered pulses."""

    firmwares = ("v1.2", "v2")

    def __init__(self, firmware: str) -> None:
        from tactdeform_hw.emulator.serving.usb_server import UsbServer

        self.server = UsbServer(firmware=firmware).start()
        self.board = (
            f"timed board, firmware {firmware}, served as a USB device (emulate --usb), owner through pyusb"
        )

    def trial(self, sig: int) -> float:
        return usb_trial(self.server, sig)

    def stop(self) -> None:
        self.server.stop()


#: How the board is served and named, by transport name.
TRANSPORTS: dict[str, Any] = {"pty": PtyBench, "tcp": TcpBench, "usb": UsbBench}


def _wait_port_free(path: str, timeout: float) -> None:
    """The guardian holds the port (and its lock) until it is done: wait for it, so the next owner opens."""
    from tactdeform_hw.device.driver.serial_driver import find_holders

    end = time.monotonic() + timeout
    me = os.getpid()
    while time.monotonic() < end:
        if not [pid for pid, _ in find_holders(path) if pid != me]:
            return
        time.sleep(0.01)


def usb_trial(server: Any, sig: int, timeout: float = 30.0, after_s: float = 0.5) -> float:
    """Seconds from ``sig`` to the last pulse with current, on a board served as a USB device."""
    with running_owner(server.name) as proc:
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
    ap.add_argument(
        "--transport",
        choices=sorted(TRANSPORTS),
        default="pty",
        help="how the board is served and named (default pty: a pseudo-terminal opened by path; tcp: the "
        "Wi-Fi board on a loopback port, opened as socket://; usb: the board served as a USB device, "
        "opened through pyusb)",
    )
    ap.add_argument(
        "--firmware",
        default=None,
        help="comma-separated firmwares to measure (default: every one the transport's board runs: pty "
        "v1.2; tcp and usb v1.2,v2)",
    )
    ap.add_argument("--json", action="store_true")
    a = ap.parse_args(argv)
    if a.trials < 1:
        ap.error(f"--trials={a.trials}: at least 1")
    bench_type = TRANSPORTS[a.transport]
    firmwares = [f.strip() for f in a.firmware.split(",")] if a.firmware else list(bench_type.firmwares)
    for fw in firmwares:
        if fw not in bench_type.firmwares:
            ap.error(f"--firmware={fw}: the {a.transport} board runs {', '.join(bench_type.firmwares)}")
    signals = []
    for name in a.signals.split(","):
        sig = getattr(signal, "SIG" + name.strip().upper(), None)
        if not isinstance(sig, signal.Signals):
            ap.error(f"--signals={a.signals}: {name.strip()!r} is not a signal name (e.g. TERM, KILL)")
        signals.append(sig)
    results: dict[str, Any] = {"transport": a.transport, "python": sys.version.split()[0]}
    for fw in firmwares:
        bench = bench_type(fw)
        out: dict[str, Any] = {"board": bench.board}
        try:
            for sig in signals:
                s = out[sig.name] = summary([bench.trial(sig) for _ in range(a.trials)])
                if not a.json:
                    print(
                        f"{a.transport} {fw} {sig.name:7s} → all-off: median {s['median_ms']} ms, p95 "
                        f"{s['p95_ms']} ms, max {s['max_ms']} ms over {s['trials']} trials",
                        flush=True,
                    )
        finally:
            bench.stop()
        if len(firmwares) == 1:
            results.update(out)
        else:
            results[fw] = out
    if a.json:
        print(json.dumps(results, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
