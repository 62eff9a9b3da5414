"""Both firmware versions' scan interrupts against the firmware's own code built on a host, each version
by its one scan engine: v2 by the statement walker, v1.2 by its compiled engine (``scan.py``, held to the
same traces under every reading in ``test_scan_engine_readings.py``)."""

from __future__ import annotations

import json
from typing import Any

import pytest

from tactdeform_hw.emulator.firmware import firmware_scan
from tactdeform_hw.emulator.firmware.firmware_scan import (
    DA_CS,
    DEFAULT_CONVENTIONS,
    HOST_BUILD,
    FirmwareScanConfig,
    ScanConventions,
    ScanTrace,
    scan_duration_us,
    trace_scan,
)
from tactdeform_hw.emulator.firmware.models import model_entry
from tactdeform_hw.emulator.timed.timing import DEFAULT_MODEL
from tactdeform_hw.protocol.firmware import FIRMWARES

from .conftest import DATA
from .test_scan_engine_readings import LoopBack, logged, scan, scan_config

#: Each version's golden traces and how many the file holds.
TRACE_FILES = {"v1.2": ("scan_traces_v12.jsonl", 22), "v2": ("scan_traces_v2.jsonl", 21)}
TRACES = {
    fw: [json.loads(line) for line in (DATA / name).read_text().splitlines() if line.strip()]
    for fw, (name, _) in TRACE_FILES.items()
}
CASES = [(fw, i) for fw in FIRMWARES for i in range(len(TRACES[fw]))]
EVERY_FIRMWARE = pytest.mark.parametrize("firmware", list(FIRMWARES))


def test_trace_files_present() -> None:
    assert set(TRACE_FILES) == set(FIRMWARES)
    assert {fw: len(t) for fw, t in TRACES.items()} == {fw: n for fw, (_, n) in TRACE_FILES.items()}


def _walked(firmware: str) -> bool:
    """Whether the version's scan engine is the statement walker (else its compiled engine)."""
    return model_entry(firmware).scan_module == firmware_scan.__name__


def _conventions(golden: dict) -> ScanConventions:
    shim = golden["shim"]
    return ScanConventions(
        spi_exchange_ns=round(shim["spi_exchange_us"] * 1000),
        dac_change_at_ns=round(shim["dac_change_at_us"] * 1000),
        gpio_write_ns=round(shim["gpio_write_us"] * 1000),
        isr_entry_ns=round(shim["isr_entry_us"] * 1000),
        timer_tick_ns=round(shim["timer_tick_us"] * 1000),
        cs_writes_costed=True,
    )


def _v12_scan(config: dict[str, Any], conventions: ScanConventions) -> ScanTrace:
    """v1.2's engine under the same readings, its scan as the walker's trace would hold it."""
    model = DEFAULT_MODEL.with_(cs_writes_costed=conventions.cs_writes_costed, dac_load=conventions.dac_load)
    tmpl = scan(config, model, LoopBack())
    return ScanTrace(
        events=logged(tmpl, model),
        isr_return_us=round(tmpl.duration_ns / 1000, 3),
        voltage=tmpl.voltages.tolist(),
        timer_ops=[
            [round(model.isr_entry_ns / 1000, 3), 1, "alarm_disable", 0],
            [round(tmpl.duration_ns / 1000, 3), 1, "alarm_enable", 0],
        ],
        alarm_ticks=tmpl.config.alarm_ticks,
    )


def _scan(
    firmware: str, config: dict[str, Any], conventions: ScanConventions = DEFAULT_CONVENTIONS
) -> ScanTrace:
    """One logged scan by the version's own scan engine."""
    if not _walked(firmware):
        return _v12_scan(config, conventions)
    return trace_scan(FirmwareScanConfig.from_dict(config), firmware, conventions)


def _duration_us(
    firmware: str, config: dict[str, Any], conventions: ScanConventions = DEFAULT_CONVENTIONS
) -> float:
    return _scan(firmware, config, conventions).isr_return_us


@pytest.mark.parametrize(
    ("firmware", "index"), CASES, ids=[f"{fw}-{TRACES[fw][i]['name']}" for fw, i in CASES]
)
def test_scan_trace_matches_the_firmware(firmware: str, index: int) -> None:
    """Every event in order and value, the return time, the voltages, the timer operations."""
    golden = TRACES[firmware][index]
    assert _conventions(golden) == HOST_BUILD
    got = _scan(firmware, golden["config"], HOST_BUILD)
    assert len(got.events) == len(golden["events"])
    for k, (a, b) in enumerate(zip(got.events, golden["events"], strict=True)):
        assert a == b, f"event {k}"
    assert got.isr_return_us == golden["isr_return_us"]
    assert got.voltage == golden["voltage"]
    assert got.timer_ops == golden["timer_ops"]
    assert got.alarm_ticks == golden["alarm_ticks"]


def _tactdeform(firmware: str) -> dict[str, Any]:
    golden = TRACES[firmware][0]
    assert golden["name"].startswith("tactdeform_32mono")
    return dict(golden["config"])


def test_chip_select_readings() -> None:
    """The protocol notes' figures: 7869.45 / 7850.25 µs on v1.2; v2 7645.45 µs with the writes costed.
    The package's default reading counts them inside the exchange."""
    assert DEFAULT_CONVENTIONS == ScanConventions(cs_writes_costed=False)
    assert _duration_us("v1.2", _tactdeform("v1.2"), HOST_BUILD) == 7869.45
    assert _duration_us("v1.2", _tactdeform("v1.2")) == 7850.25
    assert scan_duration_us(FirmwareScanConfig.from_dict(_tactdeform("v2")), "v2", HOST_BUILD) == 7645.45
    assert scan_duration_us(FirmwareScanConfig.from_dict(_tactdeform("v2")), "v2") == 7639.05


