"""The timed emulator: parser rhythm, link and queue, effect times, first pulses, torn scans, overruns,
the watchdog, extreme inputs — and the golden vectors reached through the timed drive."""

from __future__ import annotations

import json
import random
from pathlib import Path

import pytest

from tactdeform_hw.emulator.firmware.hazards import HazardKind
from tactdeform_hw.emulator.firmware.scan import ScanConfig
from tactdeform_hw.emulator.timed.link import Delivery, LinkFilter, UartLink, UsbFsLink
from tactdeform_hw.emulator.timed.model_v1_2 import TimedEmulator, configuration_bytes, pattern_latency
from tactdeform_hw.emulator.timed.timing import TimingModel
from tactdeform_hw.errors import LimitError
from tactdeform_hw.protocol import commands as c
from tactdeform_hw.protocol.constants import Opcode

VECTORS = Path(__file__).resolve().parent / "data" / "protocol_vectors.jsonl"


def kinds(emu: TimedEmulator) -> list[HazardKind]:
    return [h.kind for h in emu.hazards]


def configured(
    cfg: ScanConfig, rate: int, link: str = "usb", spacing_us: float = 20_000.0, **kw: object
) -> TimedEmulator:
    """A device configured the way a careful host does it: commands in separate writes, well apart."""
    emu = TimedEmulator(link=link, **kw)  # type: ignore[arg-type]
    data = configuration_bytes(cfg, rate)
    t = 0.0
    for cmd in c_split(data):
        emu.write(cmd, t)
        t += spacing_us
    return emu


def settled(emu: TimedEmulator) -> list:  # type: ignore[type-arg]
    """Cycles that started after the last command took effect."""
    last = max(cmd.effect_us for cmd in emu.commands if cmd.effect_us is not None)
    return [cy for cy in emu.reports.cycles() if cy.start_us > last]


def c_split(data: bytes) -> list[bytes]:
    from tactdeform_hw.protocol.decoder import decode

    return [d.raw for d in decode(data)]


# --- acceptance: the TactDeform setting, through commands ---------------------------------------------------


@pytest.mark.parametrize(("discharge", "overrun"), [(45, False), (50, True)])
def test_tactdeform_setting_over_usb(discharge: int, overrun: bool) -> None:
    cfg = ScanConfig.make(32, 1, pulse_width_us=200, discharge_us=discharge, rate_hz=125)
    emu = configured(cfg, 125)
    emu.advance_to(400_000)
    assert all(cmd.in_sync and cmd.effect_us is not None for cmd in emu.reports.commands)
    cycles = settled(emu)
    assert len(cycles) > 15
    if not overrun:
        assert all(cy.duration_us == pytest.approx(7850.25) and not cy.overrun for cy in cycles)
        assert all(cy.interval_us == pytest.approx(8000.0) for cy in cycles[:-1])
        assert HazardKind.OVERRUN not in kinds(emu)
    else:
        assert all(cy.duration_us == pytest.approx(8010.25) and cy.overrun and cy.starved for cy in cycles)
        assert all(cy.interval_us == pytest.approx(8010.25) for cy in cycles[:-1])  # back to back
        assert HazardKind.OVERRUN in kinds(emu)
        # the main loop starves: a command sent now is never read
        emu.write(c.encode_pulse_height(50))
        emu.advance_to(600_000)
        assert emu.registers.pulse_height == 100 and len(emu.queue) == 3


def test_skip_policy_keeps_the_period_grid() -> None:
    cfg = ScanConfig.make(32, 1, discharge_us=50, rate_hz=125)
    emu = TimedEmulator(model=TimingModel(overrun_policy="skip"))
    emu.configure(cfg)
    emu.advance_to(100_000)
    starts = [cy.start_us for cy in emu.reports.cycles()]
    assert starts[:3] == [8000.0, 24000.0, 40000.0]


# --- the parser's rhythm ----------------------------------------------------------------------------------


