"""The emulated USB device seen through pyusb itself, in simulated time: descriptors, class requests and
the full-speed link's packets, frames and receive queue against the firmware's 1 ms parser rhythm."""

from __future__ import annotations

import errno

import pytest

usb_core = pytest.importorskip("usb.core", reason="the emulated USB device needs pyusb")
import usb.util  # noqa: E402

from tactdeform_hw.emulator import HazardKind  # noqa: E402
from tactdeform_hw.emulator.serving.usb_backend import (  # noqa: E402
    EmulatedUsbBackend,
    EmulatedUsbDevice,
    VirtualClock,
    backend_from_name,
)
from tactdeform_hw.emulator.timed.link import UsbFsLink  # noqa: E402
from tactdeform_hw.emulator.timed.timing import TimingModel  # noqa: E402
from tactdeform_hw.errors import ConfigurationError  # noqa: E402


@pytest.fixture
def bus() -> tuple[VirtualClock, EmulatedUsbBackend, usb_core.Device]:
    clock = VirtualClock()
    be = EmulatedUsbBackend(clock=clock)
    dev = usb_core.find(idVendor=0x303A, idProduct=0x1001, backend=be)
    assert dev is not None
    for n in (0, 1):
        dev.detach_kernel_driver(n)
    return clock, be, dev


def test_pyusb_sees_an_esp32s3_usb_serial_jtag(
    bus: tuple[VirtualClock, EmulatedUsbBackend, usb_core.Device],
) -> None:
    _, _, dev = bus
    assert (dev.idVendor, dev.idProduct, dev.bDeviceClass, dev.speed) == (
        0x303A,
        0x1001,
        0xEF,
        usb.util.SPEED_FULL,
    )
    assert (dev.manufacturer, dev.product, dev.serial_number) == (
        "Espressif",
        "USB JTAG/serial debug unit",
        "F4:12:FA:C0:FF:EE",
    )
    cfg = dev.get_active_configuration()
    layout = [
        (
            i.bInterfaceNumber,
            i.bInterfaceClass,
            [(e.bEndpointAddress, usb.util.endpoint_type(e.bmAttributes)) for e in i],
        )
        for i in cfg
    ]
    assert layout == [
        (0, 0x02, [(0x82, usb.util.ENDPOINT_TYPE_INTR)]),
        (1, 0x0A, [(0x01, usb.util.ENDPOINT_TYPE_BULK), (0x81, usb.util.ENDPOINT_TYPE_BULK)]),
        (2, 0xFF, [(0x02, usb.util.ENDPOINT_TYPE_BULK), (0x83, usb.util.ENDPOINT_TYPE_BULK)]),
    ]
    assert cfg.wTotalLength == 9 + 3 * 9 + 5 * 7 + 19  # configuration, interfaces, endpoints, CDC functional


def test_cdc_class_requests_and_unsupported_ones_stall(
    bus: tuple[VirtualClock, EmulatedUsbBackend, usb_core.Device],
) -> None:
    _, be, dev = bus
    coding = bytes.fromhex("00100e00000008")  # 921600, 1 stop bit, no parity, 8 bits
    assert dev.ctrl_transfer(0x21, 0x20, 0, 0, coding) == 7
    assert bytes(dev.ctrl_transfer(0xA1, 0x21, 0, 0, 7)) == coding
    assert be.device.line_rate == 921_600
    with pytest.raises(usb_core.USBError) as ei:
        dev.ctrl_transfer(0x21, 0x7F, 0, 0, None)
    assert ei.value.errno == errno.EPIPE


def test_claim_needs_the_kernel_driver_detached() -> None:
    be = EmulatedUsbBackend(clock=VirtualClock())
    dev = usb_core.find(idVendor=0x303A, backend=be)
    assert dev.is_kernel_driver_active(1)
    with pytest.raises(usb_core.USBError) as ei:
        usb.util.claim_interface(dev, 1)
    assert ei.value.errno == errno.EBUSY
    dev.detach_kernel_driver(1)
    usb.util.claim_interface(dev, 1)
    with pytest.raises(usb_core.USBError):
        dev.attach_kernel_driver(1)  # not while claimed
    usb.util.release_interface(dev, 1)
    dev.attach_kernel_driver(1)
    assert be.device.kernel_bound == {0, 1}


