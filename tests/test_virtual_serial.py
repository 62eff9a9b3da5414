"""The emulator behind a real pseudo-terminal, the pyserial URL handler and the in-process port: the
untimed board that answers at once, and the timed board on the wall clock that ``emulate`` serves by
default.  Wall-clock checks are generous timeouts or lower bounds the model imposes."""

from __future__ import annotations

import signal
import subprocess
import sys
import time

import pytest
import serial

from tactdeform_hw.device import EtactileKitDevice, StimConfig
from tactdeform_hw.emulator import Emulator, HazardKind
from tactdeform_hw.emulator.firmware.scan import ScanConfig
from tactdeform_hw.emulator.serving.pty_server import PtyServer
from tactdeform_hw.emulator.serving.realtime import RealtimeEmulator, settle
from tactdeform_hw.emulator.serving.urlhandler.protocol_etactile import forget_shared, shared_emulator
from tactdeform_hw.emulator.timed.model_v1_2 import TimedEmulator
from tactdeform_hw.protocol import commands as c
from tactdeform_hw.protocol import firmware_math as fm

from .safety_helpers import defects

CONFIG = (
    c.encode_electrode_num(32)
    + c.encode_pulse_height(100)
    + c.encode_pulse_width(200)
    + c.encode_discharge(45)
)
CONFIG += c.encode_frequency(125)
LEVELS = [1, 2, 0, 1] * 8
REGISTERS = (
    "electrode_num",
    "polarity",
    "pulse_height",
    "pulse_width",
    "sense_pulse_height",
    "sense_pulse_width",
    "discharge_time",
    "period_us",
    "timer_alarm_ticks",
    "stim_pattern",
    "rx_pending",
)


@pytest.fixture
def pty_server():  # type: ignore[no-untyped-def]
    server = PtyServer(Emulator()).start()  # untimed: every write answered at once
    yield server
    server.stop()


@pytest.fixture
def timed_pty():  # type: ignore[no-untyped-def]
    server = PtyServer().start()  # the default: the timed board on the wall clock
    yield server
    server.stop()


def _received(server: PtyServer, n: int, timeout: float = 5.0) -> None:
    deadline = time.monotonic() + timeout
    while server.bytes_in < n and time.monotonic() < deadline:
        time.sleep(0.001)
    assert settle(server.board, timeout_s=timeout)


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
        s.write(
            b"\xfc\x04\xfe\x01\x01\x00\x02\xfb\x10\x00\xfa\xc8\x00\xf9\x01\xf8\x02"
            b"\xf7\x2d\xf6\x7d\x00\xfd\x01\x00"
        )
        assert s.read(1) == b""
    time.sleep(0.05)
    st = pty_server.emulator.state()
    assert list(st.stim_pattern[:4]) == [1, 1, 0, 2] and st.period_us == 8000.0


def test_pty_locked_parser_reproduced_and_reported(pty_server: PtyServer) -> None:
    with open_pty(pty_server.path, timeout=0.3) as s:
        s.write(b"\xfe")
        s.write(b"\xf5")  # would normally answer 4
        assert s.read(1) == b""
    emu = pty_server.emulator
    assert emu.locked and emu.state().rx_pending == 1
    assert [h.kind for h in emu.hazards][:2] == [HazardKind.PARSER_LOCKED, HazardKind.UNREAD_WHILE_LOCKED]


def test_driver_over_pty(pty_server: PtyServer) -> None:
    with _device(pty_server.path) as dev:
        dev.configure(StimConfig(current_ua=800))
        dev.send_pattern([1, 2, 0, 0] * 8)
        assert dev.hv513_count() == 4
        assert len(dev.measure()) == 32
        deadline = time.monotonic() + 2
        while (
            list(pty_server.emulator.state().stim_pattern[:32]) != [1, 2, 0, 0] * 8
            and time.monotonic() < deadline
        ):
            time.sleep(0.005)
    deadline = time.monotonic() + 2
    while list(pty_server.emulator.state().stim_pattern[:32]) != [0] * 32 and time.monotonic() < deadline:
        time.sleep(0.005)
    assert list(pty_server.emulator.state().stim_pattern[:32]) == [0] * 32  # all-off on close
    assert defects(pty_server.emulator.hazards) == []  # the proofs' own records only


