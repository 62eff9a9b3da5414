"""The pyusb CDC-ACM transport over the emulated ESP32-S3 USB device: pyusb's own code runs between them."""

from __future__ import annotations

import errno
import re
import struct
import sys
import threading
import time

import pytest

pytest.importorskip("usb.core", reason="the USB transport needs pyusb (pip install 'tactdeform_hw[usb]')")

import serial  # noqa: E402

from tactdeform_hw.device import EtactileKitDevice, StimConfig, open_device, open_port
from tactdeform_hw.device.driver import usb_transport
from tactdeform_hw.device.driver.usb_transport import UsbCdcPort, UsbDeviceSpec  # noqa: E402
from tactdeform_hw.emulator.serving.usb_backend import (  # noqa: E402
    EP_INTERRUPT,
    EmulatedUsbBackend,
    EmulatedUsbDevice,
    esp32s3_interfaces,
)
from tactdeform_hw.errors import (  # noqa: E402
    ConfigurationError,
    DeviceBusyError,
    DeviceGoneError,
    DeviceTimeoutError,
    MissingDependencyError,
    PortNotOpenError,
    TransportError,
    install_command,
)
from tactdeform_hw.protocol import encode_electrode_num, encode_pulse_height  # noqa: E402

SET_LINE_CODING = (0x21, 0x20)
SET_CONTROL_LINE_STATE = (0x21, 0x22)


@pytest.fixture
def backend() -> EmulatedUsbBackend:
    return EmulatedUsbBackend()


def port_on(backend: EmulatedUsbBackend, **kw: object) -> UsbCdcPort:
    kw.setdefault("timeout", 0.5)
    return UsbCdcPort(0x303A, 0x1001, backend=backend, **kw)  # type: ignore[arg-type]


# --- configuration ----------------------------------------------------------------------------------


def test_open_detaches_claims_sets_line_coding_and_keeps_the_chip_out_of_reset(
    backend: EmulatedUsbBackend,
) -> None:
    d = backend.device
    assert d.kernel_bound == {0, 1}  # cdc_acm holds the CDC interfaces, as on Linux
    port = port_on(backend)
    port.open()
    try:
        assert port.is_open
        assert port.detached == [0, 1] and d.kernel_bound == set()
        assert sorted(d.claims) == [0, 1]  # the JTAG interface (2) is left alone
        assert (port.comm_interface, port.data_interface) == (0, 1)
        assert (port.ep_out, port.ep_in, port.packet_size) == (0x01, 0x81, 64)
        assert d.line_coding == struct.pack("<IBBB", 921_600, 0, 0, 8) and port.line_coding_accepted
        requests = [(r[0], r[1]) for r in d.control_log]
        assert SET_LINE_CODING in requests
        lines = [r for r in d.control_log if (r[0], r[1]) == SET_CONTROL_LINE_STATE]
        assert lines and all(r[2] == 0 and r[3] == 0 for r in lines)  # DTR and RTS low, to interface 0
        assert d.resets == 0
    finally:
        port.close()
    assert not port.is_open
    assert d.kernel_bound == {0, 1} and d.claims == {}  # the kernel driver has its interfaces back
    port.close()  # idempotent


def test_unconfigured_device_gets_a_configuration_and_no_kernel_driver_is_fine() -> None:
    be = EmulatedUsbBackend([EmulatedUsbDevice(configured=False, kernel_driver=False)])
    with port_on(be) as port:
        assert be.device.configuration == 1
        assert port.detached == []
        port.write(b"\xf5")
        assert port.read(1) == b"\x04"


def test_platform_without_kernel_driver_query(backend: EmulatedUsbBackend) -> None:
    be = EmulatedUsbBackend([EmulatedUsbDevice(kernel_driver=None)])  # pyusb raises NotImplementedError
    with port_on(be) as port:
        assert port.detached == []
        port.write(b"\xf5")
        assert port.read(1) == b"\x04"


