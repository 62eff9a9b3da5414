"""The timed board on the wall clock: desynchronisation hazards, the real-time runner, resets, the live
view, the URL handler and the TCP server.  Nothing here asserts a tight timing: wall-clock checks are
lower bounds the model imposes (a reply cannot come before the parser's ticks) or generous timeouts."""

from __future__ import annotations

import socket
import time

import pytest
import serial

from tactdeform_hw.emulator import Emulator, HazardKind
from tactdeform_hw.emulator.serving.realtime import (
    SERIAL_USB,
    WIFI_TCP,
    LagRecorder,
    LiveView,
    RealtimeEmulator,
    UsbSerialJtagLines,
    settle,
)
from tactdeform_hw.emulator.serving.tcp_server import TcpServer
from tactdeform_hw.emulator.timed.model_v1_2 import TimedEmulator
from tactdeform_hw.protocol import commands as c
from tactdeform_hw.protocol.state import BoardState

CONFIG = (
    c.encode_electrode_num(32)
    + c.encode_pulse_height(100)
    + c.encode_pulse_width(200)
    + c.encode_discharge(45)
)
CONFIG += c.encode_frequency(125)
PATTERN = c.encode_pattern([1, 2, 0, 1] * 8)
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


def _registers(state: BoardState) -> dict:  # type: ignore[type-arg]
    regs = state.as_dict()
    return {k: regs[k] for k in REGISTERS}


# --- every desynchronisation reported ------------------------------------------------------------------


def _swallowed(stream: str) -> list:  # type: ignore[type-arg]
    emu = Emulator()
    emu.feed(bytes.fromhex(stream))
    return [h for h in emu.hazards if h.kind is HazardKind.PAYLOAD_HOLDS_COMMAND_BYTE]


def test_pulse_height_swallowing_an_electrode_number_is_reported_with_the_value_stored() -> None:
    (h,) = _swallowed("fb fc 08")
    assert h.detail["command"] == "PULSE_HEIGHT" and h.detail["swallowed"] == "ELECTRODE_NUM"
    assert h.detail["register"] == "pulse_height" and h.detail["stored"] == 2300 and h.offset == 1


def test_frequency_swallowing_an_hv513_request_is_reported_with_the_period_stored() -> None:
    (h,) = _swallowed("f6 4b f5")
    assert h.detail["command"] == "FREQUENCY" and h.detail["swallowed"] == "HV513_COUNT"
    assert h.detail["register"] == "period_us" and round(h.detail["stored"], 2) == 15.92


@pytest.mark.parametrize(
    ("stream", "command", "swallowed", "register", "stored"),
    [
        ("fd ff", "POLARITY", "MEASURE", "polarity", 1),
        ("fc fe", "ELECTRODE_NUM", "PATTERN", "electrode_num", 254),
        ("fa 00 f9", "PULSE_WIDTH", "SENSE_HEIGHT", "pulse_width", 0xF900),
        ("f9 f8", "SENSE_HEIGHT", "SENSE_WIDTH", "sense_pulse_height", 0xF8 << 2),
        ("f8 f7", "SENSE_WIDTH", "DISCHARGE", "sense_pulse_width", 0xF7),
        ("f7 f6", "DISCHARGE", "FREQUENCY", "discharge_time", 0xF6),
    ],
)
def test_any_command_swallowing_a_command_byte_is_reported(
    stream: str, command: str, swallowed: str, register: str, stored: int
) -> None:
    (h,) = _swallowed(stream)
    assert (h.detail["command"], h.detail["swallowed"], h.detail["register"], h.detail["stored"]) == (
        command,
        swallowed,
        register,
        stored,
    )


def test_in_step_commands_raise_no_desynchronisation_hazard() -> None:
    assert _swallowed((CONFIG + PATTERN).hex()) == []


