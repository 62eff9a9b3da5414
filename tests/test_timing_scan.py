"""The scan engine: the firmware's statement order, its arithmetic, the HV513 chain, the template cache
against the step-through, and the electrode–skin readings."""

from __future__ import annotations

import random
from dataclasses import replace
from typing import Any

import numpy as np
import pytest

from tactdeform_hw.emulator.firmware.scan import (
    POWER_ON_CHAIN,
    ChainState,
    PulseKind,
    ScanConfig,
    ScanEngine,
    Signal,
    channel_offsets_ns,
    scan_duration_ns,
)
from tactdeform_hw.emulator.firmware.skin import SkinModel
from tactdeform_hw.emulator.records.reports import Budget
from tactdeform_hw.emulator.timed.timing import TimingModel
from tactdeform_hw.errors import ConfigurationError, LimitError
from tactdeform_hw.protocol.firmware import V1_2, V2

from .scan_reference import reference_scan

MODEL = TimingModel()


def events_of(
    cfg: ScanConfig, chain: ChainState = POWER_ON_CHAIN, outputs: int = 32
) -> list[tuple[int, int, int]]:
    T, S, V = ScanEngine(outputs=outputs).template(cfg, chain).events()
    return list(zip(T.tolist(), S.tolist(), V.tolist()))


# --- the firmware's arithmetic ------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("us", "ticks"),
    [(0, 0), (2, 0), (3, 0), (4, 2), (5, 4), (38, 70), (43, 80), (193, 380), (65528, 131050)],
)
def test_busy_wait_is_int_of_us_times_2_minus_5_4_with_a_3us_floor(us: int, ticks: int) -> None:
    assert MODEL.delay_ticks(us) == ticks
    assert MODEL.delay_ns(us) == ticks * 500


@pytest.mark.parametrize(
    ("width", "effective_us"), [(1, 6.6), (6, 6.6), (7, 6.6), (10, 6.6), (11, 7.6), (200, 196.6)]
)
def test_pulse_never_shorter_than_one_exchange(width: int, effective_us: float) -> None:
    assert MODEL.pulse_width_ns(width) == round(effective_us * 1000)
    cfg = ScanConfig.make(1, 1, pulse_width_us=width)
    p = ScanEngine().template(cfg).pulses
    assert p.width_ns.tolist() == [round(effective_us * 1000)]


def test_model_documents_every_constant_and_labels_assumptions() -> None:
    rows = MODEL.describe()
    assert all(
        r["source"] in ("firmware", "firmware comment", "platform", "assumption") and r["doc"] for r in rows
    )
    assert {"gpio_write_us", "isr_entry_us", "parser_byte_us"} <= set(MODEL.assumptions())
    assert "spi_exchange_us" not in MODEL.assumptions()
    assert MODEL.with_(gpio_write_us=0.1).gpio_ns == 100
    with pytest.raises(ConfigurationError):
        MODEL.with_(no_such_constant=1)
    with pytest.raises(LimitError):
        TimingModel(spi_exchange_us=float("nan"))
    with pytest.raises(LimitError):
        TimingModel(overrun_policy="never")


# --- acceptance: the TactDeform paper's discharge reasoning ----------------------------------------------


def test_tactdeform_setting_discharge_45_fits_the_8000us_period() -> None:
    cfg = ScanConfig.make(32, 1, pulse_width_us=200, discharge_us=45, rate_hz=125)
    b = Budget.of(cfg, MODEL, 125)
    assert b.period_us == 8000.0
    assert b.rows[0].per_channel_us == pytest.approx(245.25)  # "about 245 us per channel"
    assert b.scan_us == pytest.approx(7850.25)
    assert not b.overrun and b.margin_us > 0 and b.verdict == "fits"
    assert b.actual_rate_hz == pytest.approx(125.0)


def test_tactdeform_setting_discharge_50_overruns_the_period() -> None:
    cfg = ScanConfig.make(32, 1, pulse_width_us=200, discharge_us=50, rate_hz=125)
    b = Budget.of(cfg, MODEL, 125)
    assert b.scan_us == pytest.approx(8010.25)
    assert b.overrun and b.margin_us < 0 and b.verdict == "overrun"
    assert b.actual_rate_hz == pytest.approx(1e6 / 8010.25)  # back to back
    assert b.parser_starved


