"""The v2 Wi-Fi board: the timed v2 model on the wall clock (pty, ``etactile://``, TCP), one client at a time,
the cut command a new client inherits within 2 s (and the timeout that discards it otherwise), UDP
discovery, the driver's ``socket://`` and ``etactilekit://ID`` routes, and an upstream-style client that
writes in 8-byte chunks 3 ms apart.  Everything binds 127.0.0.1 and picks free ports; wall-clock checks are
generous timeouts, never tight bounds."""

from __future__ import annotations

import json
import random
import re
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import pytest
import serial
import serial.urlhandler.protocol_socket

from tactdeform_hw.clock import MonotonicClock
from tactdeform_hw.device.driver.firmware_probe import FirmwareMismatchError
from tactdeform_hw.device.driver.serial_driver import open_device
from tactdeform_hw.emulator import Emulator, HazardKind
from tactdeform_hw.emulator.firmware.firmware_scan import DEFAULT_CONVENTIONS, FirmwareScanConfig
from tactdeform_hw.emulator.firmware.registers import V2_SCAN_REGISTERS
from tactdeform_hw.emulator.serving.realtime import SERIAL_USB, WIFI_TCP, RealtimeEmulator, TcpLink, settle
from tactdeform_hw.emulator.serving.tcp_server import TcpServer
from tactdeform_hw.emulator.serving.udp_discovery import DiscoveryResponder
from tactdeform_hw.emulator.timed.model_v2 import TimedEmulatorV2, _scan_shape, _shape
from tactdeform_hw.protocol.commands import V2_COMMANDS as v2

from .conftest import REPO
from .safety_helpers import wait_until

VECTORS = [json.loads(line) for line in (Path(__file__).parent / "data" / "protocol_vectors_v2.jsonl").open()]
N = 32
SETUP = (
    v2.encode_electrode_num(N)
    + v2.encode_stim_mode(0)
    + v2.encode_pulse_width(200)
    + v2.encode_discharge(45)
    + v2.encode_frequency(125)
)


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


def _v2_tcp(**kw: Any) -> TcpServer:
    return TcpServer(RealtimeEmulator(rules=WIFI_TCP, firmware="v2"), port=0, rules=WIFI_TCP, **kw)


# --- the timed v2 model on the wall clock ------------------------------------------------------------------


def test_realtime_v2_answers_on_the_firmwares_rhythm_and_scans() -> None:
    board = RealtimeEmulator(firmware="v2")
    board.write(SETUP + v2.encode_pattern([100 + i for i in range(N)]) + b"\xf4")
    assert board.read() == b""  # nothing is parsed before the next tick and the USB link
    assert wait_until(lambda: board.in_waiting == 1, 2.0)
    assert board.read() == bytes([N])
    assert wait_until(lambda: board.status().scans >= 2, 2.0)  # 125 Hz scans run on the wall clock
    state = board.state()
    assert list(state.stim_pattern[:N]) == [100 + i for i in range(N)] and state.stim_mode == 0
    status = board.status()
    assert status.scans >= 2 and status.registers["on"] == tuple(range(N))
    assert "mode=0" in status.lines()[0] and f"on={N}[0-{N - 1}]" in status.lines()[0]
    rec = board.reset("test")
    assert rec.discarded["electrode_num"] == N and rec.discarded["stim_mode"] == 0
    assert rec.discarded["channels_on"] == list(range(N))
    assert board.state().electrode_num == Emulator(firmware="v2").state().electrode_num


def test_realtime_v2_reports_a_mode_2_board_as_all_channels_on() -> None:
    board = RealtimeEmulator(firmware="v2")
    board.write(v2.encode_electrode_num(4) + v2.encode_sense_height(20) + v2.encode_stim_mode(2))
    assert settle(board)
    assert board.status().registers["on"] == (0, 1, 2, 3)  # a zero pattern does not stop the sense current
    assert any(h.kind is HazardKind.MODE_SENSE_ALL for h in board.hazards)