def test_pattern_swallowing_a_command_names_both_commands() -> None:
    emu = Emulator()
    emu.feed(bytes.fromhex("fc 02 fe 01 f7"))
    (h,) = [h for h in emu.hazards if h.kind is HazardKind.PATTERN_HOLDS_COMMAND_BYTE]
    assert (
        h.detail["command"] == "PATTERN"
        and h.detail["swallowed"] == "DISCHARGE"
        and h.detail["stored"] == 0xF7
    )


def test_a_u16_completed_across_a_long_gap_is_reported_and_a_split_packet_is_not() -> None:
    emu = TimedEmulator(stimulation=False)
    emu.write(b"\xfb\x05", 0)
    emu.advance_to(10_000)
    emu.write(b"\x01", 10_000)
    emu.advance_to(20_000)
    (h,) = [h for h in emu.hazards if h.kind is HazardKind.U16_COMPLETED_LATE]
    assert h.detail["command"] == "PULSE_HEIGHT" and h.detail["stored"] == 0x105 and h.detail["gap_us"] > 8000
    quick = TimedEmulator(stimulation=False)
    quick.write(b"\xfb\x05", 0)
    quick.write(b"\x01", 100)  # the next USB packet of the same frame
    quick.advance_to(20_000)
    assert not [h for h in quick.hazards if h.kind is HazardKind.U16_COMPLETED_LATE]
    assert quick.state().pulse_height == 0x105


# --- the runner -----------------------------------------------------------------------------------------


class FakeClock:
    def __init__(self) -> None:
        self.t = 100.0

    def __call__(self) -> float:
        return self.t


def test_runner_stamps_bytes_on_arrival_and_answers_when_the_model_delivers() -> None:
    clock = FakeClock()
    rt = RealtimeEmulator(clock=clock)
    clock.t += 0.0123
    rt.write(b"\xf5")
    assert rt.timed.commands == [] and rt.read() == b""  # not even on the wire yet
    clock.t += 0.010
    assert rt.catch_up() == b"\x04"
    rep = rt.timed.commands[-1]
    assert rep.name == "HV513_COUNT" and abs(rep.sent_us - 12_300) < 1


def test_runner_reports_every_fall_behind() -> None:
    clock = FakeClock()
    rt = RealtimeEmulator(clock=clock, behind_limit_us=1000)
    rt.write(CONFIG)
    for late in (0.0, 0.0004, 0.003, 0.0, 0.0025):
        due = rt.timed.next_event_us()
        clock.t = rt.t0 + due / 1e6 + late
        rt.catch_up()
    st = rt.lag.stats()
    assert st["wakeups"] == 5 and st["behind"] == 2
    assert [round(b.lag_us) for b in rt.lag.behind] == [3000, 2500]
    assert "fell behind the wall clock by 3.00 ms" in str(rt.lag.behind[0])


def test_lag_recorder_distribution() -> None:
    lag = LagRecorder(limit_us=1000)
    for i in range(1000):
        lag.record(i, float(i))
    st = lag.stats()
    assert st["median_us"] == 500 and st["p99_us"] == 990 and st["max_us"] == 999 and st["behind"] == 0


def test_reset_discards_state_and_says_what() -> None:
    clock = FakeClock()
    rt = RealtimeEmulator(clock=clock)
    rt.write(CONFIG)
    clock.t += 0.02
    rt.write(PATTERN)
    clock.t += 0.02
    rec = rt.reset("SIGUSR1")
    assert rec.discarded["electrode_num"] == 32 and rec.discarded["pulse_height"] == 100
    assert rec.discarded["channels_on"] == [i for i in range(32) if i % 4 in (0, 1, 3)]
    assert "reset (SIGUSR1)" in str(rec) and "pulse_height=100" in str(rec) and "24 channel(s) on" in str(rec)
    clock.t += 0.02
    assert _registers(rt.state()) == _registers(Emulator().state())