def _device(path: str) -> EtactileKitDevice:
    port = serial.Serial(None, 921600, timeout=0.5)
    port.port = path
    return EtactileKitDevice(port)


def test_url_handler_is_a_serialbase() -> None:
    s = serial.serial_for_url("etactile://?board=compact&switching_boards=1&timed=0", timeout=0.1)
    assert isinstance(s, serial.SerialBase)
    s.write(b"\xf5")
    assert s.in_waiting == 1 and s.read(10) == b"\x04"  # untimed: the reply exists when write returns
    s.close()
    with pytest.raises(serial.PortNotOpenError):
        s.write(b"\xff")


def test_timed_url_handler_answers_when_the_model_delivers() -> None:
    s = serial.serial_for_url("etactile://?board=compact&switching_boards=1", timeout=2)
    assert isinstance(s.emulator, RealtimeEmulator)
    s.write(b"\xf5")
    assert s.in_waiting == 0  # still on its way over the USB link
    assert s.read(1) == b"\x04"  # read waits (up to the timeout) for what the model has still to deliver
    s.close()


def test_named_url_shares_one_emulator() -> None:
    forget_shared()
    a = serial.serial_for_url("etactile://bench1")
    b = serial.serial_for_url("etactile://bench1")
    a.write(b"\xfc\x07")
    assert shared_emulator("bench1") is a.emulator is b.emulator
    assert settle(b.emulator)
    assert b.emulator.state().electrode_num == 7
    with pytest.raises(serial.SerialException, match="already open timed"):
        serial.serial_for_url("etactile://bench1?timed=0")
    forget_shared()


# --- the timed board on the pty ----------------------------------------------------------------------------


def test_pty_reply_after_a_configuration_burst_waits_for_the_parser(timed_pty: PtyServer) -> None:
    """Eight commands with a payload and 0xF5 in one write: the parser reads one command per tick, so
    the reply cannot come before about 8 ms (the untimed server answered in half a millisecond)."""
    burst = CONFIG + c.encode_polarity(1) + c.encode_sense_width(0) + c.encode_sense_height(0)
    with open_pty(timed_pty.path, timeout=2) as s:
        t0 = time.monotonic()
        s.write(burst + b"\xf5")
        assert s.read(1) == b"\x04"
        assert time.monotonic() - t0 >= 0.007
    assert timed_pty.state().pulse_height == 100


def test_pty_voltages_after_a_pattern_are_the_skin_models(timed_pty: PtyServer) -> None:
    with open_pty(timed_pty.path, timeout=2) as s:
        s.write(CONFIG)
        s.write(c.encode_pattern(LEVELS))
        _received(timed_pty, len(CONFIG) + 33)
        time.sleep(0.03)  # a few scans with the new pattern
        s.reset_input_buffer()
        s.write(b"\xff")
        reply = s.read(64)
    codes = [reply[i] | reply[i + 1] << 8 for i in range(0, 64, 2)]
    # the same registers on the timed model offline: what the skin model gives for these pulses
    cfg = ScanConfig(32, 1, 100, 200, 0, 0, 45, fm.alarm_ticks(fm.period_us_from_rate(125)), 4, bytes(LEVELS))
    offline = TimedEmulator()
    offline.configure(cfg)
    offline.advance_to(50_000)
    assert codes == offline.registers.voltage[:32]
    assert all(codes[ch] > 0 for ch in range(32) if LEVELS[ch] in (1, 2))
    assert len(set(codes)) > 4  # each electrode's contact differs


def test_pty_one_byte_per_write_gives_the_same_registers_as_whole_commands() -> None:
    """An independent client writing one byte per call (as the upstream libraries do) ends with the same
    register state as one writing whole commands."""
    stream = CONFIG + c.encode_pattern(LEVELS) + c.encode_polarity(0)
    with PtyServer() as whole, PtyServer() as single:
        with open_pty(whole.path) as a, open_pty(single.path) as b:
            a.write(stream)
            for byte in stream:
                b.write(bytes([byte]))
            _received(whole, len(stream))
            _received(single, len(stream))
        sa, sb = whole.state(), single.state()
    assert {k: sb.as_dict()[k] for k in REGISTERS} == {k: sa.as_dict()[k] for k in REGISTERS}
    assert list(sb.stim_pattern[:32]) == LEVELS and sb.polarity == 0


