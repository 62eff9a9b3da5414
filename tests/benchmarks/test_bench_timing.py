"""Speed of the timing models (run: pytest tests/benchmarks/test_bench_timing.py --benchmark-enable).

The scenario of the targets: 10 s of device time, 32 electrodes at 125 Hz, every channel at pattern 1
(1250 scans, 40 000 pulses).  Targets: event-exact >= 10x real time (<= 1 s wall), analytic >= 1000x
real time.  Baselines in the same run: the reference step-through (one scan statement by statement) for
the event engine's template cache, and the event engine for the analytic engine.  ``extra_info`` carries
``device_s`` so the real-time factor is ``device_s / mean``.
"""

from __future__ import annotations

import random

from tactdeform_hw.emulator.firmware.scan import POWER_ON_CHAIN, ScanConfig
from tactdeform_hw.emulator.records.trace import MemorySink
from tactdeform_hw.emulator.timed.analytic import Scenario, run_analytic
from tactdeform_hw.emulator.timed.model_v1_2 import TimedEmulator, configuration_bytes
from tactdeform_hw.protocol import encode_pattern

from ..scan_reference import reference_scan

CFG = ScanConfig.make(32, 1, pulse_width_us=200, discharge_us=45, rate_hz=125)
DEVICE_S = 10.0


def _event_exact_steady() -> int:
    emu = TimedEmulator()
    emu.configure(CFG)
    emu.advance_to(DEVICE_S * 1e6)
    table = emu.reports.pulse_table()  # every pulse, as columns
    return int(table["channel"].size)


def test_event_exact_10s_32_electrodes_125hz(benchmark) -> None:  # type: ignore[no-untyped-def]
    benchmark.extra_info["device_s"] = DEVICE_S
    pulses = benchmark.pedantic(_event_exact_steady, rounds=5, iterations=1)
    assert pulses == 40_000


def _render_writes() -> list[tuple[float, bytes]]:
    rng = random.Random(1)
    writes = [(0.0, configuration_bytes(CFG, 125))]
    t = 20_000.0
    while t < DEVICE_S * 1e6:
        writes.append((t, encode_pattern([rng.choice([0, 1]) for _ in range(32)])))
        t += 1e6 / 60
    return writes


WRITES = _render_writes()


def _event_exact_render() -> int:
    emu = TimedEmulator(link="usb")
    for t, data in WRITES:
        emu.advance_to(t)
        emu.write(data, t)
    emu.advance_to(DEVICE_S * 1e6)
    return len(emu.commands)


def test_event_exact_10s_with_60hz_pattern_updates(benchmark) -> None:  # type: ignore[no-untyped-def]
    """The same device fed a new pattern 60 times a second over USB (a renderer's frame rate)."""
    benchmark.extra_info["device_s"] = DEVICE_S
    commands = benchmark.pedantic(_event_exact_render, rounds=3, iterations=1)
    assert commands == 9 + len(WRITES) - 1


def test_event_exact_1s_traced_into_memory(benchmark) -> None:  # type: ignore[no-untyped-def]
    """Cost of expanding every event (14 per channel, about 57 000 per device second) into a trace sink."""

    def traced() -> int:
        emu = TimedEmulator()
        sink = MemorySink()
        emu.attach(sink)
        emu.configure(CFG)
        emu.advance_to(1e6)
        sink.close()
        return len(sink.events)

    benchmark.extra_info["device_s"] = 1.0
    n = benchmark.pedantic(traced, rounds=3, iterations=1)
    assert n == 8 + 125 * (32 * 14 + 6)  # power-on levels, then 125 scans of 32 channels and a clear


def test_baseline_reference_step_through_1s(benchmark) -> None:  # type: ignore[no-untyped-def]
    """Baseline for the template cache: 125 scans (1 s) each stepped statement by statement."""

    def stepped() -> int:
        chain = POWER_ON_CHAIN
        pulses = 0
        for _ in range(125):
            r = reference_scan(CFG, chain)
            chain = r.chain_end
            pulses += len(r.pulses)
        return pulses

    benchmark.extra_info["device_s"] = 1.0
    assert benchmark.pedantic(stepped, rounds=3, iterations=1) == 4000


SCENARIO = Scenario("steady", [(0.0, configuration_bytes(CFG, 125))], DEVICE_S * 1e6, "usb")


def test_analytic_10s_32_electrodes_125hz(benchmark) -> None:  # type: ignore[no-untyped-def]
    benchmark.extra_info["device_s"] = DEVICE_S
    tl = benchmark.pedantic(run_analytic, args=(SCENARIO,), rounds=20, iterations=1)
    assert tl.scan_start_ns.size == 1249  # configured through the link: the first 32-channel scan at 10 ms


def test_analytic_10s_with_60hz_pattern_updates(benchmark) -> None:  # type: ignore[no-untyped-def]
    benchmark.extra_info["device_s"] = DEVICE_S
    sc = Scenario("render", WRITES, DEVICE_S * 1e6, "usb")
    tl = benchmark.pedantic(run_analytic, args=(sc,), rounds=5, iterations=1)
    assert len([e for e in tl.effects_ns.values() if e is not None]) == 9 + len(WRITES) - 1
