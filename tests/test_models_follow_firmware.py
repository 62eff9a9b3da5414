"""The timed models follow the firmware exactly, its defects included: each case is the minimal reproduction
of a difference the differential (``tactdeform-hw diff-firmware``) found between the upstream firmware built
on the host and the package's model, run here on the model alone (no firmware tree needed), asserting what
the firmware's code does.  The same streams against the upstream trees are in ``test_diff_firmware.py``."""

from __future__ import annotations

import pytest

from tactdeform_hw.emulator.firmware.hazards import HazardKind
from tactdeform_hw.emulator.firmware.scan import ChainState, ScanConfig, ScanEngine
from tactdeform_hw.emulator.hostbuild.diff import DirectLink, ModelSideV1_2, ModelSideV2
from tactdeform_hw.emulator.timed.model_v1_2 import TimedEmulator
from tactdeform_hw.emulator.timed.timing import TimingModel
from tactdeform_hw.protocol.commands import encode_pattern
from tactdeform_hw.protocol.firmware import OpcodeV2

# when the upstream firmware's setup() has started its stimulation timer, both versions (the stack detection
# first; measured on the host build)
TIMER_ORIGIN_US = 1010.25


def _v1_2(writes: list[tuple[float, str]], end_us: float) -> ModelSideV1_2:
    side = ModelSideV1_2(timer_origin_us=TIMER_ORIGIN_US, hv513_count=4)
    for at_us, data in writes:
        side.write(bytes.fromhex(data), at_us)
    side.advance_to(end_us)
    return side


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
    (4043.45 + 2 + 1 + 2 + 2 µs), not at its start."""
    side = _v2(SENSED_THEN_FAST, 4400.0)
    after = [s.start_ns for s in side.emu.scans if s.start_ns >= 4040_000]
    assert after[0] == 4050_450


def test_v2_an_f5_call_ends_after_hv513_init_s_pin_writes() -> None:
    """stackSense() makes its 50 analogRead calls (1000 µs), then hv513Init() on the count it found: POL, LE,
    CLK, BL and DIN, then a CLK high and low per output (5 + 2 x 32 pin writes of 0.05 µs with 4 HV513), so
    the 0xF5 read at 3031 µs answers at 3031 + 2 + 1 + 1000 + 3.45 µs and the next call starts then."""
    side = _v2(SENSED_THEN_FAST, 4400.0)
    assert side.observe(4400.0).replies == bytes([4])
    applied = [(t, int(op)) for t, op, _ in side.emu.applied]
    assert applied[4:7] == [(3_031_000, 0xF5), (4_037_450, 0xFC), (4_043_450, 0xF6)]


def test_v2_a_scan_of_no_channel_clocks_the_chain_only_the_first_time() -> None:
    """hv513FastScan's position is a static that only channel 0 resets: with no electrode, hv513Clear
    clocks the 32 outputs (4 HV513) in the first scan after boot and none in the next (pin = 32 - 32)."""
    side = _v2([], 1100000.0)
    durations = [s.duration_ns for s in side.emu.scans[:3]]
    assert durations == [2000 + 3 * 50 + 64 * 50, 2000 + 3 * 50, 2000 + 3 * 50]


# A loop starved by overrunning scans (the next alarm already passed when Timer1_Stimulate_ISR re-enables
# it) is left where the scan took the processor: at the first of runEtactileKit's calls into the Arduino
# core (isDataAvailable, readInt_8/readInt_16, timerRead, setPeriodUs, the reply's write) at or after the
# alarm.  What it read and stored before stays; nothing after that call ever happens.

# 0xF6 65534 (a 15 µs alarm), 0xFC 1 (a scan of one channel: 19.2 µs), an unknown byte, then 0xF8
BEFORE_THE_COMMAND_BYTE = [(11286.611, "f6fefffc010065f8")]


def test_v2_a_call_starved_before_its_command_byte_leaves_the_byte_queued() -> None:
    """runEtactileKit has checked isDataAvailable() when the alarm falls; the overrunning scan takes the
    processor at readInt_8 and never gives it back, so 0xF8 is never read: it stays in the receive queue
    for good and the sense pulse width never changes."""
    side = _v2(BEFORE_THE_COMMAND_BYTE, 75265.01)
    seen = side.observe(75265.01)
    assert seen.state["rx_unread"] == 1
    assert seen.state["electrode_num"] == 1
    assert [op for _, op, _ in side.emu.applied] == [OpcodeV2.FREQUENCY, OpcodeV2.ELECTRODE_NUM]
    one_channel = [s for s in side.emu.scans if s.electrode_num == 1]
    assert len(one_channel) > 1000
    for a, b in zip(one_channel, one_channel[1:]):
        assert b.start_ns == a.start_ns + a.duration_ns  # back to back: the call never resumes


# 0xF6 65535, then 4 electrodes and a pattern of 4 x 4095: the alarm falls as the copy reads the third element
TORN_FOR_GOOD = [(2000.5, "f6ffff"), (4000.5, "fc04feff0fff0fff0fff0f")]


def test_v2_a_pattern_copy_starved_midway_keeps_the_elements_it_read() -> None:
    """0xFE's copy loop stores each element as readInt_16 returns it: the scan of 4 channels (60 µs against
    15 µs) takes the processor inside the second element's read, so channel 0 is new and 1 to 3 keep their
    old heights in every scan from then on.  The second element's two bytes have left the queue, but
    nothing stores them; the last 4 payload bytes are never read."""
    side = _v2(TORN_FOR_GOOD, 7000.0)
    seen = side.observe(7000.0)
    assert seen.state["stim_pattern"][:4] == [4095, 0, 0, 0]
    assert seen.state["rx_unread"] == 4
    four = [s for s in side.emu.scans if s.electrode_num == 4]
    assert len(four) > 30 and {s.heights for s in four} == {(4095, 0, 0, 0)}
    torn = [h for h in side.emu.hazards if h.kind is HazardKind.TORN_PATTERN]
    assert [(h.detail["new_channels"], h.detail["channels"]) for h in torn] == [(1, 4)]
    assert OpcodeV2.PATTERN not in [op for _, op, _ in side.emu.applied]


# 0xF6 62719 (a 15.5 µs alarm), then 0xFC 1 and 0xF6 1: the alarm falls as the second 0xF6's u16 is read
PERIOD_WITHOUT_ITS_ALARM = [(2000.5, "f6fff4"), (18040.402, "fc01f60100")]


def test_v2_a_frequency_starved_in_its_read_keeps_the_old_period_and_alarm() -> None:
    """The scan of one channel takes the processor inside 0xF6's readInt_16 and never gives it back:
    StimulationTimePeriod is never stored nor setPeriodUs called, so the period stays the old 15.9 µs and
    the alarm 30 ticks, the payload has left the queue, and the scans run back to back."""
    side = _v2(PERIOD_WITHOUT_ITS_ALARM, 21012.0)
    seen = side.observe(21012.0)
    assert seen.state["period_us"] == pytest.approx(15.944131851196289)
    assert seen.state["timer_alarm_ticks"] == 30
    assert seen.state["rx_unread"] == 0
    last = [s for s in side.emu.scans if s.start_ns > 19_100_000]
    assert len(last) > 50
    assert all(b.start_ns == a.start_ns + a.duration_ns for a, b in zip(last, last[1:]))


# 0xF6 63743 (a 15.5 µs alarm), 8 electrodes, 0xFA 63497: the alarm falls inside the read of 0xFA's u16
LAST_READ_STORED = [(2010.5, "f6fff8"), (3115.983, "fc08fa09f8")]


def test_v2_a_read_the_starving_scan_falls_in_is_never_stored() -> None:
    """The scan takes the processor inside 0xF8's readInt_16, before runEtactileKit stores PulseWidth, and
    never gives it back: the scans that starve the loop run the old width (0), and so do the registers
    from then on, though the payload has left the queue."""
    side = _v2(LAST_READ_STORED, 127175.983)
    seen = side.observe(127175.983)
    assert seen.state["pulse_width"] == 0
    assert seen.state["rx_unread"] == 0
    eight = [s for s in side.emu.scans if s.electrode_num == 8]
    assert eight and {s.pulse_width for s in eight} == {0}


# A scan whose alarm falls inside a main-loop call pre-empts it (Timer1_Stimulate_ISR takes the processor from
# runEtactileKit and gives it back when it returns): the call ends the scan's duration later, whatever the
# call does -- a command applied, an unknown byte skipped, a payload awaited, nothing at all.

# 0xF6 65534 (a 15 µs alarm), four unknown bytes, 0xFC 2, 0xFF and 0x00, all at 2000.5 µs
UNKNOWN_BYTES_THEN_STARVED = [(2000.5, "f6feff"), (2000.5, "d8459539"), (2000.5, "fc02ff00")]


def test_v2_a_scan_inside_a_call_that_skips_an_unknown_byte_delays_the_loop() -> None:
    """The call that reads and skips 0x39 (3021.35 µs: isDataAvailable 2 µs, readInt_8 1 µs) is pre-empted
    by the scan of no channel due at 3022 µs (2.15 µs): it ends at 3026.5 µs, so 0xFC 2's call starts then
    and 0xFF's at 3032.5; the next call's isDataAvailable() is under way at 3037 µs, when the first scan of
    two channels (32.55 µs against a 15 µs alarm) takes the processor for good: 0x00 is never read."""
    side = _v2(UNKNOWN_BYTES_THEN_STARVED, 5013.0)
    applied = [(t, int(op)) for t, op, _ in side.emu.applied]
    assert applied == [(3_000_000, 0xF6), (3_026_500, 0xFC), (3_032_500, 0xFF)]
    seen = side.observe(5013.0)
    assert seen.state["rx_unread"] == 1
    assert len(seen.replies) == 4  # 0xFF answered its two channels' readings


# 0xF6 65023 (a 15 µs alarm), an unknown byte, 0xF6 37298 (26 µs), 141 electrodes, then 0xF9 1
ALARM_IN_A_FREQUENCY_CALL = [(3303.434, "f6fffd01f6b291fc8d"), (3303.434, "f901")]


def test_v2_a_scan_due_inside_a_frequency_call_runs_before_set_period() -> None:
    """The alarm of 4022 µs falls inside the second 0xF6's read of its u16 (4020.35 to 4022.35 µs): the scan
    runs at the call's next point, setPeriodUs's timerAlarmDisable, with the old alarm; setPeriodUs then arms
    26 µs from that alarm (4048 µs), so 0xFC 141 (4024.5 µs, after the scan) and 0xF9 1 are stored before the
    first scan of 141 channels starves the loop."""
    side = _v2(ALARM_IN_A_FREQUENCY_CALL, 6037.0)
    starts = [s.start_ns for s in side.emu.scans]
    assert starts[:3] == [4_007_000, 4_022_000, 4_048_000]
    applied = [(t, int(op)) for t, op, _ in side.emu.applied]
    assert applied[1:] == [(4_015_350, 0xF6), (4_024_500, 0xFC), (4_030_500, 0xF9)]
    assert side.observe(6037.0).state["sense_pulse_height"] == 1


# 8 electrodes, pulse width 130 µs, 0xF6 587 (a 1703 µs alarm): the scans last 1075.45 µs, and the alarm of
# 49 001 µs falls inside the idle poll of the 49 000 µs tick; 0xF9 1 arrives during that scan
ALARM_IN_AN_IDLE_POLL = [(2000.5, "fc08fa8200f64b02"), (49100.0, "f901")]


def test_v2_a_scan_inside_an_idle_poll_delays_its_sleep() -> None:
    """The poll's isDataAvailable() (49 000 to 49 002 µs) finds nothing; the scan takes the processor at
    vTaskDelay(1), which is called as the scan returns (50 076.45 µs) and sleeps to the 51 000 µs tick; the
    next scan (50 704 µs) holds the processor past that tick, so 0xF9 1 is read as it returns (51 779.45
    µs), not as the first scan returns."""
    side = _v2(ALARM_IN_AN_IDLE_POLL, 53000.0)
    assert any(s.start_ns == 49_001_000 and s.duration_ns == 1_075_450 for s in side.emu.scans)
    assert side.emu.applied[-1][:2] == (51_779_450, OpcodeV2.SENSE_HEIGHT)


# 0xF6 48662 (a 20 µs alarm), 1 electrode (a scan of 19 µs), then 0xFE and, 3.7 ms later, its two bytes: the
# loop has 1 µs between scans
SLIVERS = [(2000.5, "f616befc01"), (3081.22, "fe"), (6776.817, "fffc")]


def test_v2_a_call_spanning_several_scans_is_pre_empted_by_each() -> None:
    """The call that reads 0xFE's payload starts at 7006 µs and needs 4 µs (isDataAvailable, readInt_16):
    the alarms of 7007 and 7027 µs each take the processor for 19.2 µs inside isDataAvailable, so those two
    scans still run height 0 (the model had counted one scan in the call and run the next with the new
    height); the alarms of 7047 and 7067 µs fall inside the readInt_16 that starts at 7046.4 µs, the
    call's last read, so their scans are taken inside it, before the store, and run height 0 too; the
    scan of 7087 µs runs 4095."""
    side = _v2(SLIVERS, 9033.0)
    scans = [(s.start_ns, s.heights) for s in side.emu.scans if 7_000_000 < s.start_ns < 7_100_000]
    assert scans[:5] == [
        (7_007_000, (0,)),
        (7_027_000, (0,)),
        (7_047_000, (0,)),
        (7_067_000, (0,)),
        (7_087_000, (4095,)),
    ]


# 0xF6 65535 (a 15 µs alarm), then 0xF9 246, two unknown bytes and 0xF5: the 0xF5 is read from 8014.15 µs on
# and the alarm of 8017 µs falls inside its read
ALARM_BEFORE_F5_DISABLES_IT = [(4369.366, "fefef6ffff"), (7959.381, "f9f60000f5")]


def test_v2_an_alarm_before_0xf5_disables_the_timer_pre_empts_its_call() -> None:
    """runEtactileKit disables the stimulation alarm (timerAlarmDisable) only after reading the 0xF5 byte
    (8014.15 + 2 + 1 µs): the alarm of 8017 µs comes first, so its scan runs then and the call, the detection
    and hv513Init after it, ends 2.15 µs later (9022.75 µs), where the re-enabled alarm fires at once."""
    side = _v2(ALARM_BEFORE_F5_DISABLES_IT, 9100.0)
    starts = [s.start_ns for s in side.emu.scans if 8_000_000 < s.start_ns < 9_050_000]
    assert starts == [8_002_000, 8_017_000, 9_022_750, 9_037_750]


# sense height 4, pulse width 65535 then 65534, 221 electrodes, sense width 255, discharge 61, then two 0xF5:
# the second 0xF5's stackSense() is interrupted by the first scan (221 channels, 69.9 ms), and the scans then
# overrun back to back.
F5_THEN_LONG_SCANS = [(2000.5, "f901fafffffafefffcddf8"), (2970.199, "fff73d"), (7509.598, "f5f5")]


def test_v1_2_an_f5_interrupted_in_its_stack_detection_has_left_the_queue() -> None:
    """runEtactileKit() reads the 0xF5 (readInt_8) before stackSense(): when the alarm interrupts the
    detection, the byte is no longer in the receive queue, though the reply has not been written.  So the
    256 bytes that arrive during the scan all fit (the firmware loses none; a model still holding the 0xF5
    would lose one)."""
    side = _v1_2(F5_THEN_LONG_SCANS, 10009.066)
    seen = side.observe(10009.066)
    assert seen.state["rx_unread"] == 0
    assert seen.replies == b"\x04"  # the first 0xF5's; the second's comes after its detection
    side.write(bytes(256), 20000.5)
    side.advance_to(90000.0)
    seen = side.observe(90000.0)
    assert seen.state["rx_unread"] == 256
    assert side.emu.losses == []
    assert seen.replies == b"\x04"  # the scans overrun back to back: the loop never finishes the detection


# sense height 552, sense width 0 then 2, 32 electrodes, then two 0xF5: the second one's hv513Init() runs from
# 11 009.45 us (after the tick-aligned first reply and 1000 us of analogRead), and the first alarm, at
# 11 010.25 us, comes right after its 16th pin write: the 6th CLK high of the zeros it clocks in.
F5_INIT_AT_THE_ALARM = [(4817.812, "f98af800fc20f802"), (4867.812, "f5f5")]


def test_v1_2_an_alarm_inside_hv513_init_with_clk_high_leaves_that_scan_dark() -> None:
    """hv513Init() clocks zeros with CLK high then low; the timer interrupt pre-empts it between the two, so
    the scan's hv513FastScan(0) writes CLK high on a CLK already high: no rising edge, its 1 is never
    shifted in, and the 32 channels' pulses reach no output.  The next scan selects normally."""
    side = _v1_2(F5_INIT_AT_THE_ALARM, 22000.0)
    seen = side.observe(22000.0)
    assert seen.replies == b"\x04\x04"
    assert not [p for p in seen.pulses if p[0] < 21000.0]  # the scan at 11 010.25 us: no output lit
    assert [p[3] for p in seen.pulses][:3] == [(0,), (1,), (2,)]  # the scan at 21 010.25 us
    assert seen.pulses[0][0] > 21010.25


