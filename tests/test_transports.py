"""The transport table: which port a device name opens, and how other packages add one."""

from __future__ import annotations

import re
import subprocess
import sys

import pytest

from tactdeform_hw import transports
from tactdeform_hw.device import open_device, open_port
from tactdeform_hw.emulator.serving.in_process import EmulatorPort
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
        "import sys, tactdeform_hw.device, tactdeform_hw.device.driver.usb_transport, "
        "tactdeform_hw.transports;"
        "print(sorted(m for m in sys.modules if m.startswith('tactdeform_hw.emulator')"
        " and m != 'tactdeform_hw.emulator'))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "[]"


# --- what each port declares ---------------------------------------------------------------------------


@pytest.mark.parametrize("name", ["etactile://?timed=0", "etactile://?timed=1"])
def test_the_emulators_port_resets_through_its_reset_line(name: str) -> None:
    from tactdeform_hw.protocol.commands import encode_electrode_num

    port = open_port(name)
    port.open()
    try:
        port.write(encode_electrode_num(8))
        assert _eventually(lambda: port.board_state().electrode_num == 8)
        port.pulse_reset()
        assert port.board_state().electrode_num == 0 and len(port.resets) == 1
        assert port.board_hazards == port.emulator.hazards
    finally:
        port.close()


def _eventually(check, timeout_s: float = 2.0) -> bool:  # type: ignore[no-untyped-def]
    import time

    end = time.monotonic() + timeout_s
    while not check():
        if time.monotonic() > end:
            return False
        time.sleep(0.002)
    return True


def test_capabilities_by_port() -> None:
    from tactdeform_hw.clock import InstantClock, MonotonicClock
    from tactdeform_hw.ports import board_state, is_instant, pacing_clock

    instant, timed, path = open_port("emulator"), open_port("etactile://"), open_port("/dev/ttyACM9")
    assert is_instant(instant) and isinstance(pacing_clock(instant), InstantClock)
    assert not is_instant(timed) and isinstance(pacing_clock(timed), MonotonicClock)
    assert not is_instant(path) and pacing_clock(path) is None and path.guardable
    assert board_state(path) is None  # a board cannot show its registers
    port = EmulatorPort()
    with port:
        assert is_instant(port) and board_state(port).electrode_num == 0 and port.board_hazards == []
    with pytest.raises(TransportError, match="not open"):
        port.out_waiting  # noqa: B018 - the property is the check


@pytest.mark.parametrize("name", ["/dev/ttyNOPE9", "socket://127.0.0.1:9"])
def test_a_path_or_socket_port_is_made_unopened_and_a_refused_setting_names_the_port(name: str) -> None:
    port = open_port(name, timeout=0.1)
    assert port.port == name and not port.is_open and port.write_timeout == 0.1
    with pytest.raises(TransportError, match=rf"^cannot create port '{re.escape(name)}': .*-1"):
        open_port(name, timeout=0.1, baudrate=-1)
