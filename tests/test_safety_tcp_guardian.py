"""A stop that always happens on the Wi-Fi board: the guardian over ``socket://``.

The real-time Wi-Fi board (the timed firmware model on the wall clock, TCP flow control, one client at a
time) is served in the test process; owners run as separate processes that open it as
``socket://127.0.0.1:PORT``, exactly as on a bench.  Every verdict is on the pulses the emulated board
delivered (its pulse table, in device time), never on the bytes the host meant to send.

The 150 ms bound asserted on delivered pulses is the requirement itself; the stop measured by
``tools/stop_latency.py --transport tcp`` is 5–45 ms, so the bound leaves room for a busy machine.
"""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Iterator

import pytest

from tactdeform_hw import protocol as p
from tactdeform_hw.device import StimConfig, open_device
from tactdeform_hw.device.driver.v2 import off_packet as off_packet_v2
from tactdeform_hw.device.safety.guardian import RESYNC_ZEROS, off_packet, stop_packet
from tactdeform_hw.emulator.serving.realtime import WIFI_TCP, RealtimeEmulator, TcpLink
from tactdeform_hw.emulator.serving.tcp_server import TcpServer
from tactdeform_hw.emulator.timed.model_v1_2 import TimedEmulator
from tactdeform_hw.emulator.timed.model_v2 import TimedEmulatorV2
from tactdeform_hw.protocol.commands import V2_COMMANDS as v2

from .conftest import REPO
from .safety_helpers import configure_v12_tactdeform, current_pulses_us, wait_until

ENV = dict(os.environ, PYTHONPATH=str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", ""))
WAIT_S = 60.0  # generous: the machine may be busy; nothing here but the stop bound is a timing assertion
STOP_BOUND_MS = 150.0
FIRMWARES = ("v1.2", "v2")


@pytest.fixture(params=FIRMWARES)
def wifi(request: pytest.FixtureRequest) -> Iterator[TcpServer]:
    fw = str(request.param)
    server = TcpServer(RealtimeEmulator(rules=WIFI_TCP, firmware=fw), port=0, rules=WIFI_TCP).start()
    try:
        yield server
    finally:
        server.stop()


def _owner(server: TcpServer) -> subprocess.Popen[str]:
    """``tactdeform-hw send`` holding 16 channels at 500 µA for 20 s on the Wi-Fi board."""
    return subprocess.Popen(
        [
            sys.executable, "-m", "tactdeform_hw.cli", "send", "--pattern", ",".join(["1", "0"] * 16),
            "--current-ua", "500", "--hold-ms", "20000", "--device", server.url,
            "--firmware", server.board.firmware.name,
        ],
        stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, env=ENV, cwd=str(REPO),
        start_new_session=True,
    )  # fmt: skip


def _kill_stimulating_owner(server: TcpServer) -> tuple[subprocess.Popen[str], float, float]:
    """Start an owner, wait until the board delivers its pulses, SIGKILL it; (owner, wall, device µs)."""
    proc = _owner(server)
    assert wait_until(
        lambda: bool(current_pulses_us(server.board, 0.0)) or proc.poll() is not None, timeout_s=WAIT_S
    )
    assert proc.poll() is None, proc.communicate()[1]
    time.sleep(0.05)
    t_kill = time.monotonic()
    os.kill(proc.pid, signal.SIGKILL)
    return proc, t_kill, server.board.device_us(t_kill)


def test_sigkill_of_a_tcp_owner_switches_the_board_off_within_150_ms(wifi: TcpServer) -> None:
    """No guardian on ``socket://`` left the board stimulating for good; now no pulse with current
    starts more than 150 ms after the kill, and the guardian says it proved the stop."""
    proc, _, kill_us = _kill_stimulating_owner(wifi)
    try:
        assert proc.wait(timeout=WAIT_S) == -signal.SIGKILL
        assert wait_until(
            lambda: not wifi.connected, timeout_s=WAIT_S
        )  # the guardian leaves once the board is off
        time.sleep(0.3)  # scans keep running: a board still on would deliver here
        late = [t for t in current_pulses_us(wifi.board, kill_us) if t > kill_us + 1000 * STOP_BOUND_MS]
        assert not late, f"{len(late)} pulses with current, last {(late[-1] - kill_us) / 1000:.1f} ms after"
        stderr = proc.communicate(timeout=WAIT_S)[1]
        assert "guardian" in stderr and "heights 0 proved" in stderr and "all-off pattern proved" in stderr
        assert "Traceback" not in stderr
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT, signal.SIGHUP])
def test_a_stop_signal_to_a_tcp_owner_switches_the_board_off(wifi: TcpServer, sig: signal.Signals) -> None:
    """The owner's own stop session on the Wi-Fi board: every channel off before it exits, judged on the
    delivered pulses (the same 150 ms bound as the guardian's)."""
    proc = _owner(wifi)
    try:
        assert wait_until(
            lambda: bool(current_pulses_us(wifi.board, 0.0)) or proc.poll() is not None, timeout_s=WAIT_S
        )
        assert proc.poll() is None, proc.communicate()[1]
        time.sleep(0.05)
        t_sig = time.monotonic()
        sig_us = wifi.board.device_us(t_sig)
        os.killpg(proc.pid, sig)  # as a terminal delivers it: to the whole process group
        stderr = proc.communicate(timeout=WAIT_S)[1]
        assert f"stopped by {sig.name}; every channel off" in stderr and "Traceback" not in stderr
        time.sleep(0.3)
        late = [t for t in current_pulses_us(wifi.board, sig_us) if t > sig_us + 1000 * STOP_BOUND_MS]
        assert not late, f"{len(late)} pulses with current after {sig.name}"
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()


