"""What the device promises on the timed model of whatever firmware its board runs: every test here runs
once per dialect of the registry (:data:`~tactdeform_hw.device.driver.dialects.DIALECTS`), and judges the
pulses the emulated board delivered, never the bytes the host meant to send."""

from __future__ import annotations

import itertools

import pytest

from tactdeform_hw.device.driver.base import LinkState
from tactdeform_hw.device.driver.config import StimConfig
from tactdeform_hw.device.driver.dialects import DIALECTS
from tactdeform_hw.device.driver.firmware_probe import FirmwareMismatchError
from tactdeform_hw.device.driver.serial_driver import EtactileKitDevice
from tactdeform_hw.emulator.faults import TimedPort
from tactdeform_hw.emulator.timed.model_v1_2 import TimedEmulator
from tactdeform_hw.emulator.timed.model_v2 import TimedEmulatorV2
from tactdeform_hw.protocol.firmware import V2, FirmwareSpec

SPECS = sorted(DIALECTS, key=lambda spec: spec.name)
LINKS = ["usb", "uart"]


def _timed(spec: FirmwareSpec, link: str = "usb") -> tuple[EtactileKitDevice, TimedPort]:
    """A device on the timed model of ``spec``'s firmware over ``link`` (loss-tolerant encoding)."""
    board = TimedEmulatorV2(link=link) if spec is V2 else TimedEmulator("compact", 1, link=link)
    port = TimedPort(board, link=link)
    dev = EtactileKitDevice(port, firmware=spec.name)
    assert dev.dialect is DIALECTS[spec]
    return dev, port


def _delivered_ua(port: TimedPort, t0_s: float, t1_s: float | None = None) -> list[float]:
    """The current of every pulse with current that the board delivered from ``t0_s`` (to ``t1_s``);
    v1.2 also records the off channels' sense pulses, 0 µA at sense current 0."""
    table = port.emulator.reports.pulse_table(t0_s * 1e6, None if t1_s is None else t1_s * 1e6)
    return [float(v) for v in table["current_ua"] if v > 0]


@pytest.mark.parametrize("spec", SPECS, ids=lambda spec: spec.name)
def test_close_leaves_everything_off_on_the_timed_model(spec: FirmwareSpec) -> None:
    dev, port = _timed(spec)
    dev.configure(StimConfig(electrode_count=16, current_ua=900))
    dev.send_pattern([2] * 16)
    t = port.now_s
    port.advance(0.05)
    assert max(_delivered_ua(port, t)) > 0  # the frame was delivered: the check below can see current
    dev.close()
    t = port.now_s
    port.advance(0.05)
    assert _delivered_ua(port, t) == [] and dev.closed and not port.is_open


@pytest.mark.parametrize("link", LINKS)
@pytest.mark.parametrize("spec", SPECS, ids=lambda spec: spec.name)
def test_a_hung_board_gets_the_reset_line_within_the_resync_bound_and_comes_back(
    spec: FirmwareSpec, link: str
) -> None:
    """A main loop that stopped reading while the board stimulates: the recovery's proofs time out and
    the reset line follows within ``resync_bound_s`` — the figure the fail-safe's recovery bound uses.
    After the scan the reset caught nothing is delivered until a frame asks for it, and that frame is
    delivered again at its current."""
    dev, port = _timed(spec, link)
    dev.configure(StimConfig(electrode_count=32, current_ua=500))
    dev.send_pattern([1] * 32)
    dev.keepalive()
    port.emulator.stop_reading()
    t0 = port.now_s
    dev.resync()  # FAILED, then the reset line, then in step again
    reset_at = next(t for t, _, new, _ in dev.transitions if t >= t0 and new == LinkState.RESETTING.value)
    assert 0 < reset_at - t0 <= dev.resync_bound_s()
    assert dev.link_state is LinkState.IN_STEP and port.line_resets == 1
    port.advance(0.02)
    t = port.now_s
    assert _delivered_ua(port, reset_at + 0.0085, t) == []
    dev.send_pattern([1] * 32)
    port.advance(0.05)
    assert max(_delivered_ua(port, t)) == pytest.approx(500, abs=25)
    dev.close()


@pytest.mark.parametrize(
    ("board", "driver"), list(itertools.permutations(SPECS, 2)), ids=lambda spec: spec.name
)
def test_a_driver_told_another_version_is_refused_and_stops_the_board(
    board: FirmwareSpec, driver: FirmwareSpec
) -> None:
    """A board left stimulating by a session of its own version that never closed (killed), then a driver
    told another version: the identification proves the board's own, the refusal is typed and names both,
    the port is let go, and the board delivers nothing any more (its bytes stop current on every version)."""
    earlier, port = _timed(board)
    earlier.configure(StimConfig(electrode_count=8, current_ua=800))
    earlier.send_pattern([1] * 8)
    port.advance(0.03)
    assert max(_delivered_ua(port, port.now_s - 0.02)) == pytest.approx(800, abs=25)
    with pytest.raises(FirmwareMismatchError, match=f"runs firmware {board.name}.*firmware='{driver.name}'"):
        EtactileKitDevice(port, firmware=driver.name)
    assert not port.is_open
    t = port.now_s
    port.advance(0.05)
    assert _delivered_ua(port, t) == [] and port.emulator.state().electrode_num == 0


@pytest.mark.parametrize("link", LINKS)
def test_v1_2_a_measure_reply_longer_than_the_hosts_count_is_no_proof(link: str) -> None:
    """A board whose electrode count is larger than the host believes (bytes another writer sent, or a
    lost packet tail that made a pattern swallow the count) answers 0xFF for every channel it scans.  The
    proof reads the whole reply: one longer than the host's count is a mismatch, not a proof, so ``close``
    recovers and switches the board off, judged on the pulses it delivered after the close."""
    from tactdeform_hw import protocol as p
    from tactdeform_hw.errors import LongReplyError
    from tactdeform_hw.protocol.firmware import V1_2

    dev, port = _timed(V1_2, link)
    dev.configure(StimConfig(electrode_count=1, current_ua=900))
    dev.send_pattern([0])
    port.advance(0.05)
    # behind the host's back: the count 32 and the odd channels stimulating at the height in force
    port.write(p.encode_pulse_height(90) + p.encode_electrode_num(32))
    port.write(p.encode_pattern(bytes([0, 1] * 16), electrode_num=32))
    port.advance(0.05)
    t = port.now_s
    port.advance(0.05)
    assert max(_delivered_ua(port, t)) > 0  # the odd channels are on: the check below can see them
    with pytest.raises(LongReplyError, match="expected a 2-byte reply, got 64 byte"):
        dev.measure()  # a proof in step: the longer reply is reported, the link suspect
    assert any("longer than 2 bytes" in why for _, _, _, why in dev.transitions)
    assert dev.probe() is False
    dev.close()
    t = port.now_s
    port.advance(0.05)
    assert _delivered_ua(port, t) == [] and port.emulator.registers.electrode_num in (0, 1)
