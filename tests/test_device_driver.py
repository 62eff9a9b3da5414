"""The driver: configuration order, refusals that write nothing, all-off on close, typed errors."""

from __future__ import annotations

import pytest

from tactdeform_hw.device import ChannelMapping, EtactileKitDevice, StimConfig, open_device
from tactdeform_hw.device.driver.base import LinkState
from tactdeform_hw.device.driver.dialects import DIALECTS
from tactdeform_hw.device.driver.firmware_probe import UnidentifiedBoardError
from tactdeform_hw.device.driver.v2 import buffer_levels
from tactdeform_hw.emulator import Emulator
from tactdeform_hw.errors import (
    ConfigurationError,
    DeviceGoneError,
    LimitError,
    ProtocolError,
    ShortReplyError,
    TransportError,
)
from tactdeform_hw.protocol.decoder import OK, decode
from tactdeform_hw.protocol.firmware import FIRMWARES

from . import safety_helpers

#: Every firmware version the driver speaks, by name: the tests of behaviour that does not depend on the
#: version run once per entry (a version added to the registry is held to them too).
EVERY_FIRMWARE = pytest.mark.parametrize("firmware", list(FIRMWARES))


class RecordingPort(safety_helpers.RecordingPort):
    """An in-process port that records every write and the line states at open."""

    def __init__(self, emulator: Emulator | None = None, **kw: object) -> None:
        super().__init__(emulator, **kw)
        self.lines_at_open: tuple[bool, bool] | None = None
        self.dtr = True  # pyserial's default would assert both lines
        self.rts = True

    def open(self) -> None:
        self.lines_at_open = (self.dtr, self.rts)
        super().open()


@pytest.fixture
def port() -> RecordingPort:
    return RecordingPort()


@pytest.fixture
def dev(port: RecordingPort) -> EtactileKitDevice:
    d = EtactileKitDevice(port)
    port.writes.clear()  # the proof at open (zeros, 0xF5, heights 0): the tests look at what follows
    return d


@EVERY_FIRMWARE
def test_lines_are_low_before_open(firmware: str) -> None:
    port = RecordingPort(Emulator(firmware=firmware))
    dev = EtactileKitDevice(port)
    assert dev.dialect is DIALECTS[FIRMWARES[firmware]]
    dev.close()
    assert port.lines_at_open == (False, False)


def test_configure_then_pattern_reaches_the_firmware(dev: EtactileKitDevice, port: RecordingPort) -> None:
    dev.configure(StimConfig(current_ua=1500, rate_hz=125, discharge_us=45))
    dev.send_pattern([1] * 16 + [0] * 15 + [2])
    s = port.emulator.state()
    assert s.electrode_num == 32 and s.pulse_height == 150 and s.pulse_width_us == 200
    assert s.discharge_time_us == 45 and s.period_us == 8000.0 and s.polarity == 1
    assert list(s.stim_pattern[:32]) == [1] * 16 + [0] * 15 + [2]
    assert safety_helpers.defects(port.emulator.hazards) == []  # the driver triggers no defect
    # one write per command, each a whole command
    for w in port.writes:
        assert all(i.status == OK for i in decode(w, 32))
    assert port.writes[-1] == bytes([0xFE] + [1] * 16 + [0] * 15 + [2])


def test_configure_order_never_stimulates_half_set(dev: EtactileKitDevice, port: RecordingPort) -> None:
    dev.configure(StimConfig(current_ua=1000))
    # the board's timing was unknown: the new rate is proved in force (0xFF) before anything is paced by it
    assert port.writes[-1] == b"\xff"
    writes = [w for w in port.writes if w not in (b"\xff", b"\xf5")]
    names = [decode(w, 32)[0].name for w in writes]
    assert names[0] == "PULSE_HEIGHT" and writes[0] == b"\xfb\x00\x00"
    assert names.index("ELECTRODE_NUM") + 1 == names.index("PATTERN")
    assert names[-1] == "PULSE_HEIGHT"


@EVERY_FIRMWARE
def test_reconfiguring_clears_stale_channels(firmware: str) -> None:
    port = RecordingPort(Emulator(firmware=firmware))
    dev = EtactileKitDevice(port)
    dev.configure(StimConfig(electrode_count=8, current_ua=100))
    dev.send_pattern([1] * 8)
    assert buffer_levels(port.emulator.state())[:8] == [1] * 8
    dev.configure(StimConfig(electrode_count=4, current_ua=100))
    dev.configure(StimConfig(electrode_count=8, current_ua=100))
    assert buffer_levels(port.emulator.state())[:8] == [0] * 8
    assert safety_helpers.defects(port.emulator.hazards) == []


def test_a_sense_current_v12_cannot_encode_is_refused_before_a_byte(
    dev: EtactileKitDevice, port: RecordingPort
) -> None:
    """v1.2 stores 0xF9 shifted: 30 µA is no sense height it can hold (the refusals both versions share
    are in ``test_device_dialects.py``)."""
    with pytest.raises(LimitError, match="sense_current_ua"):
        dev.configure(StimConfig(sense_current_ua=30))
    assert port.writes == []


def test_mapping_validation() -> None:
    with pytest.raises(ConfigurationError, match="second electrode"):
        ChannelMapping((0, 1, 1), 3)
    with pytest.raises(LimitError, match=r"mapping\[1\]"):
        ChannelMapping((0, 5), 3)


