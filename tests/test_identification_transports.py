"""The identification on every transport a board is served on, both firmware versions: the driver speaks
the version the board proved, and a driver told the other version is refused with the board left off."""

from __future__ import annotations

from collections.abc import Callable, Iterator
from contextlib import AbstractContextManager, contextmanager

import pytest

from tactdeform_hw.device.driver.config import StimConfig
from tactdeform_hw.device.driver.firmware_probe import FirmwareMismatchError
from tactdeform_hw.device.driver.serial_driver import open_device


@contextmanager
def _url(fw: str) -> Iterator[tuple[str, Callable[[], dict]]]:
    import uuid

    from tactdeform_hw.emulator.serving.urlhandler.protocol_etactile import shared_emulator

    name = f"ident-{uuid.uuid4().hex}"  # a board of this test's own, shared by its opens
    yield f"etactile://{name}?firmware={fw}", lambda: shared_emulator(name).state()


@contextmanager
def _pty(fw: str) -> Iterator[tuple[str, Callable[[], dict]]]:
    from tactdeform_hw.emulator.serving.pty_server import PtyServer

    server = PtyServer(firmware=fw).start()
    try:
        yield server.path, server.board.state
    finally:
        server.stop()


@contextmanager
def _tcp(fw: str) -> Iterator[tuple[str, Callable[[], dict]]]:
    from tactdeform_hw.emulator.serving.realtime import WIFI_TCP, RealtimeEmulator
    from tactdeform_hw.emulator.serving.tcp_server import TcpServer

    server = TcpServer(RealtimeEmulator(rules=WIFI_TCP, firmware=fw), port=0, rules=WIFI_TCP)
    server.start()
    try:
        yield server.url, server.board.state
    finally:
        server.stop()


@contextmanager
def _usb(fw: str) -> Iterator[tuple[str, Callable[[], dict]]]:
    pytest.importorskip("usb", reason="the [usb] extra (pyusb) serves the emulated USB device")
    from tactdeform_hw.emulator.serving.usb_server import UsbServer

    server = UsbServer(firmware=fw).start()
    try:
        yield server.name, server.board.state
    finally:
        server.stop()


TRANSPORTS: dict[str, Callable[[str], AbstractContextManager[tuple[str, Callable[[], dict]]]]] = {
    "url": _url,
    "pty": _pty,
    "tcp": _tcp,
    "usb": _usb,
}
OTHER = {"v1.2": "v2", "v2": "v1.2"}


@pytest.mark.parametrize("fw", ["v1.2", "v2"])
@pytest.mark.parametrize("transport", list(TRANSPORTS))
def test_the_board_is_driven_in_the_version_it_proved_and_refused_in_the_other(
    transport: str, fw: str
) -> None:
    # each board is served fresh for this test: no other program wrote to it, so nothing is waited out
    with TRANSPORTS[transport](fw) as (name, state):
        with pytest.raises(FirmwareMismatchError, match=f"runs firmware {fw}.*firmware='{OTHER[fw]}'"):
            open_device(name, firmware=OTHER[fw], settle_s=0.0, timeout=0.3)
        s = state()
        assert s.electrode_num == 0 and s.sense_pulse_height == 0
        dev = open_device(name, settle_s=0.0, timeout=0.3)
        try:
            assert dev.firmware == fw and dev.identification.firmware.name == fw
            dev.configure(StimConfig(electrode_count=4, current_ua=300, pulse_width_us=200))
            dev.send_pattern([1, 0, 1, 0])
        finally:
            dev.close()
        assert state().electrode_num == (0 if fw == "v2" else 4)