def _emulate(*args: str) -> subprocess.Popen[str]:
    return subprocess.Popen(
        [sys.executable, "-m", "tactdeform_hw.cli", "emulate", *args],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )


def _stop(proc: subprocess.Popen[str]) -> str:
    if proc.poll() is None:
        proc.send_signal(signal.SIGINT)
    try:
        _, err = proc.communicate(timeout=20)
    except subprocess.TimeoutExpired:
        proc.kill()
        _, err = proc.communicate()
    assert proc.returncode == 0, err
    return err


def test_emulate_cli_overflowing_client_sees_the_loss_reported_and_sigusr1_resets() -> None:
    """A pyserial client writes 600 bytes at once into the pty: the 256-byte queue drops the rest of the
    USB packets that do not fit, and the live view says so; SIGUSR1 then power-cycles the board and the
    reset is printed with the state it discarded."""
    proc = _emulate("--pty")
    try:
        path = proc.stdout.readline().strip()  # type: ignore[union-attr]
        with open_pty(path, timeout=2) as s:
            s.write(c.encode_electrode_num(32))
            time.sleep(0.05)
            s.write(c.encode_pattern(LEVELS) * 18)  # 594 bytes in one write
            time.sleep(1.5)
            proc.send_signal(signal.SIGUSR1)
            time.sleep(0.5)
            s.write(b"\xf5")
            assert s.read(1) == b"\x04"
            time.sleep(1.2)
    finally:
        err = _stop(proc)
    assert "queue_overflow" in err and "bytes_lost" in err
    lost = [line for line in err.splitlines() if "lost=" in line]
    assert lost and max(int(line.split("lost=")[1].split("B")[0]) for line in lost) > 0
    reset = [line for line in err.splitlines() if line.startswith("reset (SIGUSR1)")]
    assert reset and "electrode_num=32" in reset[0]


def test_emulate_cli_resets_on_open_and_refuses_a_trace_of_the_untimed_board(tmp_path) -> None:  # type: ignore[no-untyped-def]
    proc = _emulate("--pty", "--reset-on-open", "--quiet")
    try:
        path = proc.stdout.readline().strip()  # type: ignore[union-attr]
        for _ in range(2):
            with open_pty(path, timeout=2) as s:
                s.write(c.encode_electrode_num(5) + b"\xf5")
                assert s.read(1) == b"\x04"
            time.sleep(0.1)
    finally:
        err = _stop(proc)
    resets = [line for line in err.splitlines() if line.startswith("reset (a client opened the port")]
    assert len(resets) == 2 and "electrode_num=5" in resets[1]
    bad = subprocess.run(
        [
            sys.executable,
            "-m",
            "tactdeform_hw.cli",
            "emulate",
            "--pty",
            "--untimed",
            "--trace",
            str(tmp_path / "t.csv"),
        ],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert bad.returncode == 1 and "--trace" in bad.stderr and "Traceback" not in bad.stderr


def test_emulate_cli_serves_tcp() -> None:
    import socket

    proc = _emulate("--tcp", "0", "--quiet")
    try:
        host, port = proc.stdout.readline().strip().rsplit(":", 1)  # type: ignore[union-attr]
        with socket.create_connection((host, int(port)), timeout=5) as sock:
            sock.sendall(b"\xf5")
            sock.settimeout(5)
            assert sock.recv(1) == b"\x04"
    finally:
        err = _stop(proc)
    assert "wifi build rules" in err


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
        try:
            out, err = proc.communicate(timeout=10)
        finally:
            if proc.poll() is None:  # never leave an emulator behind
                proc.kill()
                proc.communicate()
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
            proc.send_signal(signal.SIGUSR1)  # a reset of the served board ...
            time.sleep(0.3)
    finally:
        proc.send_signal(signal.SIGINT)
        try:
            out, err = proc.communicate(timeout=20)
        finally:
            if proc.poll() is None:  # never leave an emulator behind
                proc.kill()
                proc.communicate()
    assert proc.returncode == 0, err
    text = trace.read_text()
    assert len(text.splitlines()) > 10
    assert "dac" in text.lower()
    assert "SIGUSR1" in text  # ... is in the trace: the trace records the model that answers the client