def test_skip_policy_overrun_leaves_the_main_loop_most_of_every_other_period() -> None:
    cfg = ScanConfig.make(32, 1, pulse_width_us=200, discharge_us=50, rate_hz=125)
    b = Budget.of(cfg, MODEL.with_(overrun_policy="skip"), 125)
    assert b.overrun and b.verdict == "overrun" and not b.parser_starved
    assert b.actual_rate_hz == pytest.approx(62.5)  # a scan every other period
    # 16000 - 8010.25 us outside the scan: many RTOS ticks, so no one-command-per-period limit
    assert not any("payload" in n or "only" in n for n in b.notes), b.notes
    assert any("every 2 periods" in n and "7989.75" in n for n in b.notes), b.notes


def test_skip_policy_overrun_with_less_than_a_tick_left_names_the_stride() -> None:
    cfg = ScanConfig.make(6, 1, pulse_width_us=200, discharge_us=45, rate_hz=1000)
    b = Budget.of(cfg, MODEL.with_(overrun_policy="skip"), 1000)
    gap = 2000.0 - b.scan_us
    assert b.scan_us > 1000.0 and 0 < gap < MODEL.rtos_tick_us  # overruns; two periods leave under a tick
    assert b.actual_rate_hz == pytest.approx(500.0)
    limit = [n for n in b.notes if "payload" in n]
    assert len(limit) == 1 and limit[0].endswith(
        " µs outside the scan every 2 periods: the parser reads at most one command with a payload per 2 "
        "periods"
    ), b.notes
    assert float(limit[0].split()[1]) == pytest.approx(gap, abs=0.06)
    # the same configuration fitting its period keeps the per-period wording
    fits = Budget.of(ScanConfig.make(32, 1, pulse_width_us=200, discharge_us=45, rate_hz=125), MODEL, 125)
    assert [n for n in fits.notes if "payload" in n] == [
        "only 149.8 µs per period outside the scan: the parser reads at most one command with a payload "
        "per period"
    ]


# --- acceptance: one small scan, event by event -----------------------------------------------------------


def test_four_electrode_scan_gives_the_specified_dac_and_clk_sequence() -> None:
    # pattern 1, 2, 0, 1 on a compact board with one switching board (4 HV513 = 32 outputs)
    cfg = ScanConfig.make(
        4, [1, 2, 0, 1], pulse_height=100, sense_height_raw=2, sense_width_us=20, hv513_num=4
    )
    for ev in (events_of(cfg), reference_scan(cfg).events):
        dac = [v for _, s, v in ev if s == Signal.DAC]
        assert dac == [
            100,
            0,
            0,  # ch0 monophasic: on, off, discharge
            100,
            0,
            100,
            0,
            0,  # ch1 biphasic: anodic phase, cathodic phase, discharge
            8,
            0,
            0,  # ch2 sense pulse (2 << 2 = 8), discharge
            100,
            0,
            0,  # ch3 monophasic
        ]
        # CLK pulses between LE low and LE high, with the DIN level they shift in
        groups: list[tuple[int, int]] = []
        clk = din = 0
        for _, s, v in ev:
            if s == Signal.LE and v == 0:
                clk = 0
            elif s == Signal.DIN:
                din = v
            elif s == Signal.CLK and v == 1:
                clk += 1
            elif s == Signal.LE and v == 1:
                groups.append((clk, din))
        assert groups == [(1, 1), (1, 0), (1, 0), (1, 0), (29, 0)]  # ch0 loads a 1; the clear: 32 - 3
        assert [v for _, s, v in ev if s == Signal.SEL] == [0, 1, 2, 3, -1]
        pol = [v for _, s, v in ev if s == Signal.POL]
        assert pol == [1, 1, 1, 1, 0, 1, 1, 1, 1, 1]  # ch1: POL high, phase, POL low, phase, discharge high
        assert [v for _, s, v in ev if s == Signal.BL] == [0, 1] * 4
    # times: alarm + 2 us entry + 6 GPIO writes + 3.3 us into the exchange; 196.6 us of current
    first_dac = [t for t, s, v in events_of(cfg) if s == Signal.DAC]
    assert first_dac[:2] == [5_600, 5_600 + 196_600]