def test_v2_model_sleeps_through_idle_polls_and_never_reports_an_event_in_the_past() -> None:
    """What a wall-clock runner waits for: bytes that landed are due at the parser's next call, and an
    idle board's next event is its next scan, not its next 1 ms poll."""
    emu = TimedEmulatorV2(link=TcpLink(), tx_link=TcpLink())
    emu.write(SETUP, 0.0)
    emu.advance_to(50_000.0)
    assert emu.next_event_us() > 50_000.0
    assert emu.next_event_us(scans=False) == float("inf")  # idle: no poll changes anything
    emu.write(v2.encode_pattern([5] * N), 50_000.5)  # lands at once, read by the parser's next call
    emu.advance_to(50_700.0)
    due = emu.next_event_us(scans=False)
    assert due > 50_700.0 and emu.state().stim_pattern[0] == 0
    emu.advance_to(due)
    assert list(emu.state().stim_pattern[:N]) == [5] * N
    emu.write(b"\xfe", emu.now_us)  # a cut pattern: the next event without scans is its timeout
    emu.advance_to(emu.now_us + 5000)
    assert emu.parser.processing
    assert emu.next_event_us(scans=False) >= emu.parser.command_start_us + 2_000_000


@pytest.mark.parametrize("mode", [0, 1, 2])
def test_scan_shape_fills_heights_into_one_walk_exactly(mode: int) -> None:
    rng = random.Random(mode)
    for n in (1, 7, 32):
        for _ in range(3):
            cfg = FirmwareScanConfig(
                electrode_num=n,
                stim_pattern=tuple(rng.choice([0, 1, 900, 4095]) for _ in range(n)),
                pulse_width=rng.choice([0, 5, 200]),
                discharge_time=rng.choice([0, 45]),
                polarity=rng.randint(0, 1),
                hv513_num=4,
                sense_pulse_height=rng.choice([0, 30]),
                sense_pulse_width=rng.choice([0, 20]),
                stim_mode=mode,
                prior_scans=0,
            )
            assert _scan_shape(cfg, DEFAULT_CONVENTIONS) == _shape(cfg, DEFAULT_CONVENTIONS)


def test_url_handler_serves_v2_timed_by_default_and_untimed_on_request() -> None:
    from tactdeform_hw import register_url_handlers

    register_url_handlers()
    port = serial.serial_for_url("etactile://?firmware=v2", timeout=1.0)
    try:
        assert isinstance(port.emulator, RealtimeEmulator) and port.emulator.firmware.name == "v2"
        port.write(v2.encode_electrode_num(5) + b"\xf4")
        assert port.read(1) == b"\x05"
        port.write(b"\xfe")  # a cut pattern: the USB Serial/JTAG reset discards it with the registers
        assert wait_until(lambda: port.emulator.state().command_in_progress, 1.0)
        port.dtr, port.rts = False, True
        port.rts = False
        assert "reading PATTERN payload 0/10" in port.resets[-1].discarded["parser"]
        time.sleep(0.3)  # the boot
        port.write(b"\xf4")
        assert port.read(1) == b"\x00"
    finally:
        port.close()
    instant = serial.serial_for_url("etactile://?firmware=v2&timed=0", timeout=0.2)
    try:
        assert isinstance(instant.emulator, Emulator) and instant.emulator.firmware.name == "v2"
        instant.write(b"\xfc\x03\xf4")
        assert instant.read(1) == b"\x03"
    finally:
        instant.close()


# --- the TCP board ------------------------------------------------------------------------------------------


def test_v2_tcp_serves_one_client_at_a_time() -> None:
    with _v2_tcp() as server:
        a = socket.create_connection(server.address, timeout=2)
        b = socket.create_connection(server.address, timeout=2)  # waits in the backlog
        try:
            a.sendall(v2.encode_electrode_num(7) + b"\xf4")
            assert _recv(a, 1) == b"\x07"
            b.sendall(b"\xf4")
            assert _recv(b, 1, timeout=0.3) == b""  # not accepted yet: nothing read, nothing answered
            a.close()
            assert _recv(b, 1, timeout=3) == b"\x07"
            assert server.clients == 2
        finally:
            a.close()
            b.close()