def test_v1_2_a_scan_starting_with_clk_high_loses_its_first_clock_edge() -> None:
    """The scan engine, from a chain whose CLK the pre-empted code left high (ChainState.clk_high)."""
    cfg = ScanConfig.make(2, 0)
    engine = ScanEngine(outputs=32)
    assert engine.template(cfg, ChainState(0, 0, 0)).pulse_outputs[:2] == [(0,), (1,)]
    assert engine.template(cfg, ChainState(0, 0, 0, True)).pulse_outputs[:2] == [(), ()]


# pulse height 1, sense height 4, sense width 1; then sense width 0, 255 electrodes, discharge 1,
# 32 electrodes, discharge 1 and the first 3 bytes of a pattern: one command a tick, the pattern's call at
# 11 000 us.
PATTERN_AT_THE_ALARM = [
    (2000.5, "fb0100f901f801"),
    (3026.305, "f800fcfff701fc20"),
    (3036.305, "f701fe00ff02"),
]


def test_v1_2_a_pattern_byte_costs_a_serial_available_check_and_a_read() -> None:
    """runEtactileKit()'s payload loop calls isDataAvailable() before every byte it reads: from the tick at
    11 000 us the call reads 0xFE at 11 003 us and the pattern bytes at 11 006, 11 009 and 11 012 us, so the
    alarm at 11 010.25 us comes before channel 2's byte (2): the first scan gives channel 2 a sense pulse
    (code 4), and the byte is read after the scan."""
    side = _v1_2(PATTERN_AT_THE_ALARM, 13000.0)
    first_scan = [p for p in side.observe(13000.0).pulses if 11010.25 < p[0] < 12000.0]
    assert [(p[2], p[3]) for p in first_scan[:3]] == [(4, (0,)), (4, (1,)), (4, (2,))]
    assert side.observe(13000.0).state["stim_pattern"][:3] == [0, 255, 2]


