"""Finding candidate boards through pyserial and pyusb, and ``tactdeform-hw ports``."""

from __future__ import annotations

import json
import sys
from types import SimpleNamespace

import pytest

from tactdeform_hw.cli import main
from tactdeform_hw.device.driver import discovery, usb_transport
from tactdeform_hw.device.driver.discovery import discover, serial_candidates

BOARD_SERIAL = "F4:12:FA:C0:FF:EE"


def comport(
    device: str, vid: int | None, pid: int | None, serial: str | None = None, product: str | None = None
) -> SimpleNamespace:
    """A record shaped like pyserial's ``ListPortInfo``."""
    return SimpleNamespace(
        device=device, vid=vid, pid=pid, serial_number=serial, product=product, manufacturer=None,
        description=product or "n/a", location=None,
    )  # fmt: skip


PORTS = [
    comport("/dev/ttyACM0", 0x303A, 0x1001, BOARD_SERIAL, "USB JTAG/serial debug unit"),
    comport("/dev/ttyUSB0", 0x0403, 0x6001, "FT1", "FT232R USB UART"),
    comport("/dev/ttyS0", None, None),
]


def test_serial_candidates_mark_espressif_with_reasons() -> None:
    found = {c.device: c for c in serial_candidates(PORTS)}
    board = found["/dev/ttyACM0"]
    assert board.transport == "serial" and board.likely
    assert any("0x303A" in r for r in board.reasons) and any("0x1001" in r for r in board.reasons)
    assert not found["/dev/ttyUSB0"].likely and found["/dev/ttyUSB0"].reasons == ()
    assert [c.device for c in serial_candidates(PORTS, include_all=False)] == ["/dev/ttyACM0"]


def test_discover_lists_both_routes_and_links_the_same_board() -> None:
    pytest.importorskip("usb.core")
    from tactdeform_hw.emulator.serving.usb_backend import EmulatedUsbBackend

    result = discover(usb_backend=EmulatedUsbBackend(), serial_ports=PORTS)
    assert result.usb_available and result.notes == []
    routes = {(c.transport, c.device) for c in result.candidates}
    assert ("serial", "/dev/ttyACM0") in routes and ("serial", "/dev/ttyUSB0") in routes
    assert ("serial", "/dev/ttyS0") not in routes  # no USB ids: cannot be the controller (shown with --all)
    usb = [c for c in result.candidates if c.transport == "usb"]
    assert len(usb) == 1
    u = usb[0]
    assert u.device == f"usb:303a:1001:{BOARD_SERIAL}" and u.likely and u.same_board_as == "/dev/ttyACM0"
    assert any("CDC-ACM" in r for r in u.reasons) and any("JTAG" in r for r in u.reasons)
    assert u.location and u.location.startswith("bus 1 address")
    assert {c.device for c in result.likely} == {"/dev/ttyACM0", u.device}
    assert (
        discover(usb_backend=EmulatedUsbBackend(), serial_ports=PORTS, include_all=True).candidates[2].device
        == "/dev/ttyS0"
    )


def test_unreadable_strings_are_a_note_not_an_error() -> None:
    pytest.importorskip("usb.core")
    from tactdeform_hw.emulator.serving.usb_backend import EmulatedUsbBackend, EmulatedUsbDevice

    result = discover(
        usb_backend=EmulatedUsbBackend([EmulatedUsbDevice(access_denied=True)]), serial_ports=[]
    )
    (u,) = result.candidates
    assert u.likely and u.device == "usb:303a:1001" and u.serial_number is None
    assert any("no permission" in n and "udev" in n for n in u.notes)


def test_no_libusb_still_lists_serial_ports(monkeypatch: pytest.MonkeyPatch) -> None:
    pytest.importorskip("usb.core")
    monkeypatch.setattr(usb_transport, "default_backend", lambda: None)
    result = discover(serial_ports=PORTS)
    assert not result.usb_available
    assert [c.transport for c in result.candidates] == ["serial", "serial"]
    assert any("libusb-1.0-0" in n for n in result.notes)


def test_no_pyusb_still_lists_serial_ports(monkeypatch: pytest.MonkeyPatch) -> None:
    for mod in [m for m in sys.modules if m == "usb" or m.startswith("usb.")]:
        monkeypatch.setitem(sys.modules, mod, None)
    monkeypatch.setitem(sys.modules, "usb", None)
    result = discover(serial_ports=PORTS)
    assert not result.usb_available and len(result.candidates) == 2
    assert any("[usb]'" in n for n in result.notes)  # the install command of the running package


def test_ports_command_json_with_the_emulated_bus(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    pytest.importorskip("usb.core")
    monkeypatch.setattr(
        discovery, "serial_candidates", lambda ports=None, include_all=True: serial_candidates(PORTS)
    )
    assert main(["ports", "--json", "--usb-emulator"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["usb_available"] is True
    usb = [c for c in out["candidates"] if c["transport"] == "usb"]
    assert usb[0]["vid"] == "303a" and usb[0]["likely"] and usb[0]["same_board_as"] == "/dev/ttyACM0"


def test_ports_command_text_without_libusb(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    pytest.importorskip("usb.core")
    monkeypatch.setattr(usb_transport, "default_backend", lambda: None)
    monkeypatch.setattr(
        discovery, "serial_candidates", lambda ports=None, include_all=True: serial_candidates(PORTS)
    )
    assert main(["ports"]) == 0
    out = capsys.readouterr().out
    assert "serial  /dev/ttyACM0" in out and "likely an eTactileKit controller" in out
    assert "note: USB devices not searched: pyusb found no USB backend" in out and "libusb-1.0-0" in out
    assert main(["ports", "--no-usb"]) == 0
    assert "not searched (--no-usb)" in capsys.readouterr().out


def test_ports_command_text_with_the_emulated_bus(capsys: pytest.CaptureFixture[str]) -> None:
    pytest.importorskip("usb.core")
    assert main(["ports", "--usb-emulator"]) == 0
    out = capsys.readouterr().out
    assert f"usb     usb:303a:1001:{BOARD_SERIAL}" in out
    assert "likely an eTactileKit controller: Espressif vendor id 0x303A" in out