def test_history_is_trimmed_while_serving() -> None:
    clock = FakeClock()
    rt = RealtimeEmulator(clock=clock, history_us=1e6)
    rt.write(CONFIG)
    # a frame whose scan fits the 8 ms period (6.5 ms; PATTERN's overruns it by 1.4 µs, and a loop starved
    # by back-to-back scans reads a pattern only a few bytes at a time)
    fitting = c.encode_pattern([1, 0, 2, 0] * 8)
    for _ in range(400):  # 72 patterns a second for 5.5 s of device time
        clock.t += 1 / 72
        rt.catch_up()
        rt.write(fitting)
    clock.t += 0.05
    rt.catch_up()
    t = rt.timed
    assert (
        len(t.commands) < 150
        and len(t.runs) < 400
        and len(t.host.writes) < 150
        and len(t.host.intended) < 150
    )
    assert (
        t.commands[-1].name == "PATTERN"
        and t.commands[-1].in_sync
        and t.commands[-1].first_pulse_us is not None
    )
    assert rt.lag.stats()["wakeups"] > 0 and not t.losses


def test_live_view_prints_at_most_once_a_second_and_only_on_change() -> None:
    clock = FakeClock()
    rt = RealtimeEmulator(clock=clock)
    view = LiveView()
    clock.t += 0.05
    assert view.poll(rt, 0.0)  # the first view
    assert view.poll(rt, 0.5) == []  # too soon
    clock.t += 2
    assert view.poll(rt, 2.0) == []  # nothing changed (the clock and the scan count do not count)
    rt.write(CONFIG)
    clock.t += 0.05
    lines = view.poll(rt, 2.5)
    assert lines and "electrodes=32" in lines[0] and "scans/s=125.0" in lines[1]
    rt.write(PATTERN)
    clock.t += 0.05
    assert view.poll(rt, 3.0) == []  # changed, but within a second of the last view
    lines = view.poll(rt, 3.6)
    assert lines and "on=24" in lines[0]
    rt.write(b"\xfb\xfc\x08")  # desynchronised: a hazard
    clock.t += 0.05
    lines = view.poll(rt, 4.7)
    assert any("payload_holds_command_byte" in x for x in lines)


# --- DTR / RTS ------------------------------------------------------------------------------------------


def _esptool(lines: UsbSerialJtagLines, steps: str) -> list[str | None]:
    """Apply an esptool-style sequence: D1/D0 set DTR, R1/R0 set RTS (each a control-line request)."""
    out = []
    for step in steps.split():
        if step[0] == "D":
            out.append(lines.set(step[1] == "1", lines.rts))
        else:
            out.append(lines.set(lines.dtr, step[1] == "1"))
    return out


def test_esptool_hard_reset_restarts_the_firmware() -> None:
    lines = UsbSerialJtagLines()
    assert [e for e in _esptool(lines, "R1 R0") if e] == ["held", "released"]
    assert lines.running and not lines.download_mode


def test_esptool_usb_jtag_sequence_enters_download_mode_and_a_hard_reset_leaves_it() -> None:
    lines = UsbSerialJtagLines()
    events = _esptool(lines, "R0 D0 D1 R0 R1 D0 R1 D0 R0")
    assert [e for e in events if e] == ["held", "released"] and lines.download_mode and not lines.running
    _esptool(lines, "R1 D0 R0")
    assert lines.running


def test_opening_a_port_does_not_reset_the_board() -> None:
    lines = UsbSerialJtagLines()
    assert lines.set(True, True) is None and lines.running  # pyserial's default: both asserted
    assert lines.set(False, False) is None and lines.running