def test_a_clean_close_on_tcp_releases_the_guardian_without_it_writing(
    wifi: TcpServer, capfd: pytest.CaptureFixture[str]
) -> None:
    dev = open_device(wifi.url, firmware=wifi.board.firmware.name)
    guardian = dev.guardian
    assert guardian is not None and guardian.alive and getattr(dev.port, "guardable", False)
    dev.configure(StimConfig(current_ua=500))
    dev.send_pattern([1, 0] * 16)
    assert wait_until(lambda: bool(current_pulses_us(wifi.board, 0.0)), timeout_s=WAIT_S)
    dev.close()
    assert guardian.proc.returncode == 0  # released: close() waited for it
    assert wait_until(lambda: not wifi.connected, timeout_s=WAIT_S)
    written = wifi.board.bytes_in
    assert written == dev.pacer.stats.bytes_written  # every byte the board read was the owner's
    time.sleep(0.2)
    assert wifi.board.bytes_in == written
    assert "guardian" not in capfd.readouterr().err  # it had nothing to say: it did not act


def test_a_client_waiting_in_the_backlog_gets_the_board_only_after_the_all_off(wifi: TcpServer) -> None:
    """The guardian holds the owner's connection, so the board — one client at a time — stays the dead
    owner's until the all-off is in force: a client queued in the backlog meanwhile finds it off."""
    proc, _, _ = _kill_stimulating_owner(wifi)
    waiting = socket.create_connection(wifi.address, timeout=5)  # in the backlog: not served yet
    try:
        assert wifi.clients == 1
        assert wait_until(lambda: wifi.clients == 2, timeout_s=WAIT_S)
        served_us = wifi.board.device_us()  # at or after the moment it was accepted
        time.sleep(0.3)
        after = current_pulses_us(wifi.board, served_us)
        assert not after, f"{len(after)} pulses with current after the next client got the board"
    finally:
        waiting.close()
        if proc.poll() is None:
            proc.kill()
        proc.communicate(timeout=WAIT_S)


# --- the guardian's bytes in every parser state an owner can leave on the Wi-Fi board -------------------

OWNER_UA = 500.0
DRAIN_US = 36_400.0  # the drain wait at this setting (125 Hz, 32 channels)


def _v12_board() -> tuple[TimedEmulator, bytes, float]:
    emu = TimedEmulator(link=TcpLink(), tx_link=TcpLink(), model=WIFI_TCP.timing(None))
    t = configure_v12_tactdeform(emu)
    frame = p.encode_pattern(bytes([1, 0] * 16), electrode_num=32) + p.encode_pulse_height(50)
    return emu, frame, t


def _v2_board() -> tuple[TimedEmulatorV2, bytes, float]:
    emu = TimedEmulatorV2(link=TcpLink(), tx_link=TcpLink(), model=WIFI_TCP.timing(None))
    t = 0.0
    heights = [50, 0] * 16
    for cmd in (
        v2.encode_electrode_num(32),
        v2.encode_stim_mode(0),
        v2.encode_pulse_width(200),
        v2.encode_discharge(45),
        v2.encode_frequency(125),
        v2.encode_pattern(heights),
    ):
        emu.write(cmd, at_us=t)
        t += 12_000
    frame = v2.encode_stim_mode(0) + v2.encode_pattern(heights)
    return emu, frame, t