# --- the template cache against the step-through ------------------------------------------------------------


def _rows(t: object) -> list[tuple[object, ...]]:
    p = t.pulses  # type: ignore[attr-defined]
    return [
        (
            int(p.channel[i]),
            int(p.kind[i]),
            int(p.start_ns[i]),
            int(p.width_ns[i]),
            int(p.code[i]),
            int(p.pol[i]),
            float(p.current_ua[i]),
            float(p.charge_nc[i]),
            int(p.voltage_code[i]),
            int(p.adc_ns[i]),
            bool(p.limited[i]),
            t.pulse_outputs[i],
        )  # type: ignore[attr-defined]
        for i in range(p.channel.size)
    ]


READINGS = [
    {"cs_writes_costed": costed, "dac_load": load}
    for costed in (False, True)
    for load in ("mid_exchange", "cs_rise")
]


@pytest.mark.parametrize("reading", READINGS, ids=lambda r: f"{r['cs_writes_costed']}-{r['dac_load']}")
def test_templates_are_identical_to_the_step_through_over_random_configurations(
    reading: dict[str, Any],
) -> None:
    """Under every reading of the exchange (the default one drawn most)."""
    model = MODEL.with_(**reading)
    rng = random.Random(4)
    for _ in range(120 if model == MODEL else 40):
        n = rng.choice([0, 1, 2, 4, 32, rng.randint(0, 255)])
        outputs = rng.choice([0, 8, 32, 64])
        mask = (1 << outputs) - 1
        cfg = ScanConfig(
            n,
            rng.randint(0, 1),
            rng.randint(0, 4095),
            rng.choice([1, 6, 7, 8, 11, 200, rng.randint(1, 65535)]),
            rng.randint(0, 255) << 2,
            rng.randint(0, 255),
            rng.randint(0, 255),
            16000,
            rng.choice([0, 1, 4, 8]),
            bytes(rng.choice([0, 1, 2, 3, 255]) for _ in range(n)),
        )
        chain = ChainState(
            rng.randint(0, 40), rng.getrandbits(64) & mask, rng.getrandbits(64) & mask, rng.random() < 0.25
        )
        ref = reference_scan(cfg, chain, model, outputs=outputs)
        tmpl = ScanEngine(model, outputs=outputs).template(cfg, chain)
        T, S, V = tmpl.events()
        assert list(zip(T.tolist(), S.tolist(), V.tolist())) == ref.events
        assert tmpl.duration_ns == ref.duration_ns == scan_duration_ns(cfg, model, chain.position)
        assert tmpl.chain_end == ref.chain_end
        assert _rows(tmpl) == ref.pulses
        assert {i: int(v) for i, v in enumerate(tmpl.voltages)} == ref.voltages
        assert np.all(np.diff(T) >= 0)
        if n:
            assert channel_offsets_ns(cfg, model)[1].tolist() == tmpl.first_pulse_ns.tolist()


def test_a_run_of_scans_equals_stepping_each_scan_from_the_previous_chain_state() -> None:
    """What the timed emulator replays (cached templates shifted in time) against the reference scan by
    scan — including the HV513-count-0 quirk, where the chain state changes every scan."""
    from tactdeform_hw.emulator.records.trace import MemorySink
    from tactdeform_hw.emulator.timed.model_v1_2 import TimedEmulator

    for hv in (4, 0):
        cfg = ScanConfig.make(
            5, [1, 2, 0, 1, 3], sense_height_raw=3, sense_width_us=12, rate_hz=500, hv513_num=hv
        )
        emu = TimedEmulator()
        sink = MemorySink()
        emu.attach(sink)
        emu.configure(cfg)
        emu.advance_to(20_500)
        sink.close()
        got = [(t, n, v) for t, n, v in sink.events if not n.startswith("MARK") and t > 0]
        expect = []
        chain = POWER_ON_CHAIN
        starts = [r.start_ns + j * r.stride_ns for r in emu.runs for j in range(r.count)]
        assert len(starts) == 10 and starts[:2] == [2_000_000, 4_000_000]
        for s in starts:
            ref = reference_scan(cfg, chain, MODEL, outputs=32)
            expect += [(s + t, Signal(sig).name, v) for t, sig, v in ref.events]
            chain = ref.chain_end
        assert got == expect