def test_a_configuration_burst_takes_one_tick_per_command() -> None:
    emu = TimedEmulator(link="usb")
    cfg = ScanConfig.make(32, 1)
    emu.write(configuration_bytes(cfg, 125))
    emu.advance_to(50_000)
    effects = [cmd.effect_us for cmd in emu.commands]
    assert len(effects) == 9
    ticks = [int(e // 1000) for e in effects]  # each command in its own RTOS tick
    assert all(b > a for a, b in zip(ticks, ticks[1:]))
    assert effects[-1] - effects[0] >= 8000.0
    # effect = the RTOS tick after arrival + the call's reads: Serial.available() (2 us) and the command
    # byte (1 us), then the payload loop's Serial.available() and the payload byte
    first = emu.commands[0]
    assert first.arrival_us is not None and first.effect_us == pytest.approx(2000.0 + 2 * (2.0 + 1.0))


def test_replies_are_immediate_and_travel_back_over_the_link() -> None:
    emu = TimedEmulator(link="uart")
    emu.configure(ScanConfig.make(4, 1))
    emu.advance_to(20_000)  # two scans: voltages filled
    emu.write(c.MEASURE_REQUEST)
    emu.advance_to(emu.now_us + 2000)
    reply = emu.read_tx()
    assert reply == c.encode_measure_reply(emu.registers.voltage[:4])
    assert all(v > 0 for v in emu.registers.voltage[:4])
    rep = emu.commands[-1]
    assert rep.name == "MEASURE" and rep.reply_us == pytest.approx(
        rep.effect_us + 8 * 10 * 1e6 / 921600 / 1, abs=0.01
    )
    assert emu.read_tx() == b"" and emu.in_waiting == 0


def test_half_u16_spins_until_the_second_byte_then_completes_at_once() -> None:
    emu = TimedEmulator(link="uart")
    emu.write(bytes([Opcode.PULSE_HEIGHT, 0x2C]))
    emu.advance_to(10_000)
    assert HazardKind.U16_WAITING in kinds(emu) and emu.registers.pulse_height == 0
    emu.write(b"\x01", 15_000.0)
    emu.advance_to(20_000)
    assert emu.registers.pulse_height == 0x12C
    rep = emu.commands[-1]
    # no wait for a tick: the spin's checks (isDataAvailable() > 0, then >= 2, 2 µs each) run on in the
    # main loop's time between scans; the byte lands at 15 010.85 µs, during a check for two bytes begun at
    # 15 010.35 µs, so the next one, from 15 014.35 µs, finds it, and the two bytes are read by 15 018.35 µs
    landed = 15_000 + 10 * 1e6 / 921600
    assert rep.effect_us == pytest.approx(15_018.35, abs=1e-6)
    assert landed < rep.effect_us - 2 * 2.0 - 2 * 1.0 < landed + 2 * 2.0  # not at once: at the next check


def test_pattern_with_zero_electrodes_locks_and_the_queue_fills() -> None:
    emu = TimedEmulator(link="usb")
    emu.write(c.encode_pattern(b"") + bytes(300))
    emu.advance_to(20_000)
    assert emu.parser.locked and HazardKind.PARSER_LOCKED in kinds(emu)
    assert len(emu.queue) == 255  # 256 arrived; the parser read the 0xFE and never reads again
    assert sum(lo.count for lo in emu.losses) == 301 - 256
    assert "locks the parser" in emu.commands[0].note
    emu.write(c.encode_polarity(0))
    emu.advance_to(40_000)
    assert len(emu.queue) == 256 and emu.losses[-1].count == 1 and emu.registers.polarity == 1
    assert HazardKind.UNREAD_WHILE_LOCKED in kinds(emu)


def test_a_frequency_whose_alarm_the_counter_has_passed_fires_at_once() -> None:
    emu = TimedEmulator(link="uart")
    emu.write(c.encode_frequency(1000), 5_000.0)  # counter at ~6 ms > 1 ms alarm
    emu.advance_to(20_000)
    rep = emu.commands[-1]
    starts = [cy.start_us for cy in emu.reports.cycles()]
    assert starts[0] == pytest.approx(rep.effect_us) and starts[1] == pytest.approx(rep.effect_us + 1000)


# --- the queue: a burst that outruns the parser ------------------------------------------------------------


def test_ten_patterns_at_once_over_usb_overflow_the_queue_and_desynchronise() -> None:
    cfg = ScanConfig.make(32, 1)
    emu = configured(cfg, 125)
    t0 = 300_000
    emu.advance_to(t0)
    rng = random.Random(3)
    burst = b"".join(c.encode_pattern([rng.choice([0, 1]) for _ in range(32)]) for _ in range(10))
    start = emu.host_offset
    emu.write(burst, t0)
    emu.advance_to(t0 + 140_000)
    losses = emu.losses
    assert [lo.reason for lo in losses] == ["queue_full", "queue_full"]
    assert sum(lo.count for lo in losses) == 330 - 256
    first = losses[0]
    assert first.host_offset == start + 256  # the queue was empty: byte 256 is the first lost
    assert first.data == burst[256 : 256 + first.count] and t0 + 1000 < first.time_us < t0 + 2000
    assert first.cut_command == {
        "name": "PATTERN",
        "host_offset": start + 231,
        "bytes_before_loss": 25,
        "length": 33,
    }
    assert HazardKind.QUEUE_OVERFLOW in kinds(emu)
    # seven whole patterns were read; the eighth waits for 8 more payload bytes ...
    assert sum(1 for cmd in emu.commands if cmd.opcode == Opcode.PATTERN and cmd.host_offset >= start) == 7
    assert emu.parser.cmd == Opcode.PATTERN and emu.parser.count == 24
    assert "not back in step yet; parser now reading PATTERN payload 24/32" in emu.losses[0].describe()
    # ... so the host's next commands become pattern payload: the parser is out of step
    sent = (
        c.encode_pulse_height(50) + c.encode_discharge(45) + c.encode_polarity(1) + c.encode_pulse_width(200)
    )
    emu.write(sent, t0 + 140_000)
    emu.advance_to(t0 + 240_000)
    after = emu.losses[0]
    assert after.followed[0]["name"] == "PATTERN" and not after.followed[0]["in_sync"]
    assert bytes(emu.registers.stim_pattern[24:32]) == sent[:8]
    assert emu.registers.pulse_height == 100 and emu.registers.discharge_time == 45
    assert HazardKind.PATTERN_HOLDS_COMMAND_BYTE in kinds(emu)
    # the next command the host sends is read in step again
    emu.write(c.encode_sense_width(7), t0 + 240_000)
    emu.advance_to(t0 + 340_000)
    assert after.resync_host_offset == emu.host_offset - 2 and emu.registers.sense_pulse_width == 7
    # the width's two bytes (0xC8 0x00) were left over after the pattern: read as unknown commands
    assert any(h.kind == HazardKind.UNKNOWN_BYTES and h.detail == {"count": 2} for h in emu.hazards)


# --- effects and first pulses ---------------------------------------------------------------------------


def test_first_pulse_per_channel_after_a_pattern_update() -> None:
    cfg = ScanConfig.make(32, 1, rate_hz=125)
    emu = TimedEmulator(link="usb")
    emu.configure(cfg)
    emu.advance_to(100_000)
    new = [0, 1] * 16
    emu.write(c.encode_pattern(new), 100_000)
    emu.advance_to(150_000)
    rep = emu.commands[-1]
    assert rep.value == bytes(new) and rep.in_sync
    assert rep.wire_us + rep.loop_wait_us + rep.scan_wait_us == pytest.approx(rep.latency_us)
    # the first scan after the effect, each channel at its own offset within the scan
    scan = next(cy for cy in emu.reports.cycles() if cy.start_us > rep.effect_us)
    from tactdeform_hw.emulator.firmware.scan import channel_offsets_ns

    offs = channel_offsets_ns(ScanConfig.make(32, new), emu.model)[1]
    assert [ch.first_pulse_us for ch in rep.channels] == pytest.approx(
        [scan.start_us + o / 1000 for o in offs]
    )
    assert rep.first_pulse_us == pytest.approx(scan.start_us + offs[0] / 1000)


@pytest.mark.parametrize("link", ["usb", "uart"])
def test_latency_of_a_32_electrode_pattern_is_wire_plus_tick_plus_scan(link: str) -> None:
    cfg = ScanConfig.make(32, 1)
    lat = pattern_latency(cfg, link, phases=8)
    assert lat["felt"] == 8
    for run in lat["runs"]:
        if run["mid_copy"]:  # a scan inside the copy lit channel 0 before the pattern's last byte was stored
            assert run["scan_wait_us"] is None
            assert run["first_channel_us"] < run["wire_us"] + run["loop_wait_us"]
        else:
            assert run["wire_us"] + run["loop_wait_us"] + run["scan_wait_us"] == pytest.approx(
                run["first_channel_us"]
            )
        assert run["last_channel_us"] > run["first_channel_us"]
    assert lat["mid_copy"] == sum(run["mid_copy"] for run in lat["runs"])
    # bytes still arriving over a UART when a scan takes the processor: channel 0 is felt mid-copy
    assert (lat["mid_copy"] > 0) == (link == "uart")
    if link == "uart":
        assert lat["wire_us"]["min"] == pytest.approx(33 * 10 * 1e6 / 921600, abs=0.01)
    else:
        assert 0 < lat["wire_us"]["min"] and lat["wire_us"]["max"] <= 1000 + 60
    # the scan fills 7850 of 8000 us: the parser only runs after a scan, so the loop wait can reach a period
    assert lat["loop_wait_us"]["max"] > 5000


# --- torn scans --------------------------------------------------------------------------------------------


def test_pattern_bytes_trickling_in_over_uart_tear_a_scan() -> None:
    # 255 channels: the pattern takes 2.8 ms on the wire; the parser reads it a tick at a time
    emu = TimedEmulator(link="uart")
    emu.configure(ScanConfig.make(255, 0, discharge_us=0, rate_hz=125))
    emu.advance_to(12_000)
    emu.write(c.encode_pattern([3] * 255), 12_900.0)  # 3: a sense pulse too, the scan keeps its length
    emu.advance_to(60_000)
    torn = emu.reports.torn()
    assert len(torn) == 1
    t = torn[0]
    assert 0 < t.new_channels < 255 and t.changed_channels == t.new_channels
    assert t.old_channels == 255 - t.new_channels
    rep = next(cmd for cmd in emu.commands if cmd.opcode == Opcode.PATTERN)
    assert rep.value == bytes([3] * 255) and rep.in_sync
    early = [ch.first_pulse_us for ch in rep.channels[: t.new_channels]]
    late = [ch.first_pulse_us for ch in rep.channels[t.new_channels :]]
    nxt = t.time_us + 8000
    assert all(t.time_us < x < nxt for x in early) and all(x > nxt for x in late)


def test_an_alarm_landing_mid_read_interrupts_the_call_and_tears_the_scan() -> None:
    model = TimingModel(tick_phase_us=850.0)
    emu = TimedEmulator(model=model, stimulation=True)
    emu.configure(ScanConfig.make(255, 1, pulse_width_us=10, discharge_us=0, rate_hz=10))
    emu.deliver(c.encode_pattern([2] * 255), 99_000.0)
    emu.advance_to(400_000)
    assert emu.interrupted_calls == 1
    torn = emu.reports.torn()
    assert len(torn) == 1 and torn[0].time_us == 100_000.0
    k = torn[0].new_channels
    # the call began at the tick 99 850 us: Serial.available() (2 us) and the command byte (1 us), then
    # per pattern byte the loop's Serial.available() and the byte (3 us); the alarm at 100 000 us comes
    # as the 49th byte's read ends (99 853 + 3 x 49): a read ending at the alarm has stored its byte, as
    # in the host build (the interrupt is taken at the loop's next call, the 50th byte's check)
    assert k == 49
    rep = emu.commands[-1]
    assert rep.channels[k - 1].first_pulse_us < 200_000 < rep.channels[k].first_pulse_us


def torn_hazards(emu: TimedEmulator) -> list:  # type: ignore[type-arg]
    return [h for h in emu.hazards if h.kind == HazardKind.TORN_PATTERN]


def test_a_torn_scan_is_recorded_as_a_torn_pattern_hazard() -> None:
    model = TimingModel(tick_phase_us=850.0)
    emu = TimedEmulator(model=model)
    emu.configure(ScanConfig.make(255, 1, pulse_width_us=10, discharge_us=0, rate_hz=10))
    emu.advance_to(50_000)
    emu.deliver(c.encode_electrode_num(255), 60_000.0)  # the pattern command is byte 2 since power-on
    emu.deliver(c.encode_pattern([1] * 200 + [2] * 55), 99_000.0)
    emu.advance_to(400_000)
    torn = emu.reports.torn()
    hz = torn_hazards(emu)
    assert len(torn) == 1 and len(hz) == 1
    h, t = hz[0], torn[0]
    assert h.offset == 2 and h.time_us == t.time_us == 100_000.0
    k = t.new_channels
    assert 0 < k < 200  # only channels the new pattern leaves unchanged were read before the scan
    assert h.detail == {
        "first_cycle": t.cycle,
        "cycles": 1,
        "cycle_start_us": 100_000.0,
        "command_host_offset": -1,
        "new_channels": k,
        "old_channels": 255 - k,
        "changed": [],
    }
    # once the pattern is whole, nothing more is torn
    assert all(cy.torn is (cy.index == t.cycle) for cy in emu.reports.cycles())


def test_a_pattern_trickling_in_over_several_scans_gives_one_hazard_per_torn_cycle() -> None:
    # 1920 baud: a byte every 5.2 ms, so each 8 ms scan catches the pattern a byte or two further on
    emu = TimedEmulator(link=UartLink(1920))
    emu.configure(ScanConfig.make(8, 1, pulse_width_us=200, discharge_us=45, rate_hz=125))
    emu.advance_to(12_000)
    new = [0, 2, 1, 0, 3, 1, 2, 0]
    emu.write(c.encode_pattern(new), 12_100.0)
    emu.advance_to(200_000)
    torn = emu.reports.torn()
    hz = torn_hazards(emu)
    assert len(torn) > 3 and len(hz) == len(torn) == emu.reports.summary()["torn_scans"]
    for h, t in zip(hz, torn):
        d = h.detail
        assert (d["first_cycle"], d["cycles"], d["cycle_start_us"], h.time_us) == (
            t.cycle,
            1,
            t.time_us,
            t.time_us,
        )
        assert h.offset == 0 and d["command_host_offset"] == 0 == t.command_host_offset
        assert (d["new_channels"], d["old_channels"]) == (t.new_channels, t.old_channels)
        k = d["new_channels"]
        assert d["changed"] == [[ch, 1, new[ch]] for ch in range(k) if new[ch] != 1]
        assert len(d["changed"]) == t.changed_channels
    assert [h.detail["new_channels"] for h in hz] == sorted(h.detail["new_channels"] for h in hz)


def test_a_pattern_stalled_mid_read_is_one_torn_record_for_the_stretch() -> None:
    # the host stops after 10 of the pattern's 33 bytes: every later scan is torn the same way
    emu = TimedEmulator(link="uart")
    emu.configure(ScanConfig.make(32, 0, discharge_us=0, pulse_width_us=1, rate_hz=1000))
    emu.advance_to(12_000)
    emu.write(c.encode_pattern([1] * 32)[:10], 12_100.0)
    emu.advance_to(112_000)
    torn = emu.reports.torn()
    hz = torn_hazards(emu)
    assert len(torn) > 90 and len(hz) == 1
    assert hz[0].detail["first_cycle"] == torn[0].cycle and hz[0].detail["cycles"] == len(torn)
    assert hz[0].detail["new_channels"] == 9 and hz[0].detail["changed"] == [[ch, 0, 1] for ch in range(9)]
    emu.advance_to(212_000)  # the stretch goes on: still one record, with every cycle counted
    assert len(torn_hazards(emu)) == 1
    assert torn_hazards(emu)[0].detail["cycles"] == emu.reports.summary()["torn_scans"] > len(torn)


# --- the watchdog ----------------------------------------------------------------------------------------


def test_a_scan_longer_than_300ms_reboots_the_device() -> None:
    cfg = ScanConfig.make(255, 1, pulse_width_us=65535, discharge_us=0, rate_hz=1)
    emu = configured(cfg, 1)
    emu.advance_to(3_000_000)
    wd = [h for h in emu.hazards if h.kind == HazardKind.WATCHDOG_RESET]
    assert len(wd) == 1
    cycles = emu.reports.cycles()
    cut = [cy for cy in cycles if cy.watchdog]
    assert len(cut) == 1 and cut[0].duration_us == 300_000.0 and cut[0].pulses == 5  # 65.5 ms each
    assert wd[0].time_us == pytest.approx(cut[0].start_us + 300_000)
    assert emu.reboots == 1 and emu.state().electrode_num == 0 and emu.state().period_us == 10_000.0
    # afterwards: power-on scans every 10 ms
    later = [cy for cy in cycles if cy.start_us > wd[0].time_us]
    assert later and all(cy.interval_us in (None, 10_000.0) for cy in later)


def test_bytes_arriving_while_the_device_boots_are_lost() -> None:
    emu = TimedEmulator(link="uart", model=TimingModel(boot_us=50_000))
    emu.reset()
    emu.write(c.encode_polarity(0), 10_000)
    emu.write(c.encode_discharge(9), 60_000)
    emu.advance_to(80_000)
    assert [lo.reason for lo in emu.losses] == ["rebooting", "rebooting"]
    assert emu.registers.discharge_time == 9 and emu.registers.polarity == 1


# --- extreme and stiff inputs ------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("name", "cfg", "rate"),
    [
        ("255 electrodes", ScanConfig.make(255, 1, rate_hz=10), 10),
        ("width 65535", ScanConfig.make(2, 1, pulse_width_us=65535, rate_hz=1), 1),
        ("1 Hz", ScanConfig.make(32, 1, rate_hz=1), 1),
        ("65535 Hz", ScanConfig.make(32, 1, rate_hz=65535), 65535),
        ("discharge 0", ScanConfig.make(32, 1, discharge_us=0), 125),
        ("discharge 255", ScanConfig.make(32, 1, discharge_us=255), 125),
        ("sense everywhere", ScanConfig.make(32, 0, sense_height_raw=255, sense_width_us=255), 125),
    ],
)
def test_extreme_configurations_run_with_honest_reports(name: str, cfg: ScanConfig, rate: int) -> None:
    emu = configured(cfg, rate)
    emu.advance_to(3_000_000)
    s = emu.reports.summary()
    assert s["scans"] > 0 and s["bytes_lost"] == 0
    assert all(cmd.in_sync for cmd in emu.commands)
    from tactdeform_hw.emulator.records.reports import Budget

    b = Budget.of(cfg, emu.model, rate)
    steady = settled(emu)
    assert steady
    assert all(cy.duration_us == pytest.approx(b.scan_us) for cy in steady)
    assert all(cy.overrun == b.overrun for cy in steady)
    if name == "65535 Hz":
        assert b.overrun and s["overruns"] == sum(1 for cy in emu.reports.cycles() if cy.overrun) > 100
        # every overrun is counted: the hazard records cover each overrunning cycle exactly once
        over = [h for h in emu.hazards if h.kind == HazardKind.OVERRUN]
        assert sum(h.detail["cycles"] for h in over) == s["overruns"]
    if name == "255 electrodes":
        pulses = emu.reports.pulse_table(t0_us=steady[0].start_us)
        beyond = pulses["channel"] >= 32
        assert (pulses["n_outputs"][beyond] == 0).all() and (pulses["current_ua"][beyond] == 0).all()
        assert HazardKind.CHANNELS_BEYOND_HV513 in kinds(emu)
    if name == "sense everywhere":
        assert HazardKind.SENSE_CURRENT in kinds(emu)
        assert (emu.reports.pulse_table(t0_us=steady[0].start_us)["current_ua"] == 1020 * 10).all()


def test_polarity_flips_mid_stream_change_the_next_scan() -> None:
    emu = TimedEmulator(link="usb")
    emu.configure(ScanConfig.make(4, 1, rate_hz=500))
    for i, t in enumerate(range(10_000, 60_000, 5_000)):
        emu.write(c.encode_polarity(i % 2), float(t))
    emu.advance_to(70_000)
    pol_cmds = [cmd for cmd in emu.commands if cmd.opcode == Opcode.POLARITY]
    assert len(pol_cmds) == 10 and all(cmd.first_pulse_us is not None for cmd in pol_cmds)
    table = emu.reports.pulse_table()
    for cmd in pol_cmds:
        at = table["start_us"] == cmd.first_pulse_us
        assert table["pol"][at].tolist() == [cmd.value]


# --- the fault-injection hook ---------------------------------------------------------------------------


def test_a_link_filter_sees_and_changes_every_delivery() -> None:
    class Late(LinkFilter):
        def transform(self, deliveries: list[Delivery]) -> list[Delivery]:
            return [Delivery(d.t_ns + 5_000_000, d.data, d.host_offset, d.sent_ns) for d in deliveries]

    emu = TimedEmulator(link=Late(UsbFsLink()))
    emu.write(c.encode_discharge(30))
    emu.advance_to(20_000)
    rep = emu.commands[0]
    assert rep.arrival_us == pytest.approx(1000 + 5000 + UsbFsLink()._packet_ns(2) / 1000)
    assert isinstance(emu.tx_link, UsbFsLink)
    assert isinstance(TimedEmulator(link=UartLink()).tx_link, UartLink)


def test_writes_must_come_in_time_order() -> None:
    emu = TimedEmulator()
    emu.advance_to(1000)
    with pytest.raises(LimitError):
        emu.write(b"\x00", 500)
    emu.write(b"\x00", 2000)
    with pytest.raises(LimitError):
        emu.write(b"\x00", 1500)
    with pytest.raises(LimitError):
        emu.advance_to(10)


# --- the same parser: golden vectors through the timed drive ---------------------------------------------


def _golden() -> list[dict[str, object]]:
    return [json.loads(line) for line in VECTORS.read_text().splitlines() if line.strip()]


@pytest.mark.parametrize("stimulation", [False, True])
def test_golden_vectors_through_the_timed_drive(stimulation: bool) -> None:
    """Call by call, with ticks, splits and (with stimulation) scans interleaved, the parser reaches every
    golden state (a queue large enough for the stream, no watchdog, scans that leave the loop time)."""
    model = TimingModel(rx_queue_bytes=1 << 20, watchdog_us=None, overrun_policy="skip")
    interrupted = 0
    for v in _golden():
        board = v["board"]  # type: ignore[index]
        emu = TimedEmulator(board["kind"], board["switching_boards"], model=model, stimulation=stimulation)
        emu.deliver(bytes.fromhex(v["stream"]), 0)  # type: ignore[arg-type]
        assert emu.run_until_idle(limit_us=3600e6, step_us=1e6)
        st, exp = emu.state().as_dict(), v["expect"]  # type: ignore[assignment]
        for k, want in exp.items():  # type: ignore[union-attr]
            if k == "tx":
                got = emu.read_tx()
                if stimulation:
                    assert len(got) == len(bytes.fromhex(want))  # voltages come from the scans now
                else:
                    assert got.hex() == want
            elif k == "period_us":
                assert st[k] == pytest.approx(want, abs=1e-4)
            else:
                assert st[k] == want, k
        interrupted += emu.interrupted_calls
    if stimulation:
        assert interrupted > 0  # some calls really were cut by an alarm
