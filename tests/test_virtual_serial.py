"""The emulator behind a real pseudo-terminal, the pyserial URL handler and the in-process port."""

from __future__ import annotations

import signal
import subprocess
import sys
import time

import pytest
import serial

from tactdeform_hw.device import EtactileKitDevice, StimConfig
from tactdeform_hw.emulator import Emulator, HazardKind
from tactdeform_hw.emulator.pty_server import PtyServer
from tactdeform_hw.emulator.urlhandler.protocol_etactile import forget_shared, shared_emulator

from .safety_helpers import defects


@pytest.fixture
def pty_server():  # type: ignore[no-untyped-def]
    server = PtyServer(Emulator()).start()
    yield server
    server.stop()


def open_pty(path: str, timeout: float = 0.5) -> serial.Serial:
    return serial.Serial(path, 921600, timeout=timeout)


def test_pty_hv513_reply(pty_server: PtyServer) -> None:
    with open_pty(pty_server.path) as s:
        s.write(b"\xf5")
        assert s.read(1) == b"\x04"


def test_pty_measure_reply_length(pty_server: PtyServer) -> None:
    with open_pty(pty_server.path) as s:
        s.write(b"\xfc\x1a")
        s.write(b"\xff")
        assert s.read(2 * 26) == bytes(52)
        s.timeout = 0.2
        assert s.read(1) == b""


def test_pty_no_reply_to_other_commands(pty_server: PtyServer) -> None:
    with open_pty(pty_server.path, timeout=0.3) as s:
        s.write(b"\xfc\x04\xfe\x01\x01\x00\x02\xfb\x10\x00\xfa\xc8\x00\xf9\x01\xf8\x02\xf7\x2d\xf6\x7d\x00\xfd\x01\x00")
        assert s.read(1) == b""
    time.sleep(0.05)
    st = pty_server.emulator.state()
    assert st["stim_pattern"][:4] == [1, 1, 0, 2] and st["period_us"] == 8000.0


def test_pty_locked_parser_reproduced_and_reported(pty_server: PtyServer) -> None:
    with open_pty(pty_server.path, timeout=0.3) as s:
        s.write(b"\xfe")
        s.write(b"\xf5")  # would normally answer 4
        assert s.read(1) == b""
    emu = pty_server.emulator
    assert emu.locked and emu.state()["rx_pending"] == 1
    assert [h.kind for h in emu.hazards][:2] == [HazardKind.PARSER_LOCKED, HazardKind.UNREAD_WHILE_LOCKED]


def test_driver_over_pty(pty_server: PtyServer) -> None:
    with _device(pty_server.path) as dev:
        dev.configure(StimConfig(current_ua=800))
        dev.send_pattern([1, 2, 0, 0] * 8)
        assert dev.hv513_count() == 4
        assert len(dev.measure()) == 32
        deadline = time.monotonic() + 2
        while pty_server.emulator.state()["stim_pattern"][:32] != [1, 2, 0, 0] * 8 and time.monotonic() < deadline:
            time.sleep(0.005)
    deadline = time.monotonic() + 2
    while pty_server.emulator.state()["stim_pattern"][:32] != [0] * 32 and time.monotonic() < deadline:
        time.sleep(0.005)
    assert pty_server.emulator.state()["stim_pattern"][:32] == [0] * 32  # all-off on close
    assert defects(pty_server.emulator.hazards) == []  # the proofs' own records only


def _device(path: str) -> EtactileKitDevice:
    port = serial.Serial(None, 921600, timeout=0.5)
    port.port = path
    return EtactileKitDevice(port)


def test_url_handler_is_a_serialbase() -> None:
    s = serial.serial_for_url("etactile://?board=compact&switching_boards=1", timeout=0.1)
    assert isinstance(s, serial.SerialBase)
    s.write(b"\xf5")
    assert s.in_waiting == 1 and s.read(10) == b"\x04"
    s.close()
    with pytest.raises(serial.PortNotOpenError):
        s.write(b"\xff")


def test_named_url_shares_one_emulator() -> None:
    forget_shared()
    a = serial.serial_for_url("etactile://bench1")
    b = serial.serial_for_url("etactile://bench1")
    a.write(b"\xfc\x07")
    assert shared_emulator("bench1") is a.emulator is b.emulator
    assert b.emulator.state()["electrode_num"] == 7
    forget_shared()


def test_emulate_cli_prints_path_first_and_serves() -> None:
    proc = subprocess.Popen(
        [sys.executable, "-m", "tactdeform_hw.cli", "emulate", "--pty"],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        path = proc.stdout.readline().strip()  # type: ignore[union-attr]
        assert path.startswith("/dev/")
        with open_pty(path, timeout=2) as s:
            s.write(b"\xf5")
            assert s.read(1) == b"\x04"
    finally:
        proc.send_signal(signal.SIGINT)
        out, err = proc.communicate(timeout=10)
    assert proc.returncode == 0, err
    assert "stopped:" in err


def test_emulate_cli_records_a_trace_while_serving(tmp_path) -> None:  # type: ignore[no-untyped-def]
    trace = tmp_path / "session.csv"
    proc = subprocess.Popen(
        [sys.executable, "-m", "tactdeform_hw.cli", "emulate", "--pty", "--trace", str(trace)],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        path = proc.stdout.readline().strip()  # type: ignore[union-attr]
        with open_pty(path, timeout=2) as s:
            s.write(b"\xfc\x04\xfb\x64\x00\xfa\xc8\x00\xf7\x2d\xf6\x7d\x00\xfe\x01\x00\x00\x00")
            time.sleep(0.3)
            s.write(b"\xf5")
            assert s.read(1) == b"\x04"
    finally:
        proc.send_signal(signal.SIGINT)
        out, err = proc.communicate(timeout=20)
    assert proc.returncode == 0, err
    text = trace.read_text()
    assert len(text.splitlines()) > 10
    assert "dac" in text.lower()