@pytest.mark.parametrize("timed", ["1", "0"])
def test_dtr_rts_reset_restores_the_power_on_state(timed: str) -> None:
    s = serial.serial_for_url(f"etactile://?timed={timed}", timeout=0.5)
    try:
        s.write(CONFIG)
        if timed == "1":
            settle(s.emulator)
        s.write(PATTERN + b"\xfb")  # and a half-received pulse height
        if timed == "1":
            settle(s.emulator)
        assert s.emulator.state().pulse_height == 100
        s.dtr = False
        s.rts = True  # esptool's hard reset: EN low ...
        time.sleep(0.01)
        s.rts = False  # ... and high again
        assert len(s.resets) == 1 and s.resets[0].discarded["electrode_num"] == 32
        if timed == "1":
            time.sleep(0.01)
        assert _registers(s.emulator.state()) == _registers(Emulator().state())
        s.write(b"\xf5")
        assert s.read(1) == b"\x04"  # the parser is in step after the reset
    finally:
        s.close()


def test_download_mode_answers_nothing_until_the_next_reset() -> None:
    s = serial.serial_for_url("etactile://", timeout=0.1)
    try:
        s.dtr, s.rts = False, False
        # esptool's USB-JTAG reset
        for dtr, rts in ((True, False), (True, True), (False, True), (False, False)):
            s.dtr, s.rts = dtr, rts
        assert s.lines.download_mode
        s.write(b"\xf5")
        assert s.read(1) == b""
        s.rts = True
        s.rts = False
        s.timeout = 0.5
        s.write(b"\xf5")
        assert s.read(1) == b"\x04"
    finally:
        s.close()


# --- the URL handler in real time -----------------------------------------------------------------------


def test_url_reply_waits_for_the_parser_rhythm() -> None:
    """Eight commands with a payload, then 0xF5: the firmware reads one command per 1 ms tick, so the
    reply cannot come before about 8 ms (the untimed emulator answered at once)."""
    s = serial.serial_for_url("etactile://", timeout=2)
    try:
        burst = CONFIG + c.encode_polarity(1) + c.encode_sense_width(0) + c.encode_sense_height(0)
        t0 = time.monotonic()
        s.write(burst + b"\xf5")
        assert s.read(1) == b"\x04"
        assert time.monotonic() - t0 >= 0.007
        rep = [r for r in s.emulator.timed.commands if r.name == "HV513_COUNT"][-1]
        assert rep.effect_us - rep.sent_us >= 8000
    finally:
        s.close()


def test_url_port_declares_how_to_pace_it() -> None:
    from tactdeform_hw.clock import InstantClock, MonotonicClock
    from tactdeform_hw.device.driver.pacing import default_pacer

    timed = serial.serial_for_url("etactile://", do_not_open=True)
    instant = serial.serial_for_url("etactile://?timed=0", do_not_open=True)
    assert not timed.instant and isinstance(timed.pacing_clock, MonotonicClock)
    assert instant.instant and isinstance(instant.pacing_clock, InstantClock)
    assert isinstance(default_pacer(timed).clock, MonotonicClock)
    assert isinstance(default_pacer(instant).clock, InstantClock)
    with pytest.raises(serial.SerialException, match="timed"):
        serial.serial_for_url("etactile://?timed=maybe")


def test_url_one_byte_per_write_gives_the_same_registers_as_whole_commands() -> None:
    stream = CONFIG + PATTERN
    whole = serial.serial_for_url("etactile://", timeout=0.5)
    single = serial.serial_for_url("etactile://", timeout=0.5)
    try:
        whole.write(stream)
        for b in stream:
            single.write(bytes([b]))
        assert settle(whole.emulator) and settle(single.emulator)
        assert _registers(single.emulator.state()) == _registers(whole.emulator.state())
        assert list(single.emulator.state().stim_pattern[:32]) == [1, 2, 0, 1] * 8
    finally:
        whole.close()
        single.close()


# --- TCP ------------------------------------------------------------------------------------------------


def _recv(sock: socket.socket, n: int, timeout: float = 2.0) -> bytes:
    sock.settimeout(timeout)
    out = b""
    try:
        while len(out) < n:
            got = sock.recv(n - len(out))
            if not got:
                break
            out += got
    except TimeoutError:
        pass
    return out