def test_discharge_50_fits_on_v2_only() -> None:
    v12 = {**_tactdeform("v1.2"), "discharge_time": 50}
    v2 = {**_tactdeform("v2"), "discharge_time": 50}
    assert _duration_us("v2", v2, HOST_BUILD) == 7805.45 < 8000
    assert _duration_us("v1.2", v12, ScanConventions(cs_writes_costed=False)) > 8000


@EVERY_FIRMWARE
def test_dac_load_at_cs_rise_moves_every_dac_edge_not_the_widths(firmware: str) -> None:
    cfg = _tactdeform(firmware)
    mid = _scan(firmware, cfg, HOST_BUILD)
    rise = _scan(firmware, cfg, ScanConventions(cs_writes_costed=True, dac_load="cs_rise"))
    dac_mid = [e for e in mid.events if e[1] == "DAC"]
    dac_rise = [e for e in rise.events if e[1] == "DAC"]
    assert [e[3] for e in dac_mid] == [e[3] for e in dac_rise]
    shifts = {round(b[0] - a[0], 3) for a, b in zip(dac_mid, dac_rise, strict=True)}
    assert shifts == {3.35}  # 3.3 µs later, plus the chip-select write itself
    assert rise.isr_return_us == mid.isr_return_us
    cs_up = [e[0] for e in rise.events if e[1] == "GPIO" and e[2] == DA_CS and e[3] == 1]
    assert cs_up == [e[0] for e in dac_rise]


def test_each_v2_channel_is_one_exchange_shorter() -> None:
    """With the same pulses, a v2 channel is v1.2's minus the discharge exchange and its CS writes."""
    v12 = _tactdeform("v1.2")
    v2 = _tactdeform("v2")
    inside = ScanConventions(cs_writes_costed=False)
    diff = _duration_us("v1.2", v12, inside) - _duration_us("v2", v2, inside)
    assert round(diff / 32, 3) == 6.6


def test_v2_biphasic_first_phase_follows_polarity() -> None:
    """v2: anodic → POL high then low; cathodic → low then high (v1.2: always high first)."""
    for pol, levels in ((1, [1, 0]), (0, [0, 1])):
        cfg = FirmwareScanConfig(1, [100], 20, 10, polarity=pol, stim_mode=1)
        pols = [e[3] for e in trace_scan(cfg, "v2").events if e[1] == "GPIO" and e[2] == 3]
        assert pols[:2] == levels and pols[2] == 1  # then the discharge's POL high
    v12 = {"electrode_num": 1, "stim_pattern": [2], "pulse_width": 20, "discharge_time": 10, "polarity": 0,
           "pulse_height": 100, "hv513_num": 4}  # fmt: skip
    pols = [e[3] for e in _scan("v1.2", v12).events if e[1] == "GPIO" and e[2] == 3]
    assert pols[:3] == [0, 1, 0]


def test_the_v12_step_through_agrees_with_the_golden_traces() -> None:
    """The scan engine's test oracle, the statement-by-statement step-through (which does not log chip
    selects), gives the golden order and values, pins for pins, under the host build's reading."""
    from tactdeform_hw.emulator.firmware.scan import POWER_ON_CHAIN, Signal

    from .scan_reference import reference_scan

    pins = {Signal.BL: 1, Signal.LE: 2, Signal.POL: 3, Signal.CLK: 4, Signal.DIN: 5}
    model = DEFAULT_MODEL.with_(cs_writes_costed=True)
    for golden in TRACES["v1.2"]:
        c = golden["config"]
        cfg = scan_config(c)
        chain = POWER_ON_CHAIN
        for _ in range(c["prior_scans"]):
            chain = reference_scan(cfg, chain, model).chain_end
        res = reference_scan(cfg, chain, model)
        ours = [
            [round(t / 1000, 3), "DAC", "DAC", v]
            if sig == Signal.DAC
            else [round(t / 1000, 3), "GPIO", pins[Signal(sig)], v]
            for t, sig, v in res.events
            if sig in pins or sig == Signal.DAC
        ]
        expected = [e for e in golden["events"] if not (e[1] == "GPIO" and e[2] in (43, 44))]
        assert ours == expected, golden["name"]
        assert round(res.duration_ns / 1000, 3) == golden["isr_return_us"]


@EVERY_FIRMWARE
def test_budget_widths_match_the_traces(firmware: str) -> None:
    """The budget's effective width is DAC edge to DAC edge in the golden trace, on every version."""
    from tactdeform_hw.emulator.firmware.firmware_scan import budget
    from tactdeform_hw.emulator.records.reports import firmware_budget

    golden = TRACES[firmware][0]
    dac = [e[0] for e in golden["events"] if e[1] == "DAC"]
    b = (
        budget(FirmwareScanConfig.from_dict(golden["config"]), firmware, HOST_BUILD)
        if _walked(firmware)
        else firmware_budget(scan_config(golden["config"]), DEFAULT_MODEL.with_(cs_writes_costed=True))
    )
    assert b.effective_width_us == round(dac[1] - dac[0], 3)
    assert b.scan_us == golden["isr_return_us"] and b.verdict == "fits"
    assert len(b.per_channel_us) == 32 and sum(
        b.per_channel_us
    ) + b.isr_entry_us + b.clear_us == pytest.approx(b.scan_us)