def _guardian_over_tcp(firmware: str, tail: bytes, first_us: float) -> tuple[float, float, float]:
    """The owner dies having written ``tail`` (a torn frame, whole frames before it); ``first_us`` later
    the guardian's stop lands (TCP: sent at once, behind whatever the owner left in the send queue), then
    — as when no proof comes back, the worst case — the stop again after the drain wait, 256 zeros and the
    stop again, and the all-off.  Returns the largest current delivered from the death on, how long after
    the death the last pulse with current started (ms), and the largest current once the guardian is
    done."""
    emu: TimedEmulator | TimedEmulatorV2
    if firmware == "v2":
        emu, _, t = _v2_board()
        stop, off = off_packet_v2(0), off_packet_v2(32)
    else:
        emu, _, t = _v12_board()
        stop, off = stop_packet(), off_packet(32)
    emu.advance_to(t)
    death = t + 100
    if tail:
        emu.write(tail, at_us=death)
    g = death + first_us
    emu.write(stop, at_us=g)
    emu.write(stop, at_us=g + DRAIN_US)
    tk = g + DRAIN_US + 40_000
    for i in range(RESYNC_ZEROS // 64):
        emu.write(bytes(64), at_us=tk + i * 1200)
    emu.write(stop, at_us=tk + 200_000)
    done = tk + 400_000
    emu.write(off, at_us=done)
    emu.advance_to(done + 100_000)
    table = emu.reports.pulse_table(death)
    current, start = table["current_ua"], table["start_us"]
    on = current > 0
    last_ms = float((start[on].max() - death) / 1000) if on.any() else 0.0
    after = current[start > done]
    return (
        float(current.max()) if current.size else 0.0,
        last_ms,
        float(after.max()) if after.size else 0.0,
    )


@pytest.mark.parametrize("firmware", FIRMWARES)
def test_guardian_bytes_on_the_wifi_board_stop_whatever_the_owner_left(firmware: str) -> None:
    """Judged on the pulses the timed firmware delivered over the TCP link: the owner cut at every byte of
    a frame (alone, or after frames still unread) and the guardian's stop landing right behind or after
    a delay: no pulse above the owner's 500 µA, none with current 150 ms after the death or once the
    guardian is done."""
    frame = (_v2_board() if firmware == "v2" else _v12_board())[1]
    cases = [(frame[:k], first) for k in range(len(frame)) for first in (0.0, 3_000.0)]
    cases += [(frame * 4 + frame[:k], 0.0) for k in range(0, len(frame), 7)]
    for tail, first in cases:
        peak, last_ms, after = _guardian_over_tcp(firmware, tail, first)
        assert peak <= OWNER_UA + 1e-6 and after == 0.0, (tail.hex(), first, peak, after)
        assert last_ms <= STOP_BOUND_MS, (tail.hex(), first, last_ms)


# --- the guardian's side on a socket ----------------------------------------------------------------------


def test_on_a_socket_the_stop_goes_at_once_and_stale_replies_are_no_proof() -> None:
    """A board that never answers, with the owner's stale reply already waiting in the connection: the
    guardian sends its stop at once (behind what the owner left), discards the stale byte instead of
    taking it as the proof, retries, and reports no proof — it pulses no reset line on TCP."""
    from tactdeform_hw.device.safety.guardian import switch_off

    with socket.create_server(("127.0.0.1", 0)) as listener:
        guardian_end = socket.create_connection(listener.getsockname()[:2])
        board_end, _ = listener.accept()
    with guardian_end, board_end:
        guardian_end.setblocking(False)
        board_end.sendall(b"\x04")  # the reply to the owner's last request, never read by the owner
        time.sleep(0.05)
        stop = stop_packet()
        how = switch_off(
            guardian_end.fileno(), stop, off_packet(32), reset_line=True, budget_s=0.3, drain_s=0.01,
            zeros_s=0.01,
        )  # fmt: skip
        board_end.settimeout(1.0)
        got = b""
        try:
            while chunk := board_end.recv(65536):
                got += chunk
                board_end.settimeout(0.05)
        except TimeoutError:
            pass
    assert how.startswith("NO PROOF"), how
    assert got.startswith(stop + stop)  # at once, then the first attempt of the proof loop
    assert got.count(stop) >= 3 and off_packet(32) not in got  # retried; no all-off without a proof


def test_the_stop_latency_tool_measures_the_guardian_on_tcp(capsys: pytest.CaptureFixture[str]) -> None:
    import json

    sys.path.insert(0, str(REPO / "tools"))
    import stop_latency

    args = ["--transport", "tcp", "--firmware", "v2", "--signals", "KILL", "--trials", "1", "--json"]
    assert stop_latency.main(args) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["transport"] == "tcp" and "socket://" in out["board"]
    assert out["SIGKILL"]["trials"] == 1 and 0 <= out["SIGKILL"]["max_ms"] <= STOP_BOUND_MS