# --- the HV513 chain ----------------------------------------------------------------------------------------


def test_hv513_count_zero_clear_loads_a_one_and_leaves_output_0_selected() -> None:
    cfg = ScanConfig.make(4, 1, hv513_num=0)
    ref = reference_scan(cfg, POWER_ON_CHAIN, MODEL, outputs=32)
    le_groups = [v for _, s, v in ref.events if s == Signal.SEL]
    assert le_groups[-1] == 0  # the "clear" selects output 0
    clear = ref.events[-6:]
    assert [(Signal(s).name, v) for _, s, v in clear] == [
        ("LE", 0),
        ("DIN", 1),
        ("CLK", 1),
        ("CLK", 0),
        ("LE", 1),
        ("SEL", 0),
    ]
    # with a real chain behind a count of 0, the ones accumulate: the next scan lights several outputs
    second = ScanEngine(outputs=32).template(cfg, ref.chain_end)
    assert second.pulse_outputs[0] == (0, 1, 5)
    assert ScanEngine(outputs=32).template(cfg, ChainState(0, 0, 0)).pulse_outputs[0] == (0,)


def test_channels_beyond_the_chain_reach_no_electrode() -> None:
    cfg = ScanConfig.make(40, 1, hv513_num=4)
    t = ScanEngine(outputs=32).template(cfg)
    p = t.pulses
    assert p.n_outputs[:32].tolist() == [1] * 32 and p.output[:32].tolist() == list(range(32))
    assert p.n_outputs[32:].tolist() == [0] * 8
    assert p.current_ua[32:].tolist() == [0.0] * 8 and p.limited[32:].all()


def test_both_budgets_name_channels_beyond_the_chain_in_the_same_note() -> None:
    from tactdeform_hw.emulator.firmware.firmware_scan import FirmwareScanConfig, budget
    from tactdeform_hw.emulator.records.reports import firmware_budget

    note = "channels 32..39 lie beyond the 4 HV513 chip(s)"
    closed_form = Budget.of(ScanConfig.make(40, 1, hv513_num=4), MODEL, 125)
    logged = firmware_budget(ScanConfig.make(40, 1, hv513_num=4), MODEL.with_(cs_writes_costed=True))
    walker = budget(FirmwareScanConfig(40, [100] * 40, pulse_width=200, discharge_time=45, hv513_num=4), "v2")
    assert note in closed_form.notes and note in logged.notes and note in walker.notes
    within = Budget.of(ScanConfig.make(32, 1, hv513_num=4), MODEL, 125)
    assert not any("beyond" in n for n in within.notes)


# --- voltages -----------------------------------------------------------------------------------------------


def test_voltages_are_deterministic_plausible_and_per_electrode() -> None:
    cfg = ScanConfig.make(32, 1, pulse_height=100)
    a = ScanEngine().template(cfg).voltages
    b = ScanEngine().template(cfg).voltages
    assert a.tolist() == b.tolist()
    assert len(set(a.tolist())) > 5  # the electrodes differ
    skin = SkinModel()
    # 1 mA for ~200 us into ~2 kOhm + 30 kOhm || 10 nF: roughly 10-25 V, i.e. ADC codes ~30-80 after >> 2
    assert 20 < int(a.mean()) < 100
    assert skin.pulse((0,), 0, 196.6).voltage_code == 0