def test_driver_runs_unchanged_configure_patterns_measure(backend: EmulatedUsbBackend) -> None:
    d = backend.device
    dev = EtactileKitDevice(port_on(backend))
    try:
        assert dev.hv513_count() == 4
        dev.configure(
            StimConfig(electrode_count=32, current_ua=500, pulse_width_us=180, discharge_us=40, rate_hz=100)
        )
        assert d.settle()
        st = d.state()
        assert (st.electrode_num, st.pulse_height, st.pulse_width_us, st.discharge_time_us) == (
            32,
            50,
            180,
            40,
        )
        assert st.period_us == 10_000.0 and st.rx_pending == 0
        levels = [(i % 3) for i in range(32)]
        dev.send_pattern(levels)
        assert d.settle()
        assert list(d.state().stim_pattern[:32]) == levels
        time.sleep(0.025)  # two stimulation periods: every channel has had a pulse with this pattern
        adc = dev.measure()  # one full 64-byte packet
        assert adc == list(d.emulator.registers.voltage[:32])  # what the scans measured
        assert all(v > 0 for i, v in enumerate(adc) if levels[i]) and all(0 <= v < 1024 for v in adc)
        assert d.timed.losses == []
    finally:
        dev.close()
    assert d.settle()
    st = d.state()
    assert st.pulse_height == 0 and list(st.stim_pattern[:32]) == [0] * 32  # fail-safe reached the firmware


def test_measure_reply_spanning_several_packets(backend: EmulatedUsbBackend) -> None:
    d = backend.device
    with port_on(backend) as port:
        port.write(encode_electrode_num(255))
        assert d.settle()
        port.write(b"\xff")
        reply = port.read(510)  # 7 full packets and a 62-byte one
        assert len(reply) == 510
        assert list(struct.unpack("<255H", reply)) == list(d.emulator.registers.voltage[:255])
        port.timeout = 0.02
        assert port.read(1) == b""


def test_open_device_by_name_usb_emulator() -> None:
    with open_device("usb-emulator?board=large&switching_boards=2", timeout=0.5) as dev:
        assert dev.hv513_count() == 16
        dev.configure(StimConfig(electrode_count=8))
        assert len(dev.measure()) == 8
    port = open_port("usb-emulator")
    assert isinstance(port, UsbCdcPort) and not port.is_open
    with pytest.raises(ConfigurationError, match="unknown option 'speed'"):
        open_port("usb-emulator?speed=high")


@pytest.mark.parametrize(
    ("name", "vid", "pid", "serial_number"),
    [
        ("usb:303a:1001", 0x303A, 0x1001, None),
        ("usb:303A", 0x303A, None, None),
        ("usb:", 0x303A, None, None),
        ("usb:303a:*:ABC", 0x303A, None, "ABC"),
        ("usb:303a:1001:F4:12:FA:C0:FF:EE", 0x303A, 0x1001, "F4:12:FA:C0:FF:EE"),
    ],
)
def test_usb_names(name: str, vid: int, pid: int | None, serial_number: str | None) -> None:
    spec = UsbDeviceSpec.parse(name)
    assert (spec.vid, spec.pid, spec.serial_number) == (vid, pid, serial_number)
    assert UsbDeviceSpec.parse(spec.name) == spec
    port = open_port(name)
    assert isinstance(port, UsbCdcPort) and port.spec == spec and not port.is_open


@pytest.mark.parametrize("name", ["usb:30g3:1001", "usb:303a:10000", "usb:-1"])
def test_bad_usb_names(name: str) -> None:
    with pytest.raises(ConfigurationError, match="16-bit hexadecimal"):
        open_port(name)


