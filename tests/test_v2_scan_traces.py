"""Both firmware versions' scan interrupts against the firmware's own code built on a host."""

from __future__ import annotations

import json

import pytest

from tactdeform_hw.emulator.firmware.firmware_scan import (
    DA_CS,
    DEFAULT_CONVENTIONS,
    HOST_BUILD,
    FirmwareScanConfig,
    ScanConventions,
    scan_duration_us,
    trace_scan,
)

from .conftest import DATA

TRACES = {
    fw: [json.loads(line) for line in (DATA / name).read_text().splitlines() if line.strip()]
    for fw, name in (("v1.2", "scan_traces_v12.jsonl"), ("v2", "scan_traces_v2.jsonl"))
}
CASES = [(fw, i) for fw, lines in TRACES.items() for i in range(len(lines))]


def test_trace_files_present() -> None:
    assert len(TRACES["v1.2"]) == 22 and len(TRACES["v2"]) == 21


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


@pytest.mark.parametrize(
    ("firmware", "index"), CASES, ids=[f"{fw}-{TRACES[fw][i]['name']}" for fw, i in CASES]
)
def test_scan_trace_matches_the_firmware(firmware: str, index: int) -> None:
    """Every event in order and value, the return time, the voltages, the timer operations."""
    golden = TRACES[firmware][index]
    assert _conventions(golden) == HOST_BUILD
    got = trace_scan(FirmwareScanConfig.from_dict(golden["config"]), firmware, HOST_BUILD)
    assert len(got.events) == len(golden["events"])
    for k, (a, b) in enumerate(zip(got.events, golden["events"], strict=True)):
        assert a == b, f"event {k}"
    assert got.isr_return_us == golden["isr_return_us"]
    assert got.voltage == golden["voltage"]
    assert got.timer_ops == golden["timer_ops"]
    assert got.alarm_ticks == golden["alarm_ticks"]


def _tactdeform(firmware: str) -> FirmwareScanConfig:
    golden = TRACES[firmware][0]
    assert golden["name"].startswith("tactdeform_32mono")
    return FirmwareScanConfig.from_dict(golden["config"])


def test_chip_select_readings() -> None:
    """The protocol notes' figures: 7869.45 / 7850.25 µs on v1.2; v2 7645.45 µs with the writes costed.
    The package's default reading counts them inside the exchange."""
    assert DEFAULT_CONVENTIONS == ScanConventions(cs_writes_costed=False)
    assert scan_duration_us(_tactdeform("v1.2"), "v1.2", HOST_BUILD) == 7869.45
    assert scan_duration_us(_tactdeform("v1.2"), "v1.2") == 7850.25
    assert scan_duration_us(_tactdeform("v2"), "v2", HOST_BUILD) == 7645.45
    assert scan_duration_us(_tactdeform("v2"), "v2") == 7639.05


def test_discharge_50_fits_on_v2_only() -> None:
    from dataclasses import replace

    v12 = replace(_tactdeform("v1.2"), discharge_time=50)
    v2 = replace(_tactdeform("v2"), discharge_time=50)
    assert scan_duration_us(v2, "v2", HOST_BUILD) == 7805.45 < 8000
    assert scan_duration_us(v12, "v1.2", ScanConventions(cs_writes_costed=False)) > 8000


def test_dac_load_at_cs_rise_moves_every_dac_edge_not_the_widths() -> None:
    cfg = _tactdeform("v2")
    mid = trace_scan(cfg, "v2", HOST_BUILD)
    rise = trace_scan(cfg, "v2", ScanConventions(cs_writes_costed=True, dac_load="cs_rise"))
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
    diff = scan_duration_us(v12, "v1.2", inside) - scan_duration_us(v2, "v2", inside)
    assert round(diff / 32, 3) == 6.6


def test_v2_biphasic_first_phase_follows_polarity() -> None:
    """v2: anodic → POL high then low; cathodic → low then high (v1.2: always high first)."""
    for pol, levels in ((1, [1, 0]), (0, [0, 1])):
        cfg = FirmwareScanConfig(1, [100], 20, 10, polarity=pol, stim_mode=1)
        pols = [e[3] for e in trace_scan(cfg, "v2").events if e[1] == "GPIO" and e[2] == 3]
        assert pols[:2] == levels and pols[2] == 1  # then the discharge's POL high
    v12 = FirmwareScanConfig(1, [2], 20, 10, polarity=0, pulse_height=100)
    pols = [e[3] for e in trace_scan(v12, "v1.2").events if e[1] == "GPIO" and e[2] == 3]
    assert pols[:3] == [0, 1, 0]


def test_the_v12_scan_engine_agrees_with_the_golden_traces() -> None:
    """The timed model's step-through (which does not log chip selects and counts them inside the
    exchange, the package's default reading) gives the golden order and values, pins for pins."""
    from tactdeform_hw.emulator.firmware.scan import POWER_ON_CHAIN, ScanConfig, Signal

    from .scan_reference import reference_scan

    pins = {Signal.BL: 1, Signal.LE: 2, Signal.POL: 3, Signal.CLK: 4, Signal.DIN: 5}
    inside = ScanConventions(cs_writes_costed=False)
    for golden in TRACES["v1.2"]:
        c = golden["config"]
        cfg = ScanConfig(
            c["electrode_num"],
            c["polarity"],
            c["pulse_height"],
            c["pulse_width"],
            c["sense_pulse_height"],
            c["sense_pulse_width"],
            c["discharge_time"],
            golden["alarm_ticks"],
            c["hv513_num"],
            bytes(c["stim_pattern"]),
        )
        chain = POWER_ON_CHAIN
        for _ in range(c["prior_scans"]):
            chain = reference_scan(cfg, chain).chain_end
        res = reference_scan(cfg, chain)
        ours = [
            [round(t / 1000, 3), "DAC", "DAC", v]
            if sig == Signal.DAC
            else [round(t / 1000, 3), "GPIO", pins[Signal(sig)], v]
            for t, sig, v in res.events
            if sig in pins or sig == Signal.DAC
        ]
        walker = trace_scan(FirmwareScanConfig.from_dict(c), "v1.2", inside)
        expected = [e for e in walker.events if not (e[1] == "GPIO" and e[2] in (43, 44))]
        assert ours == expected, golden["name"]
        assert round(res.duration_ns / 1000, 3) == walker.isr_return_us


def test_budget_widths_match_the_traces() -> None:
    """The budget's effective width is DAC edge to DAC edge in the golden trace, on both versions."""
    from tactdeform_hw.emulator.firmware.firmware_scan import budget

    for firmware in ("v1.2", "v2"):
        golden = TRACES[firmware][0]
        dac = [e[0] for e in golden["events"] if e[1] == "DAC"]
        b = budget(FirmwareScanConfig.from_dict(golden["config"]), firmware, HOST_BUILD)
        assert b.effective_width_us == round(dac[1] - dac[0], 3)
        assert b.scan_us == golden["isr_return_us"] and b.verdict == "fits"
        assert len(b.per_channel_us) == 32 and sum(
            b.per_channel_us
        ) + b.isr_entry_us + b.clear_us == pytest.approx(b.scan_us)
