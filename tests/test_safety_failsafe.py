"""Fail-safe: all channels off on close, exceptions, SIGINT/SIGTERM, interpreter exit and a stalled owner."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest

from tactdeform_hw.device import EtactileKitDevice, StimConfig, open_device
from tactdeform_hw.device.safety.failsafe import FailSafe, Readback, refresh
from tactdeform_hw.emulator import Emulator
from tactdeform_hw.emulator.serving.in_process import EmulatorPort
from tactdeform_hw.emulator.serving.pty_server import PtyServer

from .safety_helpers import RecordingPort

REPO = Path(__file__).resolve().parents[1]
ALL = [1] * 32


def off(emu: Emulator) -> bool:
    s = emu.state()
    return s.pulse_height == 0 and all(v == 0 for v in s.stim_pattern[: s.electrode_num])


def wait_for(cond, timeout: float = 5.0) -> bool:  # type: ignore[no-untyped-def]
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if cond():
            return True
        time.sleep(0.005)
    return cond()


def test_exception_in_the_block_leaves_everything_off() -> None:
    port = EmulatorPort()
    dev = EtactileKitDevice(port)
    with pytest.raises(RuntimeError):
        with FailSafe(dev, signals=False, at_exit=False, thread=False):
            dev.configure(StimConfig(current_ua=800))
            dev.send_pattern(ALL)
            assert not off(port.emulator)
            raise RuntimeError("renderer crashed")
    assert off(port.emulator) and dev.closed


def test_watchdog_thread_stops_a_silent_owner_and_resumes_when_it_returns() -> None:
    dev = open_device("emulator")
    emu = dev.port.emulator  # type: ignore[attr-defined]
    fs = FailSafe(dev, watchdog_s=0.05, signals=False, at_exit=False).start()
    try:
        dev.configure(StimConfig(current_ua=700))
        dev.send_pattern(ALL)
        assert not off(emu)
        assert wait_for(lambda: off(emu)), "the watchdog never switched the stalled session off"
        assert fs.watchdog_trips == 1 and fs.events[0].kind == "watchdog"
        assert fs.events[0].detail["idle_s"] > fs.watchdog_trigger_s  # acted before the 50 ms deadline
        assert dev.suspended and dev.target_ua == 700
        dev.keepalive()  # the owner is back
        assert list(emu.state().stim_pattern[:32]) == ALL and emu.state().pulse_height == 70
        for _ in range(10):  # an owner that keeps producing frames is never stopped
            time.sleep(0.01)
            dev.keepalive()
        assert fs.watchdog_trips == 1
    finally:
        fs.stop()
        dev.close()
    assert off(emu)


def test_signal_handler_starts_with_a_resync_when_it_cut_a_write() -> None:
    port = RecordingPort()
    dev = EtactileKitDevice(port)
    fs = FailSafe(dev, signals=False, at_exit=False, thread=False)
    dev.configure(StimConfig(current_ua=500))
    dev.send_pattern(ALL)
    port.emulator.feed(b"\xfe\x01\x01")  # the signal arrived while a pattern was half on the wire
    dev.wire.writing = True
    n = len(port.writes)
    with pytest.raises(SystemExit) as exc:
        fs._on_signal(signal.SIGTERM, None)
    assert exc.value.code == 128 + signal.SIGTERM
    assert port.writes[n][:1] == b"\x00"  # zeros first: the half command cannot swallow the all-off
    assert off(port.emulator) and dev.closed and fs.events[-1].kind == "signal"


CHILD = textwrap.dedent(
    """
    import sys, time
    import serial
    from tactdeform_hw.device import EtactileKitDevice, StimConfig
    from tactdeform_hw.device.safety.failsafe import FailSafe, register_at_exit
    mode, path = sys.argv[1], sys.argv[2]
    port = serial.Serial(None, 921600, timeout=0.5)
    port.port = path
    dev = EtactileKitDevice(port)
    if mode in ("signal", "stall"):
        FailSafe(dev, watchdog_s=0.08 if mode == "stall" else None).start()
    else:
        register_at_exit(dev)
    dev.configure(StimConfig(current_ua=900))
    dev.send_pattern([1, 0] * 16)
    print("ready", flush=True)
    if mode == "exception":
        raise RuntimeError("the study script crashed")
    if mode == "exit":
        sys.exit(0)
    while True:
        time.sleep(0.01)
        if mode == "signal":
            dev.keepalive()  # an owner that is alive: only the signal may stop it
    """
)


@pytest.fixture
def pty():  # type: ignore[no-untyped-def]
    server = PtyServer(Emulator()).start()
    yield server
    server.stop()


def _child(mode: str, path: str) -> subprocess.Popen[str]:
    env = dict(os.environ, PYTHONPATH=str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    proc = subprocess.Popen(
        [sys.executable, "-c", CHILD, mode, path],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env=env,
    )
    line = proc.stdout.readline()  # type: ignore[union-attr]
    assert line.strip() == "ready", proc.stderr.read() if proc.stderr else line  # type: ignore[union-attr]
    return proc


def _stimulating(emu: Emulator) -> bool:
    return list(emu.state().stim_pattern[:32]) == [1, 0] * 16 and emu.state().pulse_height == 90


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT])
def test_signals_switch_everything_off(pty: PtyServer, sig: int) -> None:
    proc = _child("signal", pty.path)
    try:
        assert wait_for(lambda: _stimulating(pty.emulator))
        time.sleep(0.1)
        assert _stimulating(pty.emulator)  # alive and driving: still on
        proc.send_signal(sig)
        rc = proc.wait(timeout=10)
    finally:
        proc.kill()
    assert rc != 0
    if sig == signal.SIGTERM:
        assert rc == 128 + signal.SIGTERM
    assert wait_for(lambda: off(pty.emulator)), pty.emulator.state()


@pytest.mark.parametrize("mode", ["exception", "exit"])
def test_interpreter_exit_switches_everything_off(pty: PtyServer, mode: str) -> None:
    proc = _child(mode, pty.path)
    rc = proc.wait(timeout=10)
    assert (rc != 0) == (mode == "exception")
    assert wait_for(lambda: off(pty.emulator)), pty.emulator.state()


def test_stalled_owner_in_another_process(pty: PtyServer) -> None:
    proc = _child("stall", pty.path)  # configures, sends one frame, then never again
    try:
        assert wait_for(lambda: off(pty.emulator), timeout=5), pty.emulator.state()
        assert proc.poll() is None  # the process is still there: only the watchdog acted
    finally:
        proc.kill()
        proc.wait(timeout=10)


def test_refresh_rewrites_what_the_firmware_should_hold() -> None:
    port = EmulatorPort()
    dev = EtactileKitDevice(port)
    dev.configure(StimConfig(current_ua=600))
    dev.send_pattern(ALL)
    port.emulator.feed(b"\xfb\x00\x02")  # a corrupted height (5.12 mA) nobody asked for
    port.emulator.feed(b"\xfe" + bytes([1, 0] * 16))
    refresh(dev)
    s = port.emulator.state()
    assert s.pulse_height == 60 and list(s.stim_pattern[:32]) == ALL
    dev.close()


def test_readback_flags_current_on_channels_meant_off_and_a_height_too_high() -> None:
    rb = Readback()
    pattern = bytes([1, 1, 0, 0])
    assert rb.check([50, 60, 0, 0], pattern, 1000) is None
    assert rb.check([50, 60, 0, 0], pattern, 1000) is None
    assert "meant off" in (rb.check([50, 60, 40, 0], pattern, 1000) or "")
    assert "meant on" in (rb.check([0, 60, 0, 0], pattern, 1000) or "")
    assert "more than" in (rb.check([200, 60, 0, 0], pattern, 1000) or "")
    assert rb.check([25, 30, 0, 0], pattern, 500) is None  # proportional: fine


def test_reconnect_and_hardware_reset_resync_before_any_pattern() -> None:
    port = EmulatorPort()
    dev = EtactileKitDevice(port)
    dev.configure(StimConfig(current_ua=400))
    dev.send_pattern(ALL)
    port.emulator.reset()  # a power glitch: the board is back at power-on, electrode count 0
    assert not dev.probe() and dev.needs_resync  # the driver notices: the measure comes back empty
    dev.reconnect()
    s = port.emulator.state()
    assert s.electrode_num == 32 and s.pulse_height == 40 and list(s.stim_pattern[:32]) == [0] * 32
    assert not port.emulator.locked and dev.probe()
    dev.send_pattern(ALL)
    port.emulator.feed(b"\xfc\x00\xfe")  # something locked the parser
    assert not dev.probe()
    dev.resync()  # no byte reaches a locked parser: the proof fails, and the driver takes the reset line
    assert [t[2] for t in dev.transitions if t[2] in ("failed", "resetting", "in_step")][-3:] == [
        "failed",
        "resetting",
        "in_step",
    ]
    assert dev.probe()
    assert dev.hardware_reset() and dev.probe()
    assert list(port.emulator.state().stim_pattern[:32]) == [0] * 32
    dev.close()
