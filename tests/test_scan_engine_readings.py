"""Firmware v1.2's one scan engine under both readings of the exchange, held to the firmware's own traces.

``emulator/firmware/scan.py`` is v1.2's scan engine everywhere: the timed and untimed models, ``timing``
under every option, the traces.  The firmware's code leaves two readings of its DAC/ADC exchange open,
and the engine's timing model takes both: whether the chip-select writes around an exchange cost GPIO
writes of their own (``cs_writes_costed``) and when the DAC output changes (``dac_load``).

Here the engine is held to

* the traces the firmware's own interrupt code logs built on a host (``scan_traces_v12.jsonl``, chip
  selects costed as the host build costs them): every pin write, chip selects included, and every DAC
  change, in order, at the same nanosecond; the interrupt's length, the readings stored, the alarm;
* the statement-by-statement walker's v1.2 outputs, recorded before v1.2 stopped being walked
  (``scan_walker_v12.jsonl``): the same for scans under all four readings (chains carried over up to two
  scans), and the budget the timing command prints for small and long scans, overruns, watchdog resets
  and channels beyond the chain.
"""

from __future__ import annotations

import json
from typing import Any

import pytest

from tactdeform_hw.emulator.firmware.scan import (
    POWER_ON_CHAIN,
    ScanConfig,
    ScanEngine,
    ScanTemplate,
    channel_offsets_ns,
    firmware_trace,
    physical_outputs,
)
from tactdeform_hw.emulator.firmware.skin import PulseOutcome
from tactdeform_hw.emulator.records.reports import firmware_budget
from tactdeform_hw.emulator.timed.timing import DEFAULT_MODEL, TimingModel
from tactdeform_hw.protocol import firmware_math as fm
from tactdeform_hw.protocol.constants import POWER_ON_PERIOD_US

from .conftest import DATA

GOLDEN = [json.loads(line) for line in (DATA / "scan_traces_v12.jsonl").read_text().splitlines() if line]
WALKED = [json.loads(line) for line in (DATA / "scan_walker_v12.jsonl").read_text().splitlines() if line]
TRACED = [r for r in WALKED if "events" in r]


class LoopBack:
    """The host build's ADC: it reads back the DAC code the exchange starts with (the firmware's traces
    store that as each channel's voltage)."""

    def pulse(self, outputs: tuple[int, ...], code: int, sample_after_us: float) -> PulseOutcome:
        return PulseOutcome(0.0, 0.0, False, code, code)


def scan_config(c: dict[str, Any]) -> ScanConfig:
    """A firmware trace's configuration as v1.2's registers hold it (the alarm from the 0xF6 rate, or the
    power-on period when none arrived)."""
    rate = c.get("frequency_hz")
    period_us = fm.period_us_from_rate(rate) if rate else POWER_ON_PERIOD_US
    return ScanConfig(
        c["electrode_num"],
        c.get("polarity", 1),
        c["pulse_height"],
        c["pulse_width"],
        c.get("sense_pulse_height", 0),
        c.get("sense_pulse_width", 0),
        c["discharge_time"],
        fm.alarm_ticks(period_us),
        c["hv513_num"],
        bytes(c["stim_pattern"]),
    )


def scan(c: dict[str, Any], model: TimingModel, skin: Any = None) -> ScanTemplate:
    """The logged scan of a trace: after ``prior_scans`` scans from power-on, the chain carried over."""
    kwargs = {} if skin is None else {"skin": skin}
    engine = ScanEngine(model, outputs=physical_outputs("compact", 1), **kwargs)
    cfg = scan_config(c)
    chain = POWER_ON_CHAIN
    for _ in range(c.get("prior_scans", 0)):
        chain = engine.template(cfg, chain).chain_end
    return engine.template(cfg, chain)


def logged(tmpl: ScanTemplate, model: TimingModel) -> list[list[Any]]:
    """The engine's scan as the firmware's log writes it: times in µs to the ns."""
    return [[round(e[0] / 1000, 3), *e[1:]] for e in firmware_trace(tmpl, model)]


def us(ns: int) -> float:
    return round(ns / 1000, 3)


def test_the_recorded_cases_are_all_there() -> None:
    assert len(GOLDEN) == 22 and len(TRACED) == 56 and len(WALKED) == 120
    readings = {(r["conventions"]["cs_writes_costed"], r["conventions"]["dac_load"]) for r in TRACED}
    assert readings == {(c, d) for c in (False, True) for d in ("mid_exchange", "cs_rise")}