def test_v2_tcp_replies_go_only_to_the_connected_client() -> None:
    with _v2_tcp() as server:
        a = socket.create_connection(server.address, timeout=2)
        a.sendall(bytes(3000) + b"\xf4")  # the reply comes after 3000 unknown bytes have been read
        a.close()
        assert wait_until(lambda: server.clients == 1 and not server.connected)
        b = socket.create_connection(server.address, timeout=2)
        try:
            assert _recv(b, 1, timeout=0.3) == b""
            b.sendall(b"\xf4")
            assert _recv(b, 1) == b"\x00"
            assert server.board.state().rx_dropped == 0  # flow control: nothing lost
        finally:
            b.close()


def test_v2_tcp_flow_control_holds_the_host_back_where_the_serial_queue_drops() -> None:
    """20 000 bytes during 125 Hz scans of 32 channels (each holds the parser off for ~7.6 ms): the TCP
    build loses none and answers the sync check behind them; the serial build's 1024-byte queue drops."""
    flood = SETUP + v2.encode_pattern([9] * N) + bytes(20_000) + b"\xf4"
    with _v2_tcp() as server, socket.create_connection(server.address, timeout=5) as sock:
        sock.sendall(flood)
        assert _recv(sock, 1, timeout=10) == bytes([N])
        assert server.board.state().rx_dropped == 0
        assert not any(h.kind is HazardKind.QUEUE_OVERFLOW for h in server.board.hazards)
    with (
        TcpServer(RealtimeEmulator(rules=SERIAL_USB, firmware="v2"), port=0, rules=SERIAL_USB) as server,
        socket.create_connection(server.address, timeout=5) as sock,
    ):
        sock.sendall(flood)
        assert wait_until(lambda: server.board.state().rx_dropped > 0, 10)
        assert any(h.kind is HazardKind.QUEUE_OVERFLOW for h in server.board.hazards)


def test_replies_to_a_host_that_has_gone_are_not_sent_to_the_next() -> None:
    """The old host's 0xF4 is still read (it reached the receive path) but its answer is not the new
    host's; the new host's own 0xF4 is answered."""
    emu = TimedEmulatorV2(link=TcpLink(), tx_link=TcpLink())
    emu.new_client("a")
    emu.write(v2.encode_electrode_num(3) + b"\xf4", 1000.0)
    emu.new_client("b")  # before the parser read them
    emu.advance_to(20_000.0)
    assert emu.read_tx() == b"" and emu.replies_dropped == 1 and emu.state().electrode_num == 3
    emu.write(b"\xf4", 20_000.0)
    emu.advance_to(40_000.0)
    assert emu.read_tx() == b"\x03"


def _cut_then_new_client(server: TcpServer, gap_s: float) -> socket.socket:
    a = socket.create_connection(server.address, timeout=2)
    a.sendall(v2.encode_electrode_num(N) + b"\xf4")
    assert _recv(a, 1) == bytes([N])
    a.sendall(b"\xfe")  # a pattern cut after its command byte
    assert wait_until(lambda: server.board.state().command_in_progress)
    a.close()
    assert wait_until(lambda: not server.connected)
    time.sleep(gap_s)
    b = socket.create_connection(server.address, timeout=2)
    assert wait_until(lambda: server.connected and server.clients == 2)
    b.sendall(v2.encode_electrode_num(0x20) + v2.encode_stim_mode(0) + v2.encode_pattern([0] * N) + b"\xf4")
    return b