def test_measure_round_trip_is_frames_plus_the_tick_wait(
    bus: tuple[VirtualClock, EmulatedUsbBackend, usb_core.Device],
) -> None:
    clock, be, dev = bus
    d = be.device
    tick_phase_us = d.timed.model.tick_phase_us
    dev.write(0x01, b"\xfc\x20")  # 32 electrodes
    clock.advance(0.0052)
    t_write = d.now_us()
    dev.write(0x01, b"\xff")
    reply = dev.read(0x81, 64, 100)
    assert len(reply) == 64
    t_host = d.now_us()
    measure = [r for r in d.timed.commands if r.name == "MEASURE"][-1]
    assert 6000 <= measure.arrival_us < 6100  # in the next frame
    assert 7000 + tick_phase_us <= measure.effect_us < 7100 + tick_phase_us  # read at the next RTOS tick
    assert 8000 < measure.reply_us <= t_host < 8400  # back in the frame after that, where the host polls
    assert 2000 < t_host - t_write < 3250


def test_one_command_with_a_payload_per_tick(
    bus: tuple[VirtualClock, EmulatedUsbBackend, usb_core.Device],
) -> None:
    clock, be, dev = bus
    d = be.device
    dev.write(0x01, b"\xfc\x04")
    assert d.settle()
    clock.advance(0.0003)
    k = 20
    dev.write(0x01, b"\xf7\x2d" * k + b"\xff")  # 20 discharge commands, then a measure request
    assert len(dev.read(0x81, 64, 100)) == 8
    reports = [r for r in d.timed.commands if r.name in ("DISCHARGE", "MEASURE")]
    effects = [r.effect_us for r in reports]
    assert len(effects) == k + 1
    first = effects[0] - effects[0] % 1000  # the tick that read the first command
    for i, t in enumerate(effects):
        # one RTOS tick each; a tick that falls inside a scan waits for the scan to end (< 300 µs here)
        assert first + 1000 * i <= t < first + 1000 * i + 300, (i, effects)
    assert d.state().discharge_time_us == 0x2D


def test_unknown_bytes_cost_no_tick(bus: tuple[VirtualClock, EmulatedUsbBackend, usb_core.Device]) -> None:
    clock, be, dev = bus
    d = be.device
    dev.write(0x01, b"\xfc\x04")
    assert d.settle()
    t_write = d.now_us()
    dev.write(0x01, bytes(200) + b"\xff")  # four packets in one frame; 200 ignored bytes
    dev.read(0x81, 64, 100)
    measure = [r for r in d.timed.commands if r.name == "MEASURE"][-1]
    assert measure.reply_us - t_write < 3500


def test_half_received_u16_spins_until_the_second_byte(
    bus: tuple[VirtualClock, EmulatedUsbBackend, usb_core.Device],
) -> None:
    clock, be, dev = bus
    d = be.device
    dev.write(0x01, b"\xfb\x10")  # pulse height, low byte only
    assert d.settle()
    assert d.state().rx_pending == 1 and d.state().pulse_height == 0
    clock.advance(0.0104)
    dev.write(0x01, b"\x00")
    clock.advance(0.0012)  # into the next frame: delivered, and read at once (no tick to wait for)
    assert d.state().pulse_height == 16 and d.state().rx_pending == 0
    height = [r for r in d.timed.commands if r.name == "PULSE_HEIGHT"][-1]
    assert 11000 <= height.arrival_us <= height.effect_us < height.arrival_us + 300


def test_a_burst_overflows_the_receive_queue_and_each_loss_is_reported(
    bus: tuple[VirtualClock, EmulatedUsbBackend, usb_core.Device],
) -> None:
    _, be, dev = bus
    d = be.device
    dev.write(0x01, b"\xfc\x20")
    assert d.settle()
    dev.write(0x01, (b"\xfe" + bytes([1]) * 32) * 10)  # 330 bytes, six packets in one frame
    assert d.settle()
    losses = [lo for lo in d.timed.losses if lo.reason == "queue_full"]
    assert [lo.count for lo in losses] == [64, 10]  # the queue took 256 bytes, no more
    hazards = [h for h in d.emulator.hazards if h.kind is HazardKind.QUEUE_OVERFLOW]
    assert len(hazards) == 2 and all(h.time_us is not None for h in hazards)
    assert d.bytes_accepted == 2 + 330


