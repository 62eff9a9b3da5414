"""What the device promises on the timed model of whatever firmware its board runs: every test here runs
once per dialect of the registry (:data:`~tactdeform_hw.device.driver.dialects.DIALECTS`), and judges the
pulses the emulated board delivered, never the bytes the host meant to send."""

from __future__ import annotations

import pytest

from tactdeform_hw.device.driver.config import StimConfig
from tactdeform_hw.device.driver.dialects import DIALECTS
from tactdeform_hw.device.driver.serial_driver import EtactileKitDevice
from tactdeform_hw.emulator.faults import TimedPort
from tactdeform_hw.emulator.timed.model_v1_2 import TimedEmulator
from tactdeform_hw.protocol.firmware import V2, FirmwareSpec

from .test_v2_driver import V2Board

SPECS = sorted(DIALECTS, key=lambda spec: spec.name)


@pytest.fixture(params=SPECS, ids=lambda spec: spec.name)
def timed(request: pytest.FixtureRequest) -> tuple[EtactileKitDevice, TimedPort]:
    """A device on the timed model of the dialect's firmware (USB link, plain encoding)."""
    spec: FirmwareSpec = request.param
    board = V2Board() if spec is V2 else TimedEmulator("compact", 1, link="usb")
    port = TimedPort(board, link="usb")  # type: ignore[arg-type]
    dev = EtactileKitDevice(port, firmware=spec.name)
    assert dev.dialect is DIALECTS[spec]
    return dev, port


def _delivered_ua(port: TimedPort, since_s: float) -> list[float]:
    """The current of every pulse with current that the board delivered since ``since_s`` (v1.2 also
    records the off channels' sense pulses, 0 µA at sense current 0)."""
    table = port.emulator.reports.pulse_table(since_s * 1e6)
    return [float(v) for v in table["current_ua"] if v > 0]


def test_close_leaves_everything_off_on_the_timed_model(timed: tuple[EtactileKitDevice, TimedPort]) -> None:
    dev, port = timed
    dev.configure(StimConfig(electrode_count=16, current_ua=900))
    dev.send_pattern([2] * 16)
    t = port.now_s
    port.advance(0.05)
    assert max(_delivered_ua(port, t)) > 0  # the frame was delivered: the check below can see current
    dev.close()
    t = port.now_s
    port.advance(0.05)
    assert _delivered_ua(port, t) == [] and dev.closed and not port.is_open