def test_new_client_inherits_a_cut_command_within_2_s_and_it_is_reported() -> None:
    """The firmware's defect: nothing resets the parser on a new connection, so a cut 0xFE takes the
    new client's ``FC 20 FB 00 …`` as its heights (0x20FC clamped to 4095)."""
    with _v2_tcp() as server:
        b = _cut_then_new_client(server, 0.0)
        try:
            assert wait_until(lambda: server.board.state().stim_pattern[0] == 4095)
            st = server.board.state()
            assert list(st.stim_pattern[:2]) == [4095, 0x00FB]
            inherited = [h for h in server.board.hazards if h.kind is HazardKind.INHERITED_COMMAND]
            assert len(inherited) == 1
            d = inherited[0].detail
            assert d["command"] == "PATTERN" and d["cut_bytes"] == "fe"
            assert d["completing_bytes"].startswith("fc 20 fb 00 fe 00")
            assert d["cut_by"].startswith("client 1") and d["completed_by"].startswith("client 2")
            assert d["stored"][:2] == [4095, 0x00FB]
            assert any(
                h.kind is HazardKind.CLAMPED and h.detail["stored"] == 4095 for h in server.board.hazards
            )
            assert "inherited_command" in str(inherited[0])

            def delivered_4095() -> bool:  # judged on the pulses the board delivered, not on the bytes
                board = server.board
                with board.lock:
                    board.state()
                    timed: Any = board.timed
                    return any(r["channel"] == 0 and r["code"] == 4095 for r in timed.delivered())

            assert wait_until(delivered_4095)
        finally:
            b.close()


def test_a_cut_command_older_than_2_s_is_discarded_before_the_new_client_speaks() -> None:
    with _v2_tcp() as server:
        b = _cut_then_new_client(server, 2.1)
        try:
            assert _recv(b, 1) == bytes([0x20])  # the new client's commands were read as sent
            st = server.board.state()
            assert st.electrode_num == 0x20 and st.stim_mode == 0 and max(st.stim_pattern) == 0
            kinds = [h.kind for h in server.board.hazards]
            assert HazardKind.COMMAND_TIMEOUT in kinds and HazardKind.INHERITED_COMMAND not in kinds
        finally:
            b.close()


# --- discovery, the CLI and the driver --------------------------------------------------------------------


def _free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _ask(port: int) -> bytes:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.settimeout(2.0)
        s.sendto(b"ETK?", ("127.0.0.1", port))
        return s.recvfrom(2048)[0]


def test_emulate_tcp_v2_answers_discovery_and_ports_and_the_driver_find_it(
    capsys: pytest.CaptureFixture[str],
) -> None:
    from tactdeform_hw.cli import main

    udp = _free_udp_port()
    proc = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "tactdeform_hw.cli",
            "emulate",
            "--tcp",
            "127.0.0.1:0",
            "--firmware",
            "v2",
            "--discovery-port",
            str(udp),
            "--quiet",
        ],
        cwd=REPO,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        assert proc.stdout is not None
        host, _, tcp = proc.stdout.readline().strip().rpartition(":")
        assert host == "127.0.0.1", proc.stderr.read() if proc.stderr else ""
        assert wait_until(lambda: _answers(udp), 10)
        reply = _ask(udp).decode()
        assert re.fullmatch(
            rf"ETK!;id=F93030;name=etactilekit-F93030;ip=127\.0\.0\.1;port={tcp};mode=AP;fw=1\.0", reply
        )
        assert main(["ports", "--no-usb", "--wifi", f"127.0.0.1:{udp}"]) == 0
        out = capsys.readouterr().out
        assert "etactilekit://F93030" in out and f"127.0.0.1:{tcp}" in out and "fw=1.0" in out
        with pytest.raises(FirmwareMismatchError):  # a v1.2 driver finds a v2 board and sends it nothing more
            open_device(f"etactilekit://F93030?discovery=127.0.0.1:{udp}", firmware="v1.2", timeout=0.3)
        with socket.create_connection(("127.0.0.1", int(tcp)), timeout=2) as sock:
            sock.sendall(b"\xf4")
            assert _recv(sock, 1) == b"\x00"  # the probe left the count at 0 and the parser in step
    finally:
        proc.send_signal(signal.SIGINT)
        _, err = proc.communicate(timeout=10)
    assert proc.returncode == 0, err
    assert f"answering discovery on UDP 127.0.0.1:{udp} as etactilekit-F93030" in err
    assert "firmware v2" in err and "Traceback" not in err


def _answers(port: int) -> bool:
    try:
        return _ask(port).startswith(b"ETK!")
    except OSError:
        return False