def test_selecting_a_board_by_serial_number() -> None:
    a = EmulatedUsbDevice(serial_number="AA:00:00:00:00:01")
    b = EmulatedUsbDevice("large", 2, serial_number="AA:00:00:00:00:02")
    be = EmulatedUsbBackend([a, b])
    with pytest.raises(
        ConfigurationError, match="2 USB devices match 303a:1001.*AA:00:00:00:00:01.*AA:00:00:00:00:02"
    ):
        port_on(be).open()
    with UsbCdcPort(0x303A, 0x1001, "AA:00:00:00:00:02", backend=be, timeout=0.5) as port:
        port.write(b"\xf5")
        assert port.read(1) == b"\x10"  # the large board with two switching boards: 16 chips
    with pytest.raises(
        TransportError, match="serial numbers present: AA:00:00:00:00:01, AA:00:00:00:00:02"
    ) as ei:
        UsbCdcPort(0x303A, 0x1001, "BB", backend=be).open()
    assert ei.value.code == errno.ENODEV


# --- line state ------------------------------------------------------------------------------------


def test_rts_without_dtr_resets_the_chip_which_is_why_both_start_low(backend: EmulatedUsbBackend) -> None:
    d = backend.device
    with port_on(backend) as port:
        port.write(encode_electrode_num(12) + encode_pulse_height(7))
        assert d.settle()
        assert d.state().electrode_num == 12 and d.resets == 0
        port.rts = True  # held in reset
        port.rts = False  # released with DTR low: the application boots again
        assert d.resets == 1 and not d.download_mode
        assert d.state().electrode_num == 0 and d.state().pulse_height == 0  # power-on state
        port.write(b"\xf5")
        assert port.read(1) == b"\x04"


def test_baudrate_change_resends_line_coding(backend: EmulatedUsbBackend) -> None:
    with port_on(backend) as port:
        port.baudrate = 115_200
        assert backend.device.line_rate == 115_200
        with pytest.raises(ConfigurationError, match="baudrate"):
            port.baudrate = 0


# --- reads, writes, timeouts ------------------------------------------------------------------------


def test_read_timeout_returns_what_arrived(backend: EmulatedUsbBackend) -> None:
    with port_on(backend, timeout=0.03) as port:
        t = time.monotonic()
        assert port.read(4) == b""
        assert time.monotonic() - t >= 0.03
        port.write(b"\xf5")
        assert port.read(4) == b"\x04"  # one byte came, the rest timed out
        port.timeout = 0
        assert port.read(1) == b""  # polls once
        port.write(b"\xf5")
        deadline = time.monotonic() + 1
        while port.in_waiting == 0 and time.monotonic() < deadline:
            pass
        assert port.in_waiting == 1 and port.read(1) == b"\x04"
        assert port.out_waiting == 0


def test_reset_input_buffer_drops_packets_already_sent(backend: EmulatedUsbBackend) -> None:
    with port_on(backend) as port:
        port.write(b"\xf5")
        time.sleep(0.01)  # the reply is on the host side of the link now
        port.reset_input_buffer()
        port.timeout = 0.02
        assert port.read(1) == b""


def test_write_timeout_becomes_device_timeout_in_the_driver(backend: EmulatedUsbBackend) -> None:
    dev = EtactileKitDevice(port_on(backend, timeout=0.05, write_timeout=0.05))
    backend.device.nak_out = True  # firmware no longer takes data
    with pytest.raises(DeviceTimeoutError, match="timed out"):
        dev.hv513_count()
    with pytest.raises(serial.SerialTimeoutException, match="0 of 1 byte"):
        dev.port.write(b"\xf5")
    backend.device.nak_out = False
    dev.close()


def test_io_on_a_closed_port(backend: EmulatedUsbBackend) -> None:
    port = port_on(backend)
    with pytest.raises(PortNotOpenError):
        port.write(b"\xff")
    with pytest.raises(PortNotOpenError):
        port.read(1)
    port.open()
    with pytest.raises(TransportError, match="already open"):
        port.open()
    port.close()


# --- unplug ------------------------------------------------------------------------------------------