@pytest.mark.parametrize("golden", GOLDEN, ids=[g["name"] for g in GOLDEN])
def test_the_engine_logs_the_firmwares_own_scans(golden: dict[str, Any]) -> None:
    """Chip selects costed as the host build costs them: every event in order and value, the return,
    the stored readings, the timer operations and the alarm."""
    model = DEFAULT_MODEL.with_(cs_writes_costed=True)
    shim = golden["shim"]
    assert (shim["spi_exchange_us"], shim["dac_change_at_us"], shim["gpio_write_us"]) == (
        model.spi_exchange_us,
        model.dac_change_at_us,
        model.gpio_write_us,
    )
    assert (shim["isr_entry_us"], shim["timer_tick_us"]) == (model.isr_entry_us, model.timer_tick_us)
    tmpl = scan(golden["config"], model, LoopBack())
    events = logged(tmpl, model)
    assert len(events) == len(golden["events"])
    for k, (a, b) in enumerate(zip(events, golden["events"], strict=True)):
        assert a == b, f"event {k}"
    assert us(tmpl.duration_ns) == golden["isr_return_us"]
    assert tmpl.voltages.tolist() == golden["voltage"]
    assert [
        [us(model.isr_entry_ns), 1, "alarm_disable", 0],
        [us(tmpl.duration_ns), 1, "alarm_enable", 0],
    ] == (golden["timer_ops"])
    assert tmpl.config.alarm_ticks == golden["alarm_ticks"]


def _reading_id(row: dict[str, Any]) -> str:
    conv = row["conventions"]
    return f"{row['name']}-{'costed' if conv['cs_writes_costed'] else 'inside'}-{conv['dac_load']}"


@pytest.mark.parametrize(
    "walked",
    TRACED,
    ids=[_reading_id(r) for r in TRACED],
)
def test_the_engine_logs_what_the_walker_logged_under_every_reading(walked: dict[str, Any]) -> None:
    model = DEFAULT_MODEL.with_(**walked["conventions"])
    tmpl = scan(walked["config"], model)
    assert logged(tmpl, model) == walked["events"]
    assert us(tmpl.duration_ns) == walked["isr_return_us"]
    starts = channel_offsets_ns(tmpl.config, model)[0].tolist()
    assert [us(t) for t in starts] == walked["channel_start_us"]
    clear_ns = tmpl.duration_ns - model.isr_exit_ns - (3 + 2 * _clear_clk(tmpl)) * model.gpio_ns
    assert us(clear_ns) == walked["clear_start_us"]
    assert tmpl.chain_end.position == walked["chain_position"]
    assert tmpl.config.alarm_ticks == walked["alarm_ticks"]


def _clear_clk(tmpl: ScanTemplate) -> int:
    from tactdeform_hw.emulator.firmware.scan import clear_clk_pulses

    n = tmpl.config.electrode_num
    return clear_clk_pulses(tmpl.config, n - 1 if n else tmpl.chain_start.position)


@pytest.mark.parametrize(
    "walked",
    WALKED,
    ids=[_reading_id(r) for r in WALKED],
)
def test_the_budget_is_the_one_the_walker_printed(walked: dict[str, Any]) -> None:
    model = DEFAULT_MODEL.with_(**walked["conventions"])
    assert firmware_budget(scan_config(walked["config"]), model).to_dict() == walked["budget"]


def test_a_costed_reading_lengthens_each_exchange_by_its_four_chip_select_writes() -> None:
    """The pulses the timed model delivers follow the reading: 0.2 µs longer per exchange when costed,
    every onset later when the DAC loads as DA_CS rises, the widths unchanged by the load moment."""
    cfg = ScanConfig.make(2, 1, pulse_width_us=200)
    inside = ScanEngine(DEFAULT_MODEL).template(cfg).pulses
    costed = ScanEngine(DEFAULT_MODEL.with_(cs_writes_costed=True)).template(cfg).pulses
    rising = ScanEngine(DEFAULT_MODEL.with_(cs_writes_costed=True, dac_load="cs_rise")).template(cfg).pulses
    assert inside.width_ns.tolist() == [196_600] * 2 and costed.width_ns.tolist() == [196_800] * 2
    assert rising.width_ns.tolist() == costed.width_ns.tolist()
    assert (rising.start_ns - costed.start_ns).tolist() == [3_350] * 2  # 3.3 µs later, and DA_CS's write


def test_timing_under_the_readings_runs_v12s_engine_not_the_walker(
    tmp_path: Any, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    """``timing --cs-writes costed --dac-load cs_rise`` on v1.2: the budget and the logged events are the
    engine's (the walker, v2's engine, is never asked)."""
    from tactdeform_hw.emulator.firmware import firmware_scan

    from .test_timing_cli import run_cli

    def refuse(*args: Any, **kwargs: Any) -> Any:
        raise AssertionError("the statement walker ran for v1.2")

    for name in ("trace_scan", "budget", "scan_duration_us"):
        monkeypatch.setattr(firmware_scan, name, refuse)
    path = tmp_path / "v12.json"
    argv = ["--cs-writes", "costed", "--dac-load", "cs_rise", "--pattern", "1,2,0,3", "--events", str(path)]
    code, out, _ = run_cli([*argv, "--json"], capsys)
    model = DEFAULT_MODEL.with_(cs_writes_costed=True, dac_load="cs_rise")
    cfg = ScanConfig.make(4, [1, 2, 0, 3])
    assert code == 0
    assert json.loads(out) == {**firmware_budget(cfg, model).to_dict(), "traces": [str(path)]}
    rows = json.loads(path.read_text())
    events = firmware_trace(ScanEngine(model).template(cfg), model)
    assert [(r["t_ns"], r["value"]) for r in rows] == [(e[0], e[3]) for e in events]
    assert {r["name"] for r in rows} >= {"GPIO43", "GPIO44", "DAC"}
