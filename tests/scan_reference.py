"""The test oracle for :mod:`tactdeform_hw.emulator.firmware.scan`: the firmware's timer interrupt stepped
through
statement by statement — slow, obviously right.  :class:`~tactdeform_hw.emulator.firmware.scan.ScanEngine`'s
templates are held to it event for event (``test_timing_scan.py``, the trace and v2 scan-trace tests, and
the timing benchmarks' baseline)."""

from __future__ import annotations

from typing import Any

from tactdeform_hw.emulator.firmware.scan import (
    POWER_ON_CHAIN,
    ChainState,
    PulseKind,
    ScanConfig,
    ScanResult,
    Signal,
    _lowest,
    _outputs,
)
from tactdeform_hw.emulator.firmware.skin import DEFAULT_SKIN, SkinModel
from tactdeform_hw.emulator.timed.timing import DEFAULT_MODEL, TimingModel
from tactdeform_hw.protocol.constants import OUTPUTS_PER_HV513, PATTERN_BIPHASIC, PATTERN_MONOPHASIC


def reference_scan(
    cfg: ScanConfig,
    chain: ChainState = POWER_ON_CHAIN,
    model: TimingModel = DEFAULT_MODEL,
    skin: SkinModel = DEFAULT_SKIN,
    outputs: int = 32,
) -> ScanResult:
    """Step through one scan statement by statement.  Times are ns after the alarm."""
    mask = (1 << outputs) - 1
    # an exchange (``DAAD``) from its call: its length, its DAC change, its ADC sample
    g, s, a, c = model.gpio_ns, model.exchange_ns, model.dac_in_exchange_ns, model.adc_in_exchange_ns
    ev: list[tuple[int, int, int]] = []
    pulses: list[tuple[Any, ...]] = []
    volts: dict[int, int] = {}
    st = {
        "t": model.isr_entry_ns,
        "bits": chain.bits,
        "latched": chain.latched,
        "pos": chain.position,
        "din": 0,
        "clk": 1 if chain.clk_high else 0,
    }

    def gpio(sig: Signal, val: int) -> None:
        st["t"] += g
        ev.append((st["t"], int(sig), val))
        if sig == Signal.DIN:
            st["din"] = val
        elif sig == Signal.CLK:
            if val == 1 and st["clk"] == 0:  # a rising edge shifts DIN in
                st["bits"] = ((st["bits"] << 1) | st["din"]) & mask
            st["clk"] = val
        elif sig == Signal.LE and val == 1:
            st["latched"] = st["bits"]
            ev.append((st["t"], int(Signal.SEL), _lowest(st["latched"])))

    def select(target: int) -> None:
        gpio(Signal.LE, 0)
        if target == 0:
            gpio(Signal.DIN, 1)
            gpio(Signal.CLK, 1)
            gpio(Signal.CLK, 0)
            st["pos"] = 0
        else:
            gpio(Signal.DIN, 0)
            for _ in range(target - st["pos"]):
                gpio(Signal.CLK, 1)
                gpio(Signal.CLK, 0)
            st["pos"] = target
        gpio(Signal.LE, 1)

    def exchange(code: int) -> int:
        """One SPI exchange setting the DAC; returns when the ADC sampled."""
        t0 = st["t"]
        ev.append((t0 + a, int(Signal.DAC), code))
        st["t"] = t0 + s
        return t0 + c

    def monophasic(ch: int, kind: PulseKind, pol: int, code: int, width: int) -> None:
        t0 = st["t"]
        ev.append((t0 + a, int(Signal.DAC), code))
        st["t"] = t0 + s
        if width >= model.pulse_wait_offset_us:
            st["t"] += model.delay_ns(width - model.pulse_wait_offset_us)
        t1 = st["t"]
        onset, end, sample = t0 + a, t1 + a, t1 + c
        outs = _outputs(st["latched"])
        o = skin.pulse(outs, code, (sample - onset) / 1000.0)
        ev.append((sample, int(Signal.ADC), o.adc_raw))
        ev.append((t1 + a, int(Signal.DAC), 0))
        st["t"] = t1 + s
        width_ns = end - onset
        pulses.append(
            (
                ch,
                int(kind),
                onset,
                width_ns,
                code,
                pol,
                o.current_ua,
                o.current_ua * width_ns / 1e6,
                o.voltage_code,
                sample,
                o.compliance_limited,
                outs,
            )
        )
        volts[ch] = o.voltage_code

    t_pol = cfg.polarity
    for ch in range(cfg.electrode_num):
        select(ch)
        gpio(Signal.POL, 1 if t_pol else 0)
        p = cfg.pattern[ch]
        if p == PATTERN_MONOPHASIC:
            monophasic(ch, PulseKind.MONO, 1 if t_pol else 0, cfg.pulse_height, cfg.pulse_width)
        elif p == PATTERN_BIPHASIC:
            gpio(Signal.POL, 1)
            monophasic(ch, PulseKind.BI_ANODIC, 1, cfg.pulse_height, cfg.pulse_width)
            gpio(Signal.POL, 0)
            monophasic(ch, PulseKind.BI_CATHODIC, 0, cfg.pulse_height, cfg.pulse_width)
        else:
            monophasic(ch, PulseKind.SENSE, 1 if t_pol else 0, cfg.sense_pulse_height, cfg.sense_pulse_width)
        exchange(0)
        gpio(Signal.POL, 1)
        gpio(Signal.BL, 0)
        if cfg.discharge_time > model.discharge_wait_offset_us:
            st["t"] += model.delay_ns(cfg.discharge_time - model.discharge_wait_offset_us)
        gpio(Signal.BL, 1)
    # the clear: "scan to position 8 * hv513" (signed loop count: no pulses when already past it)
    select(OUTPUTS_PER_HV513 * cfg.hv513_num)
    duration = st["t"] + model.isr_exit_ns
    chain_end = ChainState(st["pos"], st["bits"], st["latched"], st["clk"] == 1)
    return ScanResult(ev, pulses, duration, chain_end, volts)