def test_packets_per_frame_cap_spreads_a_burst() -> None:
    clock = VirtualClock()
    d = EmulatedUsbDevice(link=UsbFsLink(max_packets_per_frame=1))
    be = EmulatedUsbBackend([d], clock=clock)
    dev = usb_core.find(idVendor=0x303A, backend=be)
    dev.detach_kernel_driver(1)
    dev.write(0x01, bytes(300))  # five packets, one per frame: the parser keeps up
    assert d.settle()
    assert d.timed.losses == [] and d.state().rx_pending == 0


def test_locked_parser_fills_the_queue_then_loses_everything(
    bus: tuple[VirtualClock, EmulatedUsbBackend, usb_core.Device],
) -> None:
    _, be, dev = bus
    d = be.device
    dev.write(0x01, b"\xfe")  # pattern with electrode_num 0: the parser never reads again
    assert d.settle()
    assert d.emulator.locked
    for _ in range(5):
        dev.write(0x01, b"\xf5" * 64)
    assert d.settle()
    assert d.state().rx_pending == 256
    assert sum(lo.count for lo in d.timed.losses) == 5 * 64 - 256
    with pytest.raises(usb_core.USBTimeoutError):
        dev.read(0x81, 64, 20)  # no HV513 count ever comes back


def test_rts_reset_and_download_mode(bus: tuple[VirtualClock, EmulatedUsbBackend, usb_core.Device]) -> None:
    _, be, dev = bus
    d = be.device
    dev.ctrl_transfer(0x21, 0x22, 0b10, 0, None)  # RTS, no DTR: reset held
    dev.ctrl_transfer(0x21, 0x22, 0b01, 0, None)  # released with DTR high: ROM download mode
    assert d.resets == 1 and d.download_mode
    dev.write(0x01, b"\xf5")
    with pytest.raises(usb_core.USBTimeoutError):
        dev.read(0x81, 64, 20)  # no application runs
    dev.ctrl_transfer(0x21, 0x22, 0b10, 0, None)
    dev.ctrl_transfer(0x21, 0x22, 0b00, 0, None)  # released with DTR low: the application boots
    assert d.resets == 2 and not d.download_mode
    dev.write(0x01, b"\xf5")
    assert bytes(dev.read(0x81, 64, 50)) == b"\x04"


def test_timing_comes_from_the_shared_models() -> None:
    clock = VirtualClock()
    d = EmulatedUsbDevice(timing=TimingModel(tick_phase_us=250.0))
    be = EmulatedUsbBackend([d], clock=clock)
    dev = usb_core.find(idVendor=0x303A, backend=be)
    dev.detach_kernel_driver(1)
    dev.write(0x01, b"\xfc\x02\xff")
    dev.read(0x81, 64, 100)
    measure = [r for r in d.timed.commands if r.name == "MEASURE"][-1]
    assert (measure.effect_us - 250.0) % 1000 < 20  # the request was read on a 250 µs-phase tick


def test_names_and_faults_are_checked() -> None:
    with pytest.raises(ConfigurationError, match="unknown option"):
        backend_from_name("usb-emulator?x=1")
    with pytest.raises(ConfigurationError, match="switching_boards"):
        backend_from_name("usb-emulator?switching_boards=two")
    be = backend_from_name("usb-emulator?board=large&serial=XYZ&kernel_driver=0")
    assert be.device.serial_number == "XYZ" and be.device.kernel_bound == set()
    with pytest.raises(ConfigurationError, match="endpoint=0x05"):
        be.device.halt(0x05)
    with pytest.raises(ConfigurationError, match="out_bytes"):
        be.device.unplug_after(-1)
    with pytest.raises(ConfigurationError, match="no device"):
        _ = EmulatedUsbBackend([]).device
