"""Firmware v2 in time: scans, the paused alarm of 0xF5, the 2 s timeout, mode 2, upstream-paced hosts."""

from __future__ import annotations

import json

import pytest

from tactdeform_hw.emulator import HazardKind
from tactdeform_hw.emulator.firmware.firmware_scan import FirmwareScanConfig, scan_duration_us
from tactdeform_hw.emulator.firmware.registers import V2_SCAN_REGISTERS
from tactdeform_hw.emulator.timed.model_v2 import TimedEmulatorV2, pattern_in_force_v2
from tactdeform_hw.protocol.commands import V2_COMMANDS as c

from .conftest import DATA

SETUP = (
    c.encode_electrode_num(32)
    + c.encode_stim_mode(0)
    + c.encode_pulse_width(200)
    + c.encode_discharge(45)
    + c.encode_frequency(125)
    + c.encode_pattern([100] * 32)
)


def test_tactdeform_scans_run_every_period_at_the_budgeted_length() -> None:
    emu = TimedEmulatorV2()
    emu.write(SETUP, 0.0)
    emu.advance_to(50_000.0)
    scans = [s for s in emu.scans if s.electrode_num == 32]
    assert len(scans) >= 5
    want = scan_duration_us(FirmwareScanConfig(32, [100] * 32, 200, 45, frequency_hz=125), "v2")
    assert all(s.duration_ns == round(want * 1000) for s in scans)
    assert {b.start_ns - a.start_ns for a, b in zip(scans, scans[1:], strict=False)} == {8_000_000}
    assert all(s.codes == (100,) * 32 for s in scans)
    assert not [h for h in emu.hazards if h.kind is HazardKind.OVERRUN]


def test_mode_2_with_a_zero_pattern_still_stimulates_and_is_a_hazard() -> None:
    emu = TimedEmulatorV2()
    emu.write(
        c.encode_electrode_num(4)
        + c.encode_sense_height(10)
        + c.encode_sense_width(10)
        + c.encode_stim_mode(2)
        + c.encode_pattern([0] * 4),
        0.0,
    )
    emu.advance_to(40_000.0)
    last = emu.scans[-1]
    assert last.heights == (0, 0, 0, 0) and last.live_channels() == [0, 1, 2, 3] and last.codes == (10,) * 4
    hz = [h for h in emu.hazards if h.kind is HazardKind.MODE_SENSE_ALL and "scan" in h.detail]
    assert len(hz) == 1 and hz[0].detail["channels"] == [0, 1, 2, 3]  # the first scan that delivered it
    emu.write(c.encode_stim_mode(0))
    emu.advance_to(80_000.0)
    assert emu.scans[-1].live_channels() == []  # mode 0: a zero pattern is off


def test_hv513_request_pauses_the_stimulation_alarm() -> None:
    emu = TimedEmulatorV2()
    emu.write(c.encode_electrode_num(1) + c.encode_pattern([50]), 0.0)
    emu.advance_to(10_500.0)
    assert [s.start_ns for s in emu.scans] == [10_000_000]
    # sent so that the parser reads it just before the next alarm (20 ms): the scan waits for the reply
    emu.write(c.HV513_COUNT_REQUEST, 17_500.0)
    emu.advance_to(31_000.0)
    second = emu.scans[1].start_ns
    assert 20_000_000 < second <= 20_010_000 and emu.read_tx() == b"\x04"
    # the late alarm fires on re-enable and the auto-reload counts the next period from there
    assert emu.scans[2].start_ns == second + 10_000_000


def test_a_cut_command_times_out_and_later_commands_apply() -> None:
    emu = TimedEmulatorV2()
    emu.write(c.encode_electrode_num(2) + b"\xfa", 0.0)
    emu.write(c.SYNC_CHECK, 100_000.0)  # eaten as the first payload byte: no reply
    emu.advance_to(2_200_000.0)
    assert emu.read_tx() == b"" and not emu.state().command_in_progress
    assert [h for h in emu.hazards if h.kind is HazardKind.COMMAND_TIMEOUT]
    emu.write(c.SYNC_CHECK + c.encode_pulse_width(150))
    emu.advance_to(2_300_000.0)
    assert emu.read_tx() == b"\x02" and emu.state().pulse_width_us == 150


VECTORS = [
    json.loads(line) for line in (DATA / "protocol_vectors_v2.jsonl").read_text().splitlines() if line.strip()
]


