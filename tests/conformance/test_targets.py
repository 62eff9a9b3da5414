"""The conformance targets serve the firmware their names ask for, and the servers refuse a firmware that
contradicts the board they are given (a target that silently served v1.2 would pass v1.2-compatible checks
under a v2 name)."""

from __future__ import annotations

import sys

import pytest

from tactdeform_hw.emulator.firmware.skin import SkinModel
from tactdeform_hw.emulator.serving.realtime import RealtimeEmulator
from tactdeform_hw.emulator.serving.tcp_server import TcpServer
from tactdeform_hw.emulator.timed.model_v1_2 import TimedEmulator
from tactdeform_hw.emulator.timed.model_v2 import TimedEmulatorV2
from tactdeform_hw.errors import ConfigurationError

from .conftest import EMULATED_TARGETS, V2_TARGETS, name_firmware


def test_target_names_say_their_firmware() -> None:
    assert [name_firmware(n) for n in EMULATED_TARGETS] == ["v1.2"] * len(EMULATED_TARGETS)
    assert [name_firmware(n) for n in V2_TARGETS] == ["v2"] * len(V2_TARGETS)
    assert name_firmware("/dev/ttyACM0") is None and name_firmware("usb:303a:1001") is None
    with pytest.raises(pytest.UsageError):
        name_firmware("pty?firmware=v3")


def test_a_host_build_target_serves_the_version_its_tree_declares() -> None:
    """``etactile://?firmware_src=DIR`` gets the checks of the version the tree's state map declares (a
    tree that declares none gets neither module's); a folder without a PlatformIO tree is a usage error."""
    from pathlib import Path

    tiny = Path(__file__).resolve().parents[1] / "data" / "firmware_tiny"
    assert name_firmware(f"etactile://?firmware_src={tiny}") == ""
    with pytest.raises(pytest.UsageError, match="firmware_src='/nonexistent'.*src/"):
        name_firmware("etactile://?firmware_src=/nonexistent")


def test_tcp_server_serves_the_named_firmware() -> None:
    server = TcpServer(port=0, firmware="v2")
    try:
        assert isinstance(server.board.timed, TimedEmulatorV2)
        assert server.board.rules.name == "wifi"
    finally:
        server.stop()
    server = TcpServer(port=0)
    try:
        assert isinstance(server.board.timed, TimedEmulator)
    finally:
        server.stop()
    with pytest.raises(ConfigurationError):
        TcpServer(RealtimeEmulator(), port=0, firmware="v2")


@pytest.mark.skipif(sys.platform == "win32", reason="the pty server needs a POSIX pseudo-terminal")
def test_pty_server_serves_the_named_firmware() -> None:
    from tactdeform_hw.emulator.serving.pty_server import PtyServer

    server = PtyServer(firmware="v2")
    try:
        assert isinstance(server.board.timed, TimedEmulatorV2)
    finally:
        server.stop()
    server = PtyServer(RealtimeEmulator(firmware="v2"), firmware="v2")
    server.stop()
    with pytest.raises(ConfigurationError):
        PtyServer(RealtimeEmulator(), firmware="v2")


def test_usb_emulator_serves_the_named_firmware_across_a_replug() -> None:
    pytest.importorskip("usb.core", reason="the usb-emulator needs pyusb")
    from tactdeform_hw.emulator.serving.usb_backend import EmulatedUsbDevice, backend_from_name

    backend = backend_from_name("usb-emulator?firmware=v2")
    assert backend.device.firmware.name == "v2" and isinstance(backend.device.timed, TimedEmulatorV2)
    assert backend.device.state().electrode_num == 0
    dev = backend.replug()  # a power-up builds the firmware afresh: still v2
    assert isinstance(dev.timed, TimedEmulatorV2)
    assert isinstance(backend_from_name("usb-emulator").device.timed, TimedEmulator)
    with pytest.raises(ConfigurationError):
        backend_from_name("usb-emulator?firmware=v3")
    # v2's ADC reads the skin model v1.2 reads: the device hands the one it is given to either firmware
    skin = SkinModel(spread=0.0)
    assert EmulatedUsbDevice(firmware="v2", skin=skin).timed.skin is skin  # type: ignore[attr-defined]