def test_v1_2_a_pattern_call_reads_the_bytes_that_arrive_while_it_reads() -> None:
    """runEtactileKit()'s payload loop, ``while (isDataAvailable() > 0 && bytesRead < requiredBytes)``,
    checks the queue again before every byte: a call reads the bytes that arrive during it, and ends only
    at a check that finds none.  A 32-electrode pattern over the UART (one byte per 10.85 us) written at
    70 841.5 us: at the tick at 71 000 us its first 14 bytes wait; the call reads the command byte at
    71 003 us and channel j at 71 006 + 3j us, and channel j's byte (byte j + 1, arriving at
    70 841.5 + 10.85 (j + 2) us) is there at its check, 71 003 + 3j us, up to j = 17; channel 18's is not
    (71 058.5 > 71 057).  The scan at 71 100 us is torn after 18 channels (a call that read only the 13
    waiting when it began would have left it 13), and the rest are read at the next tick."""
    emu = TimedEmulator(link="uart", model=TimingModel(timer_start_us=1100.0))  # alarms at 1100 + 2000k us
    emu.configure(ScanConfig.make(32, 0, pulse_width_us=10, discharge_us=0, rate_hz=500))
    emu.advance_to(70_000.0)
    emu.write(encode_pattern([1] * 32), 70_841.5)
    emu.advance_to(75_000.0)
    torn = [(h.time_us, h.detail["new_channels"]) for h in emu.hazards if h.kind is HazardKind.TORN_PATTERN]
    assert torn == [(71_100.0, 18)]
    written = [ch.written_us for ch in emu.commands[-1].channels]
    assert written[:18] == [71_006.0 + 3 * j for j in range(18)]
    assert written[18:] == [72_003.0 + 3 * j for j in range(14)]