def _slow_enough(vector: dict) -> bool:
    """No rate above 1 kHz on the way: faster scans can starve the main loop (as on the board), and the
    vectors were computed without scans."""
    from tactdeform_hw.protocol.decoder import decode
    from tactdeform_hw.protocol.firmware import V2

    return all(
        not (d.opcode == 0xF6 and isinstance(d.value, int) and d.value > 1000)
        for d in decode(bytes.fromhex(vector["stream"]), 0, V2)
    )


UPSTREAM = [
    v
    for v in VECTORS
    if "arrivals" not in v
    and "final_time_us" not in v
    and not v["category"].startswith("overflow")
    and _slow_enough(v)
]


@pytest.mark.parametrize("vector", UPSTREAM[::12], ids=[v["id"] for v in UPSTREAM[::12]])
def test_upstream_paced_client_gets_the_predicted_state(vector: dict) -> None:
    """8-byte chunks 3 ms apart over USB, with scans running: the state the vectors predict."""
    data = bytes.fromhex(vector["stream"])
    emu = TimedEmulatorV2()
    chunks = [data[i : i + 8] for i in range(0, len(data), 8)]
    for k, chunk in enumerate(chunks):
        emu.write(chunk, 3000.0 * k)
    emu.advance_to(3000.0 * len(chunks) + 20_000.0)
    state = emu.state()
    expect = vector["expect"]
    for key in (
        *V2_SCAN_REGISTERS,
        "timer_alarm_ticks",
        "hv513_num",
        "stim_pattern",
        "rx_pending",
        "command_in_progress",
    ):
        assert state.as_dict()[key] == expect[key], key
    tx = emu.read_tx().hex()
    if "ff" not in vector["stream"]:
        assert tx == expect["tx"]
    else:  # measure replies carry the voltages of the scans that ran meanwhile
        assert len(tx) == len(expect["tx"])


def test_pattern_in_force_is_ordered_and_upstream_pacing_is_slower() -> None:
    whole = pattern_in_force_v2([100] * 32, phases=4)
    paced = pattern_in_force_v2([100] * 32, phases=4, chunking="upstream")
    for r in (whole, paced):
        assert r["applied_us"]["min"] <= r["first_channel_us"]["min"] <= r["last_channel_us"]["min"]
    assert paced["applied_us"]["min"] >= 8 * 3000  # nine chunks, the last sent 24 ms after the first
    assert whole["applied_us"]["max"] < 10_000


def test_delivered_pulses_follow_each_electrode_and_the_biphasic_polarity() -> None:
    """Safety reads what the board delivered: per-electrode heights, both phases, the configured
    polarity first (v2), widths as the scan really made them."""
    emu = TimedEmulatorV2()
    emu.write(
        c.encode_electrode_num(3)
        + c.encode_stim_mode(1)
        + c.encode_polarity(0)
        + c.encode_pulse_width(200)
        + c.encode_pattern([100, 0, 250]),
        0.0,
    )
    emu.advance_to(15_000.0)
    rows = emu.delivered()
    assert [(r["channel"], r["code"], r["polarity"]) for r in rows] == [
        (0, 100, "cathodic"),
        (0, 100, "anodic"),
        (2, 250, "cathodic"),
        (2, 250, "anodic"),
    ]
    assert {r["width_us"] for r in rows} == {196.6}
    assert emu.peak_current_ua() == {0: 1000.0, 2: 2500.0}
    assert rows[0]["charge_nc"] == pytest.approx(1000.0 * 196.6 / 1000)


def test_width_zero_still_delivers_one_exchange() -> None:
    emu = TimedEmulatorV2()
    emu.write(c.encode_electrode_num(1) + c.encode_pulse_width(0) + c.encode_pattern([300]), 0.0)
    emu.advance_to(15_000.0)
    assert [r["width_us"] for r in emu.delivered()] == [6.6]
    assert [h.kind for h in emu.hazards if h.kind is HazardKind.SHORT_PULSE_WIDTH]


