"""The timed models follow the firmware exactly, its defects included: each case is the minimal reproduction
of a difference the differential (``tactdeform-hw diff-firmware``) found between the upstream firmware built
on the host and the package's model, run here on the model alone (no firmware tree needed), asserting what
the firmware's code does.  The same streams against the upstream trees are in ``test_diff_firmware.py``."""

from __future__ import annotations

from tactdeform_hw.emulator.hostbuild.diff import ModelSideV2
from tactdeform_hw.protocol.firmware import OpcodeV2

# when the upstream firmware's setup() has started its stimulation timer, both versions (the stack detection
# first; measured on the host build)
TIMER_ORIGIN_US = 1010.25


def _v2(writes: list[tuple[float, str]], end_us: float) -> ModelSideV2:
    side = ModelSideV2(timer_origin_us=TIMER_ORIGIN_US, hv513_count=4)
    for at_us, data in writes:
        side.write(bytes.fromhex(data), at_us)
    side.advance_to(end_us)
    return side


# 0xF6 65535 (a 15 µs alarm), then sense width 254, 228 electrodes and a measure request: the 0xFF's call is
# interrupted by the first scan of 228 channels (3114 µs), which overruns.
STARVED = [(3901.495, "f6ff"), (3941.495, "ff"), (17119.009, "f8fefce4ff")]


def test_v2_a_call_interrupted_by_an_overrunning_scan_never_resumes() -> None:
    """Timer1_Stimulate_ISR re-enables its alarm once the counter has passed it, so the next scan starts as
    the handler returns, and so on: runEtactileKit, interrupted inside the 0xFF's writeBytes, never gets the
    processor back.  The firmware never answers, and the scans run back to back."""
    side = _v2(STARVED, 60000.0)
    seen = side.observe(60000.0)
    assert seen.replies == b""
    assert seen.state["electrode_num"] == 228
    long_scans = [s for s in side.emu.scans if s.electrode_num == 228]
    assert len(long_scans) > 10
    for a, b in zip(long_scans, long_scans[1:]):
        assert b.start_ns == a.start_ns + a.duration_ns  # back to back: the loop has no time between
    assert OpcodeV2.MEASURE not in [op for _, op, _ in side.emu.applied[-3:]]


def test_v2_a_starved_loop_reads_nothing_more_and_its_queue_fills() -> None:
    """Bytes sent to a starved loop stay in the receive queue (1024 bytes in the firmware's serial build);
    the rest is lost: nothing is applied, a 0xF4 is not answered."""
    filler = "fc01" * 700  # 1400 bytes
    side = _v2([*STARVED, (30000.0, filler), (31000.0, "f4")], 60000.0)
    seen = side.observe(60000.0)
    assert seen.replies == b""
    assert seen.state["electrode_num"] == 228
    assert seen.state["rx_unread"] == 1024
    assert seen.state["rx_dropped"] == 1400 + 1 - 1024


def test_v2_the_same_request_answers_when_the_scans_leave_the_loop_time() -> None:
    """The contrast: with 0xF6 1000 (a 1 ms alarm) the 228-channel scan still interrupts the call, but the
    next alarm is not due when it returns, so the loop finishes the 0xFF and answers 2 x 228 bytes."""
    writes = [(3901.495, "f6e8"), (3941.495, "03"), (17119.009, "f8fefce4ff")]
    side = _v2(writes, 60000.0)
    assert len(side.observe(60000.0).replies) == 2 * 228


def test_v2_a_starved_loop_s_queue_overflows_as_the_bytes_arrive() -> None:
    """0xFC 32 and 0xF6 28466 (a 35 µs alarm): the scans run back to back and the loop never reads again.
    The serial driver still stores what arrives (initCommunication's 1024-byte receive buffer), so 1176
    bytes sent at once overflow it at once, before the next scan: the 3 bytes of the second 0xF6 were waiting
    unread, so 3 + 1176 - 1024 = 155 are lost."""
    writes = [(2000.5, "fc20"), (4904.391, "f6326ff60100"), (9425.323, "00" * 1176)]
    side = _v2(writes, 9425.5)
    seen = side.observe(9425.5)
    assert seen.state["rx_dropped"] == 155
    assert seen.state["rx_unread"] == 1024


# discharge 214 µs, biphasic, 4 electrodes and a pattern, 0xF5, then 4 electrodes again and 0xF6 65535
SENSED_THEN_FAST = [(2000.5, "f7d6fb01"), (2020.5, "fc04fe00008f910000cd8ef5"), (2580.973, "fc04f6fffff7")]


def test_v2_a_call_that_reads_a_command_with_a_payload_checks_the_queue_twice() -> None:
    """runEtactileKit calls isDataAvailable() before reading a command byte and again, in the same call,
    before reading its payload: 2 x 2 µs + 1 µs a byte, so each of these 2-byte commands takes 6 µs (a call
    on a payload already waiting checks once)."""
    side = _v2(SENSED_THEN_FAST, 4400.0)
    applied = [(round(t / 1000, 3), int(op)) for t, op, _ in side.emu.applied]
    assert applied[:5] == [(3000.0, 0xF7), (3006.0, 0xFB), (3012.0, 0xFC), (3018.0, 0xFE), (3031.0, 0xF5)]


def test_v2_a_new_frequency_s_alarm_is_enabled_at_the_end_of_its_call() -> None:
    """setPeriodUs (timerAlarmDisable, timerAlarmWrite, timerAlarmEnable) runs after the u16's read, the
    call's last: with the counter already past the new 30-tick alarm, the scan starts as the call ends
    (4040 + 2 + 1 + 2 + 2 µs), not at its start."""
    side = _v2(SENSED_THEN_FAST, 4400.0)
    after = [s.start_ns for s in side.emu.scans if s.start_ns >= 4040_000]
    assert after[0] == 4047_000


def test_v2_a_scan_of_no_channel_clocks_the_chain_only_the_first_time() -> None:
    """hv513FastScan's position is a static that only channel 0 resets: with no electrode, hv513Clear
    clocks the 32 outputs (4 HV513) in the first scan after boot and none in the next (pin = 32 - 32)."""
    side = _v2([], 1100000.0)
    durations = [s.duration_ns for s in side.emu.scans[:3]]
    assert durations == [2000 + 3 * 50 + 64 * 50, 2000 + 3 * 50, 2000 + 3 * 50]
