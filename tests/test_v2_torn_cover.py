"""No torn pattern on firmware v2: every pattern that may differ from the one in force is copied while mode
2 at sense height 0 is in force (the cover), so a scan that pre-empts the copy delivers no current
instead of part old, part new heights."""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Any

import pytest

from tactdeform_hw.clock import SimulatedClock
from tactdeform_hw.device.driver.config import StimConfig
from tactdeform_hw.device.driver.pacing import Pacer, PacingPolicy
from tactdeform_hw.device.driver.v2 import covered_pattern
from tactdeform_hw.emulator import HazardKind
from tactdeform_hw.emulator.timed.model_v2 import TimedEmulatorV2
from tactdeform_hw.protocol.commands import V2_COMMANDS as c2
from tactdeform_hw.protocol.firmware import V2, OpcodeV2

from .test_v2_driver import _timed_v2

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tools"))
import safety_campaign as sc  # noqa: E402

N = 16


def _recorded_writes(monkeypatch: pytest.MonkeyPatch, port: Any) -> list[bytes]:
    """Every write the driver makes to ``port`` from now on, in order (each still reaches the board)."""
    writes: list[bytes] = []
    inner = port.write

    def spy(data: bytes) -> int:
        writes.append(bytes(data))
        return int(inner(data))

    monkeypatch.setattr(port, "write", spy)
    return writes


def _emulator_before_a_scan(mode: int) -> tuple[TimedEmulatorV2, int, int]:
    """16 electrodes at 222 Hz on a UART in ``mode`` at sense height 0, heights 0 in force; the first alarm
    that falls less than 20 µs after one of the idle parser's ticks, and that tick (see
    tests/test_safety_pacing.py: a pattern read on that tick is pre-empted by the scan)."""
    emu = TimedEmulatorV2(link="uart")
    emu.write(
        c2.encode_electrode_num(N)
        + c2.encode_stim_mode(mode)
        + c2.encode_pulse_width(200)
        + c2.encode_discharge(45)
        + c2.encode_frequency(222)
        + c2.encode_pattern([0] * N, electrode_num=N),
        0.0,
    )
    emu.advance_to(40_000.0)
    last, before = emu.scans[-1], emu.scans[-2]
    period_ns = last.start_ns - before.start_ns
    tick = emu.model.rtos_tick_ns
    alarm = next(
        last.start_ns + j * period_ns
        for j in range(5, 1000)
        if 0 < (last.start_ns + j * period_ns) % tick < 20_000
    )
    return emu, alarm, alarm - alarm % tick


def test_a_scan_in_mode_2_that_preempts_the_copy_is_no_torn_pattern_and_delivers_nothing() -> None:
    """The emulator's reading of the spec ("Stimulation scan" 3c: in mode 2 every channel gets the sense
    pulse, the pattern ignored): the scan pre-empts the copy and holds part new, part old heights, yet
    uses none of them — no torn pattern, and no pulse at sense height 0.  The same copy in mode 0 is torn
    (the control)."""
    for mode, torn_expected in ((c2.STIM_MODE_IMPEDANCE, 0), (c2.STIM_MODE_MONOPHASIC, 1)):
        emu, alarm, wake = _emulator_before_a_scan(mode)
        emu.write(c2.encode_pattern([100] * N, electrode_num=N), (wake - 500_000) / 1000)
        emu.advance_to(alarm / 1000 + 10_000)
        scan = next(s for s in emu.scans if s.start_ns == alarm)
        assert 0 < scan.heights.count(100) < N  # the scan pre-empted the copy
        torn = [h for h in emu.hazards if h.kind is HazardKind.TORN_PATTERN]
        assert len(torn) == torn_expected, mode
        if mode == c2.STIM_MODE_IMPEDANCE:
            assert scan.pulses == () and not scan.live_channels()


def test_the_pattern_that_tore_written_under_the_cover_is_not_torn() -> None:
    """tests/test_safety_pacing.py's torn pattern (read on the tick 20 µs before an alarm), written at the
    same moment under the cover: the scan runs in mode 2 without current (a dropout), the next one has the
    new heights whole in mode 0."""
    emu, alarm, wake = _emulator_before_a_scan(c2.STIM_MODE_MONOPHASIC)
    cover = b"".join(covered_pattern([100] * N, c2.STIM_MODE_MONOPHASIC, sense_code=0))
    emu.write(cover, (wake - 500_000) / 1000 - 2 * 10.85)  # its pattern arrives when the bare one did
    emu.advance_to(alarm / 1000 + 10_000)
    assert [h for h in emu.hazards if h.kind is HazardKind.TORN_PATTERN] == []
    scan = next(s for s in emu.scans if s.start_ns == alarm)
    assert scan.stim_mode == c2.STIM_MODE_IMPEDANCE and scan.pulses == ()  # inside the cover
    after = emu.scans[scan.index + 1]
    assert after.stim_mode == c2.STIM_MODE_MONOPHASIC and after.heights == (100,) * N
    assert sc.dropouts(emu.scans) == 1  # the price, as the campaign counts it: that one scan
    ops = [op for t, op, _ in emu.applied if t >= wake]
    assert ops == [OpcodeV2.STIM_MODE, OpcodeV2.PATTERN, OpcodeV2.STIM_MODE]