# 4 electrodes, sense width 255, discharge 254 (a scan of 2.04 ms); at the tick at 11 000 us an unknown byte,
# then 0xF9 1 and 0xF9 2 wait: the call for 0xF9 1 starts at 11 003 us, its last read ends at 11 009 us and
# the payload loop's last Serial.available() check runs to 11 011 us, across the alarm at 11 010.25 us.
CHECK_AT_THE_ALARM = [(2000.5, "fc04f8fff7fe"), (10500.5, "04f901f902")]


def test_v1_2_a_scan_inside_the_last_check_delays_the_call_s_sleep() -> None:
    """runEtactileKit()'s payload loop checks isDataAvailable() once more after the command's last byte and
    only then calls vTaskDelay(1): the alarm inside that check runs its scan (to 13 054.7 us) first, so
    vTaskDelay is called after the scan and the loop sleeps to the tick at 14 000 us.  Had vTaskDelay come
    before the scan, its tick (12 000 us) would fall inside it and the loop would read 0xF9 2 as the scan
    returns."""
    side = _v1_2(CHECK_AT_THE_ALARM, 13_900.0)
    seen = side.observe(13_900.0)
    assert (seen.state["sense_pulse_height"], seen.state["rx_unread"]) == (4, 2)
    assert [(r.start_ns, r.duration_ns) for r in side.emu.runs if r.start_ns > 11_000_000][:1] == [
        (11_010_250, 2_044_450)
    ]
    side.advance_to(14_010.0)
    seen = side.observe(14_010.0)
    assert (seen.state["sense_pulse_height"], seen.state["rx_unread"]) == (8, 0)


