"""Identification at the seams, judged on the pulses the emulated Wi-Fi board delivered: a second program on
a busy board is refused and leaves nothing that becomes current, and a command cut by an earlier client
never becomes current in the next program's session."""

from __future__ import annotations

import socket
import time

import pytest

from tactdeform_hw.device.driver.config import StimConfig
from tactdeform_hw.device.driver.firmware_probe import FirmwareMismatchError
from tactdeform_hw.device.driver.serial_driver import open_device
from tactdeform_hw.emulator import HazardKind
from tactdeform_hw.emulator.serving.realtime import WIFI_TCP, RealtimeEmulator
from tactdeform_hw.emulator.serving.tcp_server import TcpServer
from tactdeform_hw.errors import BoardBusyError

from .safety_helpers import delivered_pulses, wait_until

FIRMWARES = ("v1.2", "v2")


def _tcp(fw: str) -> TcpServer:
    return TcpServer(RealtimeEmulator(rules=WIFI_TCP, firmware=fw), port=0, rules=WIFI_TCP)


def _now_us(board: RealtimeEmulator) -> float:
    with board.lock:
        board.state()
        return float(board.timed.now_us)


@pytest.mark.parametrize("fw", FIRMWARES)
def test_a_second_program_on_a_busy_wifi_board_is_refused_and_nothing_it_wrote_becomes_current(
    fw: str,
) -> None:
    with _tcp(fw) as server:
        first = open_device(server.url, timeout=0.3)
        assert first.firmware == fw
        first.configure(StimConfig(electrode_count=4, current_ua=500, pulse_width_us=200))
        first.send_pattern([1] * 4)
        with pytest.raises(BoardBusyError, match="serves one client at a time.*only bytes written"):
            open_device(server.url, timeout=0.3)
        time.sleep(0.1)
        first.close()  # the second program's bytes are read now, behind the first's all-off
        left_us = _now_us(server.board)
        time.sleep(0.4)
        seen = delivered_pulses(server.board)
        assert seen and max(ua for _, _, ua in seen) <= 500 + 1e-6
        assert [p for p in seen if p[0] > left_us + 20_000 and p[2] > 0] == []
        st = server.board.state()
        assert st.electrode_num == 0 and not st.command_in_progress


@pytest.mark.parametrize("fw", FIRMWARES)
def test_a_command_cut_by_an_earlier_client_never_becomes_current(fw: str) -> None:
    """An earlier client writes electrode count 32 and a pattern holding 1½ entries, and leaves; the next
    program opens the board 50 ms later, configures 500 µA and a pattern on 8 electrodes.  v2 discards
    the cut pattern by its 2 s timeout while the identification waits (reported as a timeout); v1.2's cut
    pattern takes the identification's zeros as levels, which are off."""
    with _tcp(fw) as server:
        a = socket.create_connection(server.address, timeout=2)
        a.sendall(bytes.fromhex("fc20fefc20fb"))
        assert wait_until(lambda: server.board.state().electrode_num == 0x20)
        a.close()
        assert wait_until(lambda: not server.connected)
        time.sleep(0.05)
        dev = open_device(server.url, timeout=0.3)
        try:
            dev.configure(StimConfig(electrode_count=8, current_ua=500, pulse_width_us=200))
            dev.send_pattern([1] * 8)
            time.sleep(0.3)
        finally:
            dev.close()
        seen = delivered_pulses(server.board)
        assert seen and max(ua for _, _, ua in seen) <= 500 + 1e-6
        assert {ch for _, ch, ua in seen if ua > 0} <= set(range(8))
        kinds = {h.kind for h in server.board.hazards}
        assert HazardKind.INHERITED_COMMAND not in kinds
        if fw == "v2":
            assert HazardKind.COMMAND_TIMEOUT in kinds  # the firmware discarded it, and it is on record


def test_a_v12_driver_is_refused_on_the_v2_wifi_board_and_leaves_it_off() -> None:
    with _tcp("v2") as server:
        with pytest.raises(FirmwareMismatchError, match="runs firmware v2"):
            open_device(server.url, firmware="v1.2", timeout=0.3)
        assert wait_until(lambda: not server.connected)
        st = server.board.state()
        assert st.electrode_num == 0 and st.stim_mode == 0 and not st.command_in_progress
        assert (
            delivered_pulses(server.board) == []
            or max(ua for _, _, ua in delivered_pulses(server.board)) == 0
        )