def test_a_scan_that_preempts_the_pattern_copy_is_torn_and_recorded() -> None:
    """v2 copies a complete pattern in one parser call; an alarm inside that call scans the channels
    already copied at their new heights and the rest at their old ones."""
    n = 255
    emu = TimedEmulatorV2(link="uart")
    emu.write(
        c.encode_electrode_num(n)
        + c.encode_pulse_width(20)
        + c.encode_discharge(10)
        + c.encode_frequency(30)
        + c.encode_pattern([10] * n),
        0.0,
    )
    # 511 bytes at 10.85 us each end about 32.5 ms; the parser copies them (about 0.5 ms) from its 33 ms
    # tick, and the 30 Hz alarm comes at 33.333 ms, in the middle of the copy
    emu.write(c.encode_pattern([200] * n), 26_955.0)
    emu.advance_to(80_000.0)
    torn = [h for h in emu.hazards if h.kind is HazardKind.TORN_PATTERN]
    first = emu.scans[0]
    assert first.start_ns == 33_333_000 and len(torn) == 1
    k = torn[0].detail["new_channels"]
    assert 0 < k < n and first.heights == (200,) * k + (10,) * (n - k)
    assert emu.scans[1].heights == (200,) * n  # the next scan has all of it
    assert [t for t, op, _ in emu.applied if op == 0xFE][-1] == 33_000_000


def test_a_measure_reply_carries_the_skin_models_readings_as_on_v1_2() -> None:
    """``AD = DAAD(0)`` is the ADC's reading as the pulse ends, stored unshifted (v1.2 keeps ``raw >> 2``):
    the same electrode–skin model answers on both versions, not the DAC code sent."""
    from tactdeform_hw.emulator.firmware.skin import SkinModel
    from tactdeform_hw.emulator.timed.model_v1_2 import TimedEmulator
    from tactdeform_hw.protocol.commands import V1_2_COMMANDS as c1

    def v2_readings(heights: list[int], **options: object) -> list[int]:
        emu = TimedEmulatorV2(**options)  # type: ignore[arg-type]
        setup = c.encode_electrode_num(4) + c.encode_stim_mode(0) + c.encode_pulse_width(200)
        emu.write(setup + c.encode_discharge(45) + c.encode_frequency(125) + c.encode_pattern(heights), 0.0)
        emu.advance_to(30_000.0)
        emu.write(bytes([0xFF]), 30_000.0)
        emu.advance_to(60_000.0)
        reply = emu.read_tx()
        return [int.from_bytes(reply[2 * i : 2 * i + 2], "little") for i in range(4)]

    v1 = TimedEmulator()
    setup = c1.encode_electrode_num(4) + c1.encode_pulse_height(100) + c1.encode_pulse_width(200)
    v1.write(
        setup + c1.encode_discharge(45) + c1.encode_frequency(125) + c1.encode_pattern([1, 1, 0, 1]), 0.0
    )
    v1.advance_to(30_000.0)

    got = v2_readings([100, 100, 0, 100])
    assert got != [100, 100, 0, 100]  # not the code sent
    assert [r >> 2 for r in got] == v1.registers.voltage[:4]  # v1.2's stored reading, per electrode
    assert len(set(got[:2] + got[3:])) == 3  # each electrode's own contact
    doubled = v2_readings([200, 200, 0, 200])
    assert all(1.8 * a < b < 2.2 * a for a, b in zip(got[:2] + got[3:], doubled[:2] + doubled[3:]))
    lifted = v2_readings([100, 100, 0, 100], skin=SkinModel(open_electrodes=frozenset({1})))
    assert lifted[1] > got[1] and lifted[0] == got[0]  # off the skin: the source's compliance
    assert v2_readings([100, 100, 0, 100], skin=None) == [100, 100, 0, 100]  # the host build's loop-back


@pytest.mark.parametrize(
    "change",
    [
        c.encode_pulse_width(120),
        c.encode_discharge(20),
        c.encode_polarity(0),
        c.encode_stim_mode(1),
        c.encode_stim_mode(2) + c.encode_sense_height(12) + c.encode_sense_width(30),
    ],
    ids=["pulse_width", "discharge", "polarity", "stim_mode", "sense"],
)
def test_a_register_change_that_keeps_the_pattern_is_felt_at_the_next_scan(change: bytes) -> None:
    """Most scans repeat the one before, so the model keeps the last scan: a change of any register a scan
    reads, with the pattern unchanged, must still give the scan a board set that way from the start
    gives (a stale scan here would keep delivering the old width, polarity or mode)."""
    changed = TimedEmulatorV2()
    changed.write(SETUP, 0.0)
    changed.advance_to(30_000.0)
    changed.write(change, 30_000.0)
    changed.advance_to(70_000.0)
    fresh = TimedEmulatorV2()
    fresh.write(SETUP + change, 0.0)
    fresh.advance_to(70_000.0)
    last, want = changed.scans[-1], fresh.scans[-1]
    assert (last.duration_ns, last.pulses) == (want.duration_ns, want.pulses)
    assert last.pulses != changed.scans[0].pulses or last.duration_ns != changed.scans[0].duration_ns