def test_v1_2_the_differential_s_model_costs_chip_selects_as_the_host_build() -> None:
    """DAAD() lowers and raises DA_CS and AD_CS around its SPI exchange: four GPIO writes the host build's
    shim costs (0.05 us each) and the model's default reading counts inside the 6.6 us exchange.  The
    differential's model side takes the shim's reading: with 0xF6 11402 (an 87 us period) a scan of 4
    sense pulses is 88.45 us (3 DAAD calls a channel, 0.6 us), longer than the period, so the scans run
    back to back and the loop never reads the 0xF7 22 that waits (86.05 us under the default reading: the
    loop runs between scans and stores it)."""
    writes = [(2000.5, "f68a2c"), (2000.5, "fd"), (2000.5, "02fc04f716")]
    side = _v1_2(writes, 8489.0)
    assert side.emu.model.cs_writes_costed
    four = [r for r in side.emu.runs if r.template.duration_ns > 80_000]
    assert four[0].duration_ns == 88_450 and four[0].starved
    assert side.observe(8489.0).state["discharge_time"] == 0
    default = TimedEmulator(
        "compact",
        1,
        link=DirectLink(),
        tx_link=DirectLink(),
        model=TimingModel(timer_start_us=TIMER_ORIGIN_US),
    )
    for at_us, data in writes:
        default.write(bytes.fromhex(data), at_us)
    default.advance_to(8489.0)
    assert not default.model.cs_writes_costed
    assert [r.duration_ns for r in default.runs if r.duration_ns > 80_000][0] == 86_050
    assert default.registers.discharge_time == 22


def test_v1_2_a_byte_arriving_during_a_call_finds_the_bytes_it_has_not_read_yet() -> None:
    """runEtactileKit() reads a command and its payload one Serial.read() at a time: 125 x 0xF7 254 fill
    the 256-byte receive queue to 250; the call at the 3000 us tick reads 0xF7 from 3002 us and 254 from
    3005 us, so 8 bytes arriving at 3002.5 us find 249 waiting (the model had taken both bytes at the
    call's start: 248) and the last one is lost."""
    side = _v1_2([(2000.5, "f7fe" * 125), (3002.5, "00" * 8)], 3020.0)
    assert [(lo.time_us, lo.count, lo.reason) for lo in side.emu.losses] == [(3002.5, 1, "queue_full")]
    assert side.observe(3020.0).state["rx_unread"] == 255
    early = _v1_2([(2000.5, "f7fe" * 125), (3001.5, "00" * 8)], 3020.0)  # before 0xF7's read: 2 lost
    assert [(lo.time_us, lo.count) for lo in early.emu.losses] == [(3001.5, 2)]


# discharge 254, then 254 (or 32) electrodes, a measure request and 0xF6 1: the call for 0xF6 reads its u16
# from 31 010 us to 31 012 us, across the alarm at 31 010.25 us, and setPeriodUs() comes after that read.
def _frequency_at_the_alarm(electrodes: str) -> list[tuple[float, str]]:
    return [
        (4876.87, "71"),
        (6206.937, "f7"),
        (6206.937, "fefc"),
        (23379.394, electrodes),
        (30450.161, "fff60100"),
    ]