class SilentPort(RecordingPort):
    """Answers one byte where more were asked for and nothing to a one-byte request, once ``silent``."""

    silent = True

    def read(self, size: int = 1) -> bytes:
        if not self.silent:
            return super().read(size)
        return b"\x01"[: min(size, 1)] if size > 1 else b""


def test_a_board_that_never_answers_as_a_firmware_is_refused_at_open() -> None:
    port = SilentPort()
    with pytest.raises(UnidentifiedBoardError, match="answered 01"):
        EtactileKitDevice(port)
    # nothing but the identification's off bytes was written, and the port was let go
    assert set(b"".join(port.writes)) <= {0x00, 0xFC, 0xFB, 0xF9, 0xF5, 0xF4} and not port.is_open


@EVERY_FIRMWARE
def test_short_reply_is_typed(firmware: str) -> None:
    port = SilentPort(Emulator(firmware=firmware))
    port.silent = False
    dev = EtactileKitDevice(port)
    port.silent = True
    with pytest.raises(ShortReplyError, match="hv513_count: expected a 1-byte reply, got 0"):
        dev.hv513_count()
    assert dev.needs_resync
    with pytest.raises(ProtocolError):
        dev.configure(StimConfig(electrode_count=4))
    assert dev.needs_resync and port.emulator.state().electrode_num == 0  # no configuration went out


@EVERY_FIRMWARE
def test_a_board_silent_after_a_short_reply_fails_configure_with_a_short_reply(firmware: str) -> None:
    """docs/safety.md: a board that does not answer the recovery stays marked for it, and ``configure``
    raises :class:`ShortReplyError`, so the caller knows nothing went out."""
    port = SilentPort(Emulator(firmware=firmware))
    port.silent = False
    dev = EtactileKitDevice(port)
    port.silent = True
    with pytest.raises(ShortReplyError):
        dev.hv513_count()
    with pytest.raises(ShortReplyError):
        dev.configure(StimConfig(electrode_count=4))


class ShortMeasurePort(RecordingPort):
    """Once ``short`` is set, every reply comes back at most one byte long."""

    short = False

    def read(self, size: int = 1) -> bytes:
        return super().read(min(size, 1) if self.short else size)


@EVERY_FIRMWARE
def test_short_measure_reply_is_typed_and_marks_a_resync(firmware: str) -> None:
    """A short reply proves nothing: the next command is preceded by a resync.  Whether that resync can
    pass on a port that cuts every reply to one byte is the version's: v1.2 proves the boundary by a
    measure (2 bytes per electrode), v2 by the sync check (one byte)."""
    port = ShortMeasurePort(Emulator(firmware=firmware))
    dev = EtactileKitDevice(port)
    dev.configure(StimConfig(electrode_count=4))
    port.short = True
    with pytest.raises(ShortReplyError, match="expected a 8-byte reply, got 1"):
        dev.measure()
    assert dev.needs_resync
    seen = len(dev.transitions)
    try:
        dev.hv513_count()
    except ShortReplyError as exc:
        assert "after resync" in str(exc)
    assert LinkState.SYNCING.value in [new for _, _, new, _ in list(dev.transitions)[seen:]]


class BrokenPort(RecordingPort):
    def write(self, data: bytes) -> int:
        raise OSError(5, "Input/output error")


def test_transport_failures_are_typed() -> None:
    port = BrokenPort()
    with pytest.raises(DeviceGoneError) as err:
        EtactileKitDevice(port)
    assert isinstance(err.value.__cause__, OSError) and not port.is_open


@EVERY_FIRMWARE
def test_resync_recovers_a_desynchronised_parser(firmware: str) -> None:
    """A pattern cut short by a fault on the link, then two stray bytes: after the resync the board holds
    what a board that never lost step holds, for the configuration and then for a frame."""
    port, twin = (RecordingPort(Emulator(firmware=firmware)) for _ in range(2))
    dev, ref = EtactileKitDevice(port), EtactileKitDevice(twin)
    for d in (dev, ref):
        d.configure(StimConfig(current_ua=300))
    port.emulator.feed(b"\xfe" + b"\x01" * 10)  # a pattern cut short by a fault on the link
    port.emulator.feed(b"\xfb\xdc")  # and a half command
    assert port.emulator.state() != twin.emulator.state()
    dev.resync()
    s = port.emulator.state()
    assert s.rx_pending == 0 and s.electrode_num == 32 and buffer_levels(s)[:32] == [0] * 32
    assert _registers(s) == _registers(twin.emulator.state())
    for d in (dev, ref):
        d.send_pattern([1] * 32)
    assert buffer_levels(port.emulator.state())[:32] == [1] * 32
    assert _registers(port.emulator.state()) == _registers(twin.emulator.state())


def _registers(state: object) -> dict[str, object]:
    """The firmware's variables a scan reads (the receive queue's counters left out)."""
    regs = dict(state.as_dict())  # type: ignore[attr-defined]
    for counter in ("rx_pending", "rx_dropped", "command_in_progress"):
        regs.pop(counter, None)
    return regs


@EVERY_FIRMWARE
def test_open_device_by_url_and_errors(firmware: str) -> None:
    with open_device(f"etactile://?board=large&switching_boards=2&firmware={firmware}") as d:
        assert d.firmware == firmware and d.hv513_count() == 16
    with pytest.raises(TransportError):
        open_device("/dev/does-not-exist-etactile")
    import serial

    with pytest.raises(serial.SerialException, match="unknown option"):
        serial.serial_for_url("etactile://?bogus=1")