def test_unplug_mid_session(backend: EmulatedUsbBackend) -> None:
    d = backend.device
    dev = EtactileKitDevice(port_on(backend))
    dev.configure(StimConfig(electrode_count=32, current_ua=300))
    dev.send_pattern([1] * 32)
    backend.unplug()
    with pytest.raises(DeviceGoneError, match="is gone .*unplugged.*configure it again") as ei:
        dev.send_pattern([0] * 32)
    assert ei.value.code == errno.ENODEV
    with pytest.raises(DeviceGoneError):  # every later call says the same, without touching libusb
        dev.measure()
    # close() on a configured device whose board is gone: the all-off cannot be confirmed, so it raises,
    # having released the port; a second close() is silent
    with pytest.raises(DeviceGoneError, match="is gone"):
        dev.close()
    assert dev.closed and not dev.port.is_open and dev.port.usb_device is None
    dev.close()
    # plugged back in: a powered-up board on a new address, cdc_acm bound again, opens as new
    backend.replug()
    assert d.kernel_bound == {0, 1}
    with EtactileKitDevice(port_on(backend)) as dev2:
        assert dev2.hv513_count() == 4
        assert d.state().electrode_num == 0


def test_unplug_during_a_blocking_read(backend: EmulatedUsbBackend) -> None:
    with port_on(backend, timeout=5.0) as port:
        timer = threading.Timer(0.05, backend.unplug)
        timer.start()
        t = time.monotonic()
        with pytest.raises(DeviceGoneError):
            port.read(1)
        assert time.monotonic() - t < 2.0
        timer.join()


def test_unplug_mid_write(backend: EmulatedUsbBackend) -> None:
    dev = EtactileKitDevice(port_on(backend))
    backend.device.unplug_after(out_bytes=3)  # the resync's first request never leaves whole
    with pytest.raises(DeviceGoneError):
        dev.resync()
    dev.close()  # never configured: there is no all-off to send, so closing a gone board is silent
    assert dev.closed and not dev.port.is_open and dev.port.usb_device is None


def test_port_close_after_an_unplug_never_raises_and_releases(backend: EmulatedUsbBackend) -> None:
    d = backend.device
    port = port_on(backend)
    port.open()
    backend.unplug()
    port.close()  # nothing to reach: released all the same
    assert not port.is_open and port.usb_device is None
    port.close()
    with pytest.raises(PortNotOpenError):
        port.write(b"\xff")
    backend.replug()
    assert d.kernel_bound == {0, 1}  # the kernel's driver is bound to the new device


# --- stalled endpoints ---------------------------------------------------------------------------------


def test_stalled_out_endpoint_is_cleared_and_the_packet_sent_once(backend: EmulatedUsbBackend) -> None:
    d = backend.device
    with port_on(backend) as port:
        d.halt(0x01)
        port.write(encode_electrode_num(5))
        assert port.stalls_cleared == 1 and 0x01 not in d.halted
        assert d.settle()
        assert d.state().electrode_num == 5 and d.bytes_accepted == 2  # neither lost nor doubled


def test_stalled_in_endpoint_is_cleared_and_the_reply_read(backend: EmulatedUsbBackend) -> None:
    d = backend.device
    with port_on(backend) as port:
        port.write(encode_electrode_num(3))
        d.halt(0x81)
        port.write(b"\xff")
        assert port.read(6) == bytes(6)
        assert port.stalls_cleared == 1


def test_endpoint_that_keeps_stalling_is_reported(backend: EmulatedUsbBackend) -> None:
    d = backend.device
    dev = EtactileKitDevice(port_on(backend))
    d.halt(0x01, sticky=True)
    with pytest.raises(TransportError, match=r"bulk OUT endpoint 0x01 .* stalled again .*resync\(\)") as ei:
        dev.hv513_count()
    assert not isinstance(ei.value, DeviceGoneError) and ei.value.code == errno.EPIPE
    d.sticky_halts.clear()
    d.halted.clear()
    dev.close()
    d.halt(0x81, sticky=True)
    with port_on(backend) as port:
        port.write(b"\xf5")
        with pytest.raises(TransportError, match="bulk IN endpoint 0x81 .* stalled again"):
            port.read(1)