def test_v1_2_a_last_check_pre_empted_by_many_scans_sleeps_after_the_last_of_them() -> None:
    """A 47 µs alarm and scans of 46.95 µs leave the loop 50 ns a period: after 0xFD 2's payload is read
    (9730 µs), the payload loop's last Serial.available() (2 µs) spans 40 scans, so vTaskDelay(1) is
    called at about 11 610 µs and the loop reads 0xF9 from the 12 000 µs tick, in slivers too (14 900 µs),
    and its payload at 17 720 µs: the first pulse of height 2 is at 18 618.7 µs.  (The model had ended the
    check as the first scan returned and read 0xF9 from the 10 000 µs tick: 16 644.7 µs.)"""
    side = _v1_2([(2000.5, "f62352fc02fd02"), (2010.5, "f902")], 14899.0)
    assert side.observe(14899.0).state["rx_unread"] == 2
    side.advance_to(19000.0)
    assert side.observe(19000.0).pulses[0][:3] == (18618.7, 18625.5, 8)


def test_v1_2_a_frequency_whose_scan_overruns_never_stores_the_period() -> None:
    """The alarm comes inside the u16's read, before runEtactileKit() stores StimulationTimePeriod: the
    handler re-enables the old 10 ms alarm as it returns, but its scan of 254 channels takes 67.3 ms, so
    the next scan starts at once, and so on: the loop never resumes, and the period stays 10 ms and the
    timer's alarm 20 000 ticks."""
    side = _v1_2(_frequency_at_the_alarm("fe"), 300_000.0)
    seen = side.observe(300_000.0)
    assert (seen.state["timer_alarm_ticks"], seen.state["period_us"]) == (20_000, 10_000.0)
    long_scans = [r for r in side.emu.runs if r.start_ns > 31_000_000]
    assert long_scans[0].start_ns == 31_010_250 and long_scans[0].starved


def test_v1_2_a_frequency_whose_scan_returns_in_time_sets_the_period_after_it() -> None:
    """The contrast: with 32 channels the scan (8.48 ms) returns before the old alarm's next one, the loop
    resumes and setPeriodUs() writes the 1 s alarm then: the register holds the old alarm during the scan,
    the new one from its end, and the next scan follows 1 s after the one the call let in."""
    side = _v1_2(_frequency_at_the_alarm("20"), 35_000.0)
    assert side.observe(35_000.0).state["timer_alarm_ticks"] == 20_000
    side.advance_to(1_040_000.0)
    assert side.observe(1_040_000.0).state["timer_alarm_ticks"] == 2_000_000
    starts = [r.start_ns for r in side.emu.runs if r.start_ns > 31_000_000]
    assert starts == [31_010_250, 1_031_010_250]


def test_v1_2_a_byte_arriving_during_a_call_that_skips_an_unknown_byte_finds_it_still_queued() -> None:
    """The same in a run of calls that each read and ignore one unknown byte (3 us each: Serial.available()
    then Serial.read()): the call at 3012 us reads its byte from 3014 us, so 8 bytes arriving at 3012.5 us
    find 250 waiting, not 249, and two are lost."""
    side = _v1_2([(2990.5, "00" * 6), (3002.5, "00" * 248), (3012.5, "00" * 8)], 3016.0)
    assert [(lo.time_us, lo.count) for lo in side.emu.losses] == [(3012.5, 2)]


# 0xF6 65279 (a 15 µs alarm), mode 2 (the sense pulse on every channel) at sense width 254, then 0xFC 4
# and 0xFC 0 back to back: the alarm due at 14123.4 µs falls inside the second's last read
COUNT_LOWERED_IN_ITS_LAST_READ = [
    (4881.184, "f4f5f60100fd00fb3f"),
    (12153.317, "f6fefffb02f8fefbccf4"),
    (12163.317, "91de64b3b1a8c39978e8"),
    (12163.317, "f5f762fdfefd01"),
    (12173.317, "f4fbfffc04fc00f4"),
]


def test_v2_an_alarm_in_a_call_s_last_read_scans_the_registers_from_before_it() -> None:
    """The alarm comes inside the readInt_8 of 0xFC 0, before runEtactileKit stores ElectrodeNum = 0: the
    scan is of the four channels 0xFC 4 had set, in mode 2, and lasts 1.39 ms against the 15 µs alarm, so
    it starves the loop.  The count stays 4, the byte read has left the queue, and the 0xF4 behind it is
    never answered."""
    side = _v2(COUNT_LOWERED_IN_ITS_LAST_READ, 15000.0)
    assert [(t, int(op)) for t, op, _ in side.emu.applied][-1] == (14_111_850, 0xFC)
    late = [s for s in side.emu.scans if s.start_ns >= 14_111_850]
    assert late and {(s.electrode_num, s.duration_ns) for s in late} == {(4, 1_388_450)}
    seen = side.observe(15000.0)
    assert seen.state["electrode_num"] == 4
    assert seen.state["rx_unread"] == 1
    assert seen.replies.endswith(bytes.fromhex("04000400"))


def test_v1_2_the_idle_loop_s_poll_of_a_tick_inside_a_scan_reads_what_arrived_during_the_scan() -> None:
    """An idle runEtactileKit() finds nothing, calls vTaskDelay(1) and polls again at every tick; a tick
    inside a scan (the one of 12 000 us inside the scan from 11 010.25 to 13 018.7 us: 4 sense pulses of
    255 us, discharge 245 us) wakes the loop as the scan returns, and that poll reads the 0xF5 that arrived
    at 13 010.214 us during the scan: its reply comes 1 ms of detection later, at 14 025.15 us, not after
    the tick of 14 000 us."""
    side = _v1_2([(2010.5, "f8fff7f5fc04"), (13010.214, "f5")], 13100.0)
    assert side.observe(13100.0).state["rx_unread"] == 0
    side.advance_to(15022.0)
    assert side.emu.tx_log == [(14025.15, b"\x04")]