def test_compliance_limit_caps_current_at_long_strong_pulses() -> None:
    cfg = ScanConfig.make(2, 1, pulse_height=1000, pulse_width_us=65535)
    p = ScanEngine().template(cfg).pulses
    assert p.limited.all()
    assert (p.current_ua < 10_000).all()
    assert p.voltage_code.tolist() == [SkinModel().adc_of_voltage(300.0) >> 2] * 2
    open_skin = SkinModel(open_electrodes=frozenset({1}))
    q = ScanEngine(skin=open_skin).template(ScanConfig.make(2, 1, pulse_height=100)).pulses
    assert q.current_ua[1] == 0 and q.limited[1] and not q.limited[0]


def test_sense_pulses_carry_current_on_channels_off_in_the_pattern() -> None:
    cfg = ScanConfig.make(32, 0, sense_height_raw=10, sense_width_us=50)
    p = ScanEngine().template(cfg).pulses
    assert set(p.kind.tolist()) == {PulseKind.SENSE}
    assert (p.code == 40).all() and (p.current_ua == 400).all() and (p.charge_nc > 0).all()


def test_biphasic_channels_give_an_anodic_then_a_cathodic_phase() -> None:
    p = ScanEngine().template(ScanConfig.make(1, 2, polarity=0)).pulses
    assert p.kind.tolist() == [PulseKind.BI_ANODIC, PulseKind.BI_CATHODIC]
    assert p.pol.tolist() == [1, 0]


def test_untimed_emulator_scan_seam_fills_measure_replies() -> None:
    from tactdeform_hw.emulator import Emulator
    from tactdeform_hw.emulator.firmware.scan import ScanVoltages
    from tactdeform_hw.protocol import commands as c

    plain = Emulator()
    setup = (
        c.encode_electrode_num(3)
        + c.encode_pulse_height(100)
        + c.encode_pulse_width(200)
        + c.encode_pattern([1, 1, 1])
    )
    plain.feed(setup)
    assert plain.feed(c.MEASURE_REQUEST) == bytes(6)  # no scan seam: nothing measured
    emu = Emulator()
    emu.scan = ScanVoltages()
    emu.feed(setup)
    reply = c.parse_measure_reply(emu.feed(c.MEASURE_REQUEST), 3)
    expect = ScanEngine().template(ScanConfig.make(3, 1)).voltages.tolist()
    assert reply == expect and all(v > 0 for v in reply)


def test_a_timing_model_for_a_firmware_takes_each_constant_from_its_table() -> None:
    """``TimingModel.for_firmware`` copies the firmware table's constants by name: a table whose every
    constant differs from v1.2's gives a model that carries each of them, and the table's queue size."""
    table = replace(
        V1_2.timing,
        spi_exchange_us=7.0,
        dac_change_at_us=3.5,
        gpio_write_us=0.07,
        isr_entry_us=2.5,
        pulse_wait_offset_us=8,
        discharge_wait_offset_us=9,
        delay_min_us=4,
        delay_ticks_per_us=2.5,
        delay_offset_ticks=6.0,
        timer_ticks_per_us=4,
        watchdog_us=250_000.0,
        rtos_tick_us=500.0,
        parser_call_us=3.0,
        parser_byte_us=1.5,
        hv513_detect_us=900.0,
    )
    m = TimingModel.for_firmware(replace(V2, timing=table))
    got = (
        m.spi_exchange_us,
        m.dac_change_at_us,
        m.gpio_write_us,
        m.isr_entry_us,
        m.pulse_wait_offset_us,
        m.discharge_wait_offset_us,
        m.delay_min_us,
        m.delay_ticks_per_us,
        m.delay_offset_ticks,
        m.timer_tick_us,
        m.watchdog_us,
        m.rtos_tick_us,
        m.parser_call_us,
        m.parser_byte_us,
        m.hv513_detect_us,
        m.rx_queue_bytes,
    )
    assert got == (7.0, 3.5, 0.07, 2.5, 8, 9, 4, 2.5, 6.0, 0.25, 250_000.0, 500.0, 3.0, 1.5, 900.0, 1024)
    assert TimingModel.for_firmware(V1_2, gpio_write_us=0.1).gpio_write_us == 0.1  # a change wins