# --- error messages --------------------------------------------------------------------------------


def test_no_backend_says_which_package_installs_libusb(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(usb_transport, "default_backend", lambda: None)
    with pytest.raises(TransportError) as ei:
        open_device("usb:303a:1001")
    msg = str(ei.value)
    for needle in ("libusb-1.0-0", "brew install libusb", "pip install libusb-package", "/dev/ttyACM0"):
        assert needle in msg


def test_no_backend_on_this_machine_is_reported_not_crashed() -> None:
    if usb_transport.default_backend() is not None:
        pytest.skip("libusb is installed here; the no-backend path is covered with a patched lookup")
    with pytest.raises(TransportError, match="libusb-1.0-0"):
        UsbCdcPort().open()


def test_missing_pyusb_names_the_extra(monkeypatch: pytest.MonkeyPatch) -> None:
    for mod in [m for m in sys.modules if m == "usb" or m.startswith("usb.")]:
        monkeypatch.setitem(sys.modules, mod, None)
    monkeypatch.setitem(sys.modules, "usb", None)
    with pytest.raises(MissingDependencyError, match=re.escape(install_command("usb"))) as ei:
        open_port("usb:303a:1001")
    assert ei.value.package == "pyusb" and ei.value.extra == "usb"
    with pytest.raises(MissingDependencyError):
        EmulatedUsbBackend()


def test_no_device_attached() -> None:
    be = EmulatedUsbBackend([])
    with pytest.raises(TransportError, match="no USB device 303a:1001 is attached.*data cable") as ei:
        EtactileKitDevice(port_on(be))
    assert ei.value.code == errno.ENODEV


def test_access_denied_says_which_permission() -> None:
    be = EmulatedUsbBackend([EmulatedUsbDevice(access_denied=True)])
    with pytest.raises(TransportError) as ei:
        EtactileKitDevice(port_on(be))
    msg = str(ei.value)
    assert msg.startswith("access denied to USB device 303a:1001")
    for needle in ('ATTR{idVendor}=="303a"', "plugdev", "udevadm", "WinUSB"):
        assert needle in msg
    assert ei.value.code == errno.EACCES
    with pytest.raises(TransportError, match="access denied: cannot read the serial number.*plugdev"):
        UsbCdcPort(0x303A, 0x1001, "F4:12:FA:C0:FF:EE", backend=be).open()


def test_interface_held_by_another_program(backend: EmulatedUsbBackend) -> None:
    with port_on(backend) as first:
        with pytest.raises(
            DeviceBusyError, match="in use by another program.*another program holds it"
        ) as ei:
            port_on(backend).open()
        assert ei.value.code == errno.EBUSY
        assert str(ei.value).endswith("nothing was written to it")
        first.write(b"\xf5")  # the first session is untouched
        assert first.read(1) == b"\x04"


def test_data_endpoints_must_be_bulk() -> None:
    interfaces = esp32s3_interfaces()
    interfaces[1].endpoints[1].bmAttributes = EP_INTERRUPT
    be = EmulatedUsbBackend([EmulatedUsbDevice(interfaces=interfaces)])
    with pytest.raises(
        TransportError, match="endpoint 0x81 of the CDC data interface 1 is interrupt, not bulk"
    ):
        port_on(be).open()
    assert be.device.kernel_bound == {0, 1} and be.device.claims == {}  # a failed open gives everything back


def test_device_without_cdc_data_interface() -> None:
    interfaces = [i for i in esp32s3_interfaces() if i.bInterfaceNumber == 2]
    be = EmulatedUsbBackend([EmulatedUsbDevice(interfaces=interfaces)])
    with pytest.raises(TransportError, match="no CDC data interface"):
        port_on(be).open()