def test_emulate_pty_v2_serves_the_timed_v2_board() -> None:
    proc = subprocess.Popen(
        [sys.executable, "-m", "tactdeform_hw.cli", "emulate", "--pty", "--firmware", "v2", "--quiet"],
        cwd=REPO,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        assert proc.stdout is not None
        path = proc.stdout.readline().strip()
        with serial.Serial(path, 921600, timeout=2) as port:
            port.write(v2.encode_electrode_num(9) + b"\xfb\x07\xf4")  # mode 7 clamps to 2
            assert port.read(1) == b"\x09"
    finally:
        proc.send_signal(signal.SIGINT)
        _, err = proc.communicate(timeout=10)
    assert proc.returncode == 0, err
    assert "in real time, serial build rules, firmware v2" in err


@pytest.mark.parametrize(
    ("argv", "flag", "value"),
    [
        # v1.2 has no discovery
        (["--tcp", "0", "--discovery-port", "9"], "--discovery-port", "--firmware v2"),
        (["--pty", "--firmware", "v2", "--kit-id", "ABC123"], "--kit-id", "--tcp"),
        (["--tcp", "0", "--firmware", "v2", "--kit-id", "XYZ"], "--kit-id", "XYZ"),
        (["--tcp", "host:port"], "--tcp", "host:port"),
        (["--tcp", "70000"], "--tcp", "70000"),
        (["--tcp", "0", "--firmware", "v2", "--discovery-port", "70000"], "--discovery-port", "70000"),
    ],
)
def test_emulate_refuses_bad_wifi_options_naming_them(
    argv: list[str], flag: str, value: str, capsys: pytest.CaptureFixture[str]
) -> None:
    from tactdeform_hw.cli import main

    assert main(["emulate", *argv]) != 0
    err = capsys.readouterr().err
    assert err.startswith(f"tactdeform-hw emulate: error: {flag}") and value in err and "Traceback" not in err


def test_socket_url_opens_through_pyserials_handler_paced_on_the_wall_clock() -> None:
    """A v1.2 Wi-Fi board behind ``socket://``: opened by pyserial's own handler (wrapped to declare
    itself guardable: a guardian shares the connection), paced in wall time, driven after the version
    probe."""
    from tactdeform_hw.device.driver.config import StimConfig

    with TcpServer(RealtimeEmulator(rules=WIFI_TCP), port=0) as server:
        dev = open_device(server.url, firmware="auto", timeout=1.0)
        try:
            assert isinstance(dev.port, serial.urlhandler.protocol_socket.Serial)
            assert isinstance(dev.pacer.clock, MonotonicClock)
            assert dev.port.guardable and not dev.port.reset_line
            assert dev.guardian is not None and dev.guardian.alive
            dev.configure(StimConfig(electrode_count=8))
            dev.send_pattern([1, 0, 0, 0, 0, 0, 0, 1])
            assert wait_until(lambda: list(server.board.state().stim_pattern[:8]) == [1, 0, 0, 0, 0, 0, 0, 1])
        finally:
            dev.close()


def test_v12_driver_refused_on_the_v2_tcp_board_by_socket_and_by_discovery() -> None:
    with _v2_tcp() as server, DiscoveryResponder("C0FFEE", port=0, tcp_port=server.address[1]) as responder:
        with pytest.raises(FirmwareMismatchError):
            open_device(server.url, firmware="v1.2", timeout=0.3)
        assert wait_until(lambda: not server.connected)
        with pytest.raises(FirmwareMismatchError):
            open_device(
                f"etactilekit://C0FFEE?discovery=127.0.0.1:{responder.address[1]}",
                firmware="v1.2",
                timeout=0.3,
            )
        assert server.clients == 2
        st = server.board.state()
        assert st.electrode_num == 0 and st.stim_mode == 0 and not st.command_in_progress
        assert not any(h.kind is HazardKind.INHERITED_COMMAND for h in server.board.hazards)


# --- an upstream-style client: 8-byte chunks, 3 ms apart ---------------------------------------------------

#: vectors whose final state does not depend on time: one arrival, no timeout, no overflow (and no random
#: bytes: some set a rate whose scans overrun the period, and then the scans starve the parser, as on the
#: board — the vectors run no scans)
PLAIN = [
    v
    for v in VECTORS
    if "arrivals" not in v and "final_time_us" not in v and not v["category"].startswith("overflow")
]
CHOSEN = [v for v in PLAIN if v["category"] == "burst/python_api_setup"]
CHOSEN += [
    next(v for v in PLAIN if v["category"] == cat)
    for cat in (
        "pattern/complete",
        "burst/config",
        "pattern/stale_channels",
        "pattern/truncated_pending",
        "unknown/run_then_command",
        "replies/burst",
        "truncated/pending",
        "single/sync_check",
    )
]
COMPARED = (
    *V2_SCAN_REGISTERS,
    "timer_alarm_ticks",
    "hv513_num",
    "stim_pattern",
    "rx_pending",
    "rx_dropped",
    "command_in_progress",
)


def _upstream_write(write: Any, data: bytes) -> None:
    """The upstream Python ``write_byte_array`` and Unity ``SerialHandler.Write``: 8 bytes, then 3 ms."""
    for i in range(0, len(data), 8):
        write(data[i : i + 8])
        time.sleep(0.003)


def _check_against_vector(board: RealtimeEmulator, vec: dict[str, Any], replies: bytes) -> None:
    assert settle(board)
    state = board.state()
    regs = state.as_dict()
    expect = vec["expect"]
    for key in COMPARED:
        assert regs[key] == expect[key], (vec["id"], key)
    assert float(state.period_us) == pytest.approx(expect["period_us"], rel=1e-6)
    assert len(replies) == len(expect["tx"]) // 2, vec["id"]
    untimed = Emulator(firmware="v2")
    untimed.feed(bytes.fromhex(vec["stream"]))
    assert {k: untimed.state().as_dict()[k] for k in COMPARED} == {k: regs[k] for k in COMPARED}


def test_upstream_style_client_over_the_pty_reaches_the_vectors_state() -> None:
    from tactdeform_hw.emulator.serving.pty_server import PtyServer

    for vec in CHOSEN:
        stream = bytes.fromhex(vec["stream"])
        with PtyServer(RealtimeEmulator(rules=SERIAL_USB, firmware="v2")) as server:
            with serial.Serial(server.path, 921600, timeout=0.5) as port:
                _upstream_write(port.write, stream)
                assert wait_until(lambda: server.bytes_in == len(stream))  # noqa: B023 (waited for at once)
                n = len(vec["expect"]["tx"]) // 2
                replies = port.read(n) if n else b""
                _check_against_vector(server.board, vec, replies)


def test_upstream_style_client_over_tcp_reaches_the_vectors_state() -> None:
    for vec in CHOSEN:
        stream = bytes.fromhex(vec["stream"])
        with _v2_tcp() as server, socket.create_connection(server.address, timeout=2) as sock:
            sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            _upstream_write(sock.sendall, stream)
            assert wait_until(lambda: server.bytes_in == len(stream))  # noqa: B023 (waited for at once)
            replies = _recv(sock, len(vec["expect"]["tx"]) // 2, timeout=1.0)
            _check_against_vector(server.board, vec, replies)


def test_wifi_board_tool_reports_lag_cpu_and_latency_on_both_transports() -> None:
    proc = subprocess.run(
        [sys.executable, "tools/wifi_board.py", "--idle", "0.2", "--stream", "0.5", "--json"],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert proc.returncode == 0, proc.stderr[-2000:]
    out = json.loads(proc.stdout)
    for transport in ("pty", "tcp"):
        r = out[transport]
        assert r["configured"]
        for name in ("idle", "stream"):
            ph = r[name]
            assert ph["wakeups"] > 0 and ph["lag_max_ms"] >= ph["lag_p99_ms"] >= ph["lag_median_ms"] >= 0
        lat = r["latency"]
        assert lat["applied"] >= 0.8 * lat["writes"] > 0  # frames are stored, none lost
        assert 0 < lat["applied_us"]["min_us"] <= lat["first_pulse_us"]["min_us"]  # causal, and stored first
        p = r["prediction"]["first_channel_us"]
        assert 0 < p["min"] <= p["mean"] <= p["max"]