def test_v2_a_call_s_bytes_leave_the_queue_as_run_etactile_kit_reads_them() -> None:
    """runEtactileKit() reads a command byte after one isDataAvailable() (2 µs) and its payload after a
    second (readInt_8, 1 µs a byte): the queue keeps a byte until its read starts, though the model's call
    takes them at its start (the 'state rx_unread' cause)."""
    side = _v2([(2000.5, "f801fb01")], 2999.0)
    seen = []
    for t_us in (2999.0, 3001.0, 3002.5, 3004.0, 3005.5, 3007.0, 3008.5, 3010.0, 3011.5):
        side.advance_to(t_us)
        seen.append(side.observe(t_us).state["rx_unread"])  # waiting, or landing at the model's next call
    assert seen == [4, 4, 3, 3, 2, 2, 1, 1, 0]


def test_v2_a_byte_arriving_while_a_call_reads_finds_its_unread_bytes_in_the_queue() -> None:
    """1024 bytes fill the queue; the call at the 3000 µs tick reads 0xF8 at 3002 µs and its payload at
    3005 µs, so two bytes arriving at 3003 µs find 1023 queued: one fits, the HWCDC driver drops the other
    (the 'state rx_dropped' and 'state stim_pattern' cause)."""
    side = _v2([(2000.5, "f801" * 512), (3003.0, "f801")], 3100.0)
    assert side.emu.state().rx_dropped == 1


# 1 electrode in mode 2 (sense height 255), then 0xF6 43754 (a 22 µs alarm) and 0xFC 0: the scans of 4019
# and 4041 µs take the processor inside the 0xFC call, the alarm of 4063 µs falls inside its last read
LATER_ALARM_IN_LAST_READ = [(2761.842, "fc01"), (3049.205, "f9fffb02f6eaaafc00")]


def test_v2_a_later_alarm_inside_a_call_s_last_read_scans_what_was_stored_before_it() -> None:
    """runEtactileKit's 0xFC call reads its byte from 4040.2 µs; the scan of 4041 µs pre-empts it, the call
    resumes at 4060.2 µs and reads the count from 4062.2 to 4063.2 µs: the alarm of 4063 µs falls inside that
    last read, so its scan, like a first alarm there, runs before ElectrodeNum = 0 is stored, on one
    channel; the scan of 4085 µs runs none."""
    side = _v2(LATER_ALARM_IN_LAST_READ, 4100.0)
    scans = [(s.start_ns, s.electrode_num) for s in side.emu.scans]
    assert scans == [(4_019_000, 1), (4_041_000, 1), (4_063_000, 1), (4_085_000, 0)]


# 32 electrodes, then a pattern whose copy the alarm of 11010.25 µs interrupts
TORN_AT_AN_ELEMENT = [
    (2242.218, "fc20"),
    (
        10172.698,
        "fe03000100fcdec4180000010001000100ff00ff00cb8c020003004dad030001000000c5a103000200010002000100ff00"
        "ffd6ff00030000000100327b01000100",
    ),
]


def test_v2_a_pattern_element_whose_read_the_alarm_falls_in_is_stored_after_the_scan() -> None:
    """The call at the 11000 µs tick reads 0xFE by 11003 µs and copies one element (readInt_16, 2 µs) at a
    time from 11005 µs: the alarm of 11010.25 µs falls inside element 2's read, and the scan takes the
    processor there, before the element is stored, so it runs elements 0 and 1 new and the rest old."""
    side = _v2(TORN_AT_AN_ELEMENT, 11100.0)
    assert [(s.start_ns, s.heights[:4]) for s in side.emu.scans] == [(11_010_250, (3, 1, 0, 0))]
    torn = [h.detail["new_channels"] for h in side.emu.hazards if h.kind is HazardKind.TORN_PATTERN]
    assert torn == [2]


# 1 electrode, then 0xF6 whose payload (53384: a 19.2 us scan every 18 us) comes 40 us later (random seed
# 87056, minimal)
PAYLOAD_DURING_ITS_COMMAND_CALL = [(4992.748, "fc01fdfffeff00fd01fd01f6"), (5032.748, "88d0")]


def test_v2_a_payload_arriving_while_its_command_byte_is_read_is_read_by_the_same_call() -> None:
    """The call at 5031 µs reads 0xF6 from 5033 µs; its payload, arriving at 5032.748 µs, is counted by the
    call's second isDataAvailable() at 5034 µs and read by it, so setPeriodUs writes the new alarm at 5038
    µs and the first scan at the new rate starts then (the model had read the payload in the next call, 2 µs
    later: the 'pulses start' and 'state period_us' of the 100 000-stream run).  The same whether the
    payload is written after the model ran the call or before."""
    late = _v2(PAYLOAD_DURING_ITS_COMMAND_CALL, 5100.0)
    ahead = ModelSideV2(timer_origin_us=TIMER_ORIGIN_US, hv513_count=4)
    for at_us, data in PAYLOAD_DURING_ITS_COMMAND_CALL:
        ahead.emu.write(bytes.fromhex(data), at_us)
    ahead.advance_to(5100.0)
    for side in (late, ahead):
        assert [s.start_ns for s in side.emu.scans if s.start_ns > 5_000_000][:2] == [5_038_000, 5_057_200]
        assert side.emu.applied[-1][:2] == (5_034_000, OpcodeV2.FREQUENCY)