def test_tcp_serves_one_client_at_a_time() -> None:
    with TcpServer(port=0) as server:
        a = socket.create_connection(server.address, timeout=2)
        b = socket.create_connection(server.address, timeout=2)  # waits in the backlog
        try:
            a.sendall(b"\xf5")
            assert _recv(a, 1) == b"\x04"
            b.sendall(b"\xf5")
            assert _recv(b, 1, timeout=0.2) == b""
            a.close()
            assert _recv(b, 1, timeout=3) == b"\x04"
            assert server.clients == 2
        finally:
            a.close()
            b.close()


def test_tcp_replies_go_only_to_the_client_that_is_connected() -> None:
    """A reply the firmware writes after its client has gone is not kept for the next one."""
    with TcpServer(port=0) as server:
        a = socket.create_connection(server.address, timeout=2)
        a.sendall(CONFIG + b"\xf5")  # the reply comes ~6 ms later, after five ticks
        a.close()
        time.sleep(0.1)
        b = socket.create_connection(server.address, timeout=2)
        try:
            assert _recv(b, 1, timeout=0.3) == b""
            b.sendall(b"\xf5")
            assert _recv(b, 1) == b"\x04"
        finally:
            b.close()


def test_tcp_flow_control_holds_the_host_back_instead_of_dropping() -> None:
    """20 000 unknown bytes and a 0xF5: the Wi-Fi build's stream loses nothing (the serial build's queue
    would drop most of them), and the reply comes once the parser has read them all."""
    with TcpServer(port=0, rules=WIFI_TCP) as server:
        sock = socket.create_connection(server.address, timeout=5)
        try:
            sock.sendall(bytes(20_000) + b"\xf5")
            assert _recv(sock, 1, timeout=10) == b"\x04"
            assert not server.board.timed.losses
        finally:
            sock.close()


def test_tcp_with_the_serial_build_rules_drops_a_flood() -> None:
    with TcpServer(port=0, rules=SERIAL_USB) as server:
        sock = socket.create_connection(server.address, timeout=5)
        try:
            sock.sendall(bytes(4000))
            deadline = time.monotonic() + 5
            while not server.board.timed.losses and time.monotonic() < deadline:
                time.sleep(0.01)
            assert server.board.timed.losses
            assert any(h.kind is HazardKind.QUEUE_OVERFLOW for h in server.board.hazards)
        finally:
            sock.close()


def test_tcp_reset_on_open() -> None:
    with TcpServer(port=0, reset_on_open=True) as server:
        for _ in range(2):
            sock = socket.create_connection(server.address, timeout=2)
            try:
                sock.sendall(c.encode_electrode_num(9) + b"\xf5")
                assert _recv(sock, 1) == b"\x04"
            finally:
                sock.close()
            deadline = time.monotonic() + 3
            while server.connected and time.monotonic() < deadline:
                time.sleep(0.01)
        assert len(server.resets) == 2 and server.resets[1].discarded["electrode_num"] == 9


# --- the measuring tool ---------------------------------------------------------------------------------


def test_realtime_lag_tool_reports_lag_cpu_and_pattern_latency() -> None:
    import json
    import subprocess
    import sys

    from .conftest import REPO

    proc = subprocess.run(
        [sys.executable, "tools/realtime_lag.py", "--idle", "0.3", "--stream", "0.6", "--json"],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert proc.returncode == 0, proc.stderr[-2000:]
    out = json.loads(proc.stdout)
    assert out["configured"]
    for phase in ("idle", "stream"):
        ph = out[phase]
        assert ph["wakeups"] > 0 and ph["lag_max_ms"] >= ph["lag_p99_ms"] >= ph["lag_median_ms"] >= 0
        assert ph["cpu_percent"] >= 0
    lat = out["pattern_latency_pty"]
    assert lat["n"] >= 0.8 * lat["writes"]  # nearly every pattern written was felt
    assert lat["min_us"] > 0  # causality: no pulse carries a pattern before the host wrote it
    model = out["pattern_latency_model"]
    assert model["min"] <= model["mean"] <= model["max"]
