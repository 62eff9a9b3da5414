"""The transport table: which port a device name opens, and how other packages add one."""

from __future__ import annotations

import subprocess
import sys

import pytest

from tactdeform_hw import transports
from tactdeform_hw.device import open_device, open_port
from tactdeform_hw.emulator.transport import EmulatorPort
from tactdeform_hw.errors import TransportError, TransportUnavailableError


def inproc_port(name: str, *, timeout: float | None, baudrate: int) -> EmulatorPort:
    """A third-party transport as an entry point names it."""
    return EmulatorPort(timeout=timeout)


@pytest.mark.parametrize(
    ("name", "scheme"),
    [
        ("/dev/ttyACM0", "path"),
        ("COM3", "path"),
        ("etactile://a?timed=0", "etactile"),
        ("socket://127.0.0.1:5000", "socket"),
        ("etactilekit://kit-1", "etactilekit"),
        ("usb:303a:1001", "usb"),
        ("usb://303a:1001", "usb"),
        ("usb-emulator", "usb-emulator"),
        ("usb-emulator?board=large", "usb-emulator"),
        ("loop://", "loop"),
    ],
)
def test_the_scheme_picks_the_transport(name: str, scheme: str) -> None:
    assert transports.scheme_of(name) == scheme


def test_usb_url_and_the_short_form_name_the_same_board() -> None:
    pytest.importorskip("usb", reason="the USB transport needs pyusb (extra [usb])")
    a, b = open_port("usb://303a:1001"), open_port("usb:303a:1001")
    assert a.spec == b.spec and (a.spec.vid, a.spec.pid) == (0x303A, 0x1001)


def test_a_registered_transport_opens_its_scheme(monkeypatch: pytest.MonkeyPatch) -> None:
    made: list[str] = []

    def factory(name: str, *, timeout: float | None, baudrate: int) -> EmulatorPort:
        made.append(name)
        return EmulatorPort(timeout=timeout)

    monkeypatch.setitem(transports._registered, "bench", factory)
    with open_device("bench://rig-2") as dev:
        assert dev.hv513_count() == 4
    assert made == ["bench://rig-2"]
    assert transports.available_transports()["bench"].endswith("factory")


def test_an_entry_point_transport_is_imported_when_used(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(transports, "_entry_points", {"inproc": "tests.test_transports:inproc_port"})
    port = open_port("inproc://x")
    assert isinstance(port, EmulatorPort) and port.timeout == 0.5


def test_a_transport_whose_module_is_missing_is_a_specific_error(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(transports, "_entry_points", {"ble": "no_such_transport_pkg.ble:open_port"})
    with pytest.raises(TransportUnavailableError, match="'ble' transport .*no_such_transport_pkg") as ei:
        open_port("ble://aa:bb")
    assert isinstance(ei.value, TransportError) and ei.value.scheme == "ble"


def test_an_unknown_scheme_is_refused_naming_it() -> None:
    with pytest.raises(TransportError, match="nosuch://x"):
        open_port("nosuch://x")


def test_the_device_layer_does_not_import_the_emulator() -> None:
    code = (
        "import sys, tactdeform_hw.device, tactdeform_hw.device.usb_transport, tactdeform_hw.transports;"
        "print(sorted(m for m in sys.modules if m.startswith('tactdeform_hw.emulator')"
        " and m != 'tactdeform_hw.emulator'))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "[]"