# 32 electrodes of sense width 214 (7.2 ms scans), pulse width 65535, then 0xFF and 0xF5 (random seed 20543,
# minimal, but for its last write): 0xF5 is answered at 11 009.45 us, just before the alarm of 11 010.25 us
POLL_AFTER_A_REPLY = [
    (2000.5, "f9fffc20f5f8d6fa0000"),
    (2546.995, "fa0100"),
    (2546.995, "fafffffff5"),
    (12999.82, "fdfef8fffb96fffa"),
]


def test_v1_2_a_poll_the_alarm_pre_empts_sleeps_to_the_tick_after_the_scan() -> None:
    """runEtactileKit() returns after answering 0xF5 without vTaskDelay(1), so the loop polls again at once
    (Serial.available(), 2 µs, then vTaskDelay(1)); the alarm of 11 010.25 µs pre-empts that poll, so after
    the scan (to 18 207.7 µs) and the rest of the poll the loop sleeps to the 19 000 µs tick: the bytes that
    arrived during the scan are read from then (the model had read them as the scan returned: the 'state
    rx_unread' of the 100 000-stream run)."""
    side = _v1_2(POLL_AFTER_A_REPLY, 18900.0)
    assert side.observe(18900.0).state["rx_unread"] == 8
    side.advance_to(21000.0)
    assert [(c.name, c.effect_us) for c in side.emu.commands][-3:] == [
        ("POLARITY", 19006.0),
        ("SENSE_WIDTH", 20006.0),
        ("PULSE_HEIGHT", 21009.0),
    ]


def test_v1_2_a_spin_on_a_half_u16_reads_at_its_next_check_for_two_bytes() -> None:
    """0xF6 with one byte of its u16: runEtactileKit() spins, ``isDataAvailable() > 0`` then ``>= 2``, 2 µs
    each, for 2 s, pre-empted by the scans; the second byte arrives at 2 073 447.451 µs, inside a check for
    two bytes begun before it, so the next one (from 2 073 448.4 µs) finds it and setPeriodUs() runs at
    2 073 452.4 µs, where its scan starts (the model had restarted the spin at the arrival: 2 073 453.451
    µs, the 'pulses start' of the 100 000-stream run, random seed 31686)."""
    side = _v1_2([(4136.06, "fc01f9"), (5173.543, "fef6ff"), (2073447.451, "ff")], 2073470.0)
    assert [(c.name, c.effect_us) for c in side.emu.commands][-1] == ("FREQUENCY", 2073452.4)
    assert side.emu.runs[-1].start_ns == 2_073_452_400


def test_v1_2_an_unknown_byte_waits_for_the_rest_of_a_pre_empted_check() -> None:
    """0xF8 147 is read by 11 009 µs; the payload loop's last check is pre-empted by the scan of 11 010.25 µs
    (5.05 ms), so after it the check's rest runs, then vTaskDelay(1) sleeps to the 17 000 µs tick, where the
    unknown 0x1E is read (3 µs) and then 0xF6, whose setPeriodUs() runs at 17 012 µs (the model's run of
    calls that skip unknown bytes had read 0x1E as the scan returned: 17 009 µs, random seed 74129)."""
    writes = [(3249.849, "fdfff9c1"), (3299.849, "fdfffc1cf702fafffffc20"), (3299.849, "e6f8931e")]
    side = _v1_2([*writes, (10801.614, "f6fff8")], 17100.0)
    assert [(c.name, c.effect_us) for c in side.emu.commands][-1] == ("FREQUENCY", 17012.0)
    assert side.emu.runs[-1].start_ns == 17_012_000


# 0xF6 65534 (a 15 us alarm), then 0xF6 0 whose call (6000-6007 us) ends on the alarm (random seed 3392)
IGNORED_RATE_ON_THE_ALARM = [(4823.451, "fefef6fefff8b2"), (5853.361, "f600"), (5853.361, "00fb00fd01")]


def test_v2_an_ignored_rate_calls_no_set_period_and_the_alarm_at_its_end_is_the_loop_s_own() -> None:
    """``if (rcv != 0) setPeriodUs(...)``: 0xF6 0 stores nothing and reaches no read point after its u16, so
    the alarm of 6007 µs, where its call ends, is taken at the loop's next call, and the scans stay on the
    15 µs grid (the model had counted setPeriodUs' read point for it, and stopped on its own check that
    an alarm inside a call comes at one)."""
    side = _v2(IGNORED_RATE_ON_THE_ALARM, 6100.0)
    starts = [s.start_ns for s in side.emu.scans if 5_990_000 <= s.start_ns <= 6_040_000]
    assert starts == [5_992_000, 6_007_000, 6_022_000, 6_037_000]
    assert side.emu.applied[-3][:2] == (6_000_000, OpcodeV2.FREQUENCY)