def test_the_cover_zeroes_a_sense_height_that_is_not_proved_0_and_leaves_it_there() -> None:
    """Mode 2 is never in force at a sense height above 0: a configured sense current (code 12) or an
    unknown one is set to 0 before the mode and left there (restored behind ``FB mode``, it would be a
    current on every channel whenever that ``FB mode`` does not apply); a sense width whose mode-2 scan
    would outlast the frame's is zeroed and restored after the mode (a width at height 0 is no current)."""
    codes = [5, 0, 7]
    bare = [c2.encode_stim_mode(2), c2.encode_pattern(codes, electrode_num=3), c2.encode_stim_mode(1)]
    assert covered_pattern(codes, 1, sense_code=0) == bare
    assert covered_pattern(codes, 1, sense_code=12) == [c2.encode_sense_height(0), *bare]
    assert covered_pattern(codes, 1, sense_code=None) == [c2.encode_sense_height(0), *bare]
    assert covered_pattern(codes, 1, sense_code=12, sense_width_us=90) == [
        c2.encode_sense_height(0),
        c2.encode_sense_width(0),
        *bare,
        c2.encode_sense_width(90),
    ]


def test_a_session_with_a_sense_current_writes_each_new_pattern_in_one_covered_write(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """The driver's frame path on the timed v2 board with a configured sense current: each frame is one
    write (so the pacing puts nothing between its commands), mode 2 is only ever in force at sense height
    0 (the interlock reads every command of the write in turn), the heights arrive whole, and the sense
    height the first cover zeroed stays 0 (modes 0 and 1 never use it)."""
    dev, port, _ = _timed_v2()
    writes = _recorded_writes(monkeypatch, port)
    cfg = StimConfig(
        electrode_count=8, current_ua=1000, pulse_width_us=100, rate_hz=100, sense_current_ua=120
    )
    dev.configure(cfg)
    sense = dev.transfer.to_code(120, "sense_current_ua")
    assert sense > 0
    writes.clear()
    dev.send_pattern([1, 0, 1, 0, 0, 0, 0, 1])
    port.advance(0.05)
    dev.send_pattern([2, 2, 0, 0, 0, 0, 0, 0])  # a change of mode: the same single write
    port.advance(0.05)
    code = dev.transfer.to_code(1000)
    assert writes == [
        b"".join(covered_pattern([code, 0, code, 0, 0, 0, 0, code], 0, sense_code=sense)),
        b"".join(covered_pattern([code, code, 0, 0, 0, 0, 0, 0], 1, sense_code=0)),
    ]
    emu = port.emulator
    assert [h for h in emu.hazards if h.kind is HazardKind.TORN_PATTERN] == []
    assert all(s.sense_pulse_height == 0 for s in emu.scans if s.stim_mode == 2)
    assert emu.registers.sense_pulse_height == 0 and emu.registers.stim_mode == 1
    dev.close()


def test_write_commands_is_one_write_padded_per_command_and_spaced_as_a_pattern() -> None:
    """The pacing rule of the cover: one write, each command padded under robust encoding — the mode by
    its own value, the pattern not at all, since a command follows it (:func:`paddings`) — and the group
    spaced after the previous pattern as a pattern alone would be."""
    clock = SimulatedClock()
    pacer = Pacer(clock=clock, policy=PacingPolicy(firmware=V2, queue_bytes=1024, robust_encoding=True))
    pacer.set_timing(0.008, 0.00785)
    out: list[bytes] = []
    pattern = c2.encode_pattern([1, 2], electrode_num=2)
    pacer.write(out.append, pattern)
    t0 = clock.now()
    group = covered_pattern([3, 4], 0, sense_code=0)
    pacer.write_commands(out.append, group)
    assert len(out) == 2
    assert out[0] == pattern + b"\x00\x00"  # a pattern alone: its two zeros
    assert out[1] == b"\xfb\x02\x02" + c2.encode_pattern([3, 4], electrode_num=2) + b"\xfb\x00\x00"
    assert clock.now() - t0 >= pacer.payload_interval_s() - 1e-9
    assert pacer.stats.commands == 4 and pacer.stats.payload_commands == 4


@pytest.mark.parametrize("robust", [True, False], ids=["robust", "plain"])
def test_under_the_robust_encoding_heights_in_force_are_written_again_only_under_the_cover(
    monkeypatch: pytest.MonkeyPatch, robust: bool
) -> None:
    """A refresh and a forced pattern of the same heights, under the loss-tolerant encoding: each is the
    cover written twice (a byte lost from a pattern written alone would shift its heights into the mode in
    force); under the plain encoding they stay the mode and the pattern (refresh) and the pattern alone."""
    dev, port, _ = _timed_v2(robust=robust)
    writes = _recorded_writes(monkeypatch, port)
    dev.configure(StimConfig(electrode_count=4, current_ua=1000, pulse_width_us=100, rate_hz=100))
    dev.send_pattern([2, 0, 2, 0])
    port.advance(0.05)
    code = dev.transfer.to_code(1000)
    codes = [code, 0, code, 0]
    pattern = c2.encode_pattern(codes, electrode_num=4)
    cover = b"\xfb\x02\x02" + pattern + b"\xfb\x01\x01"
    writes.clear()
    dev.refresh()
    port.advance(0.05)
    assert writes == ([cover, cover] if robust else [c2.encode_stim_mode(1), pattern])
    writes.clear()
    dev.send_pattern([2, 0, 2, 0])  # the same frame again: written again, as it is
    port.advance(0.05)
    assert writes == ([cover, cover] if robust else [pattern])
    assert port.emulator.registers.stim_pattern[:4] == codes
    dev.close()
