"""The v1.2 timed model's scan engine is a compiled form of the statement-by-statement walker.

``emulator/firmware/firmware_scan.py`` walks the firmware's interrupt statement by statement and is held
to the traces the firmware's own code logs (``tests/data/scan_traces_v12.jsonl``).  The timed model runs
``emulator/firmware/scan.py`` instead: the same interrupt compiled into per-kind channel blocks and cached
templates, fast enough for hours of scans.  Here the engine is checked against the walker for every
configuration hypothesis draws (and two scans in a row, the chain carried over): the same pin writes and
DAC codes at the same nanoseconds, and the same interrupt length.  The engine adds what the walker does
not log (the selected output, the stored ADC readings); the walker logs the chip-select pins, which the
engine folds into its exchange times.
"""

from __future__ import annotations

from hypothesis import given, settings
from hypothesis import strategies as st

from tactdeform_hw.emulator.firmware import firmware_scan as fs
from tactdeform_hw.emulator.firmware.firmware_scan import FirmwareScanConfig, trace_scan
from tactdeform_hw.emulator.firmware.scan import (
    POWER_ON_CHAIN,
    ScanConfig,
    ScanEngine,
    ScanTemplate,
    Signal,
    physical_outputs,
)
from tactdeform_hw.emulator.firmware.skin import DEFAULT_SKIN
from tactdeform_hw.emulator.timed.timing import DEFAULT_MODEL
from tactdeform_hw.protocol.firmware import V1_2

#: the walker's pins as the engine's signals (the chip selects have no signal of their own)
PIN_SIGNAL = {fs.BL: Signal.BL, fs.LE: Signal.LE, fs.POL: Signal.POL, fs.CLK: Signal.CLK, fs.DIN: Signal.DIN}
LOGGED = {*PIN_SIGNAL.values(), Signal.DAC}

configs = st.builds(
    dict,
    electrode_num=st.integers(0, 24),
    pattern=st.lists(st.sampled_from([0, 1, 2, 3, 0xF7]), min_size=24, max_size=24),
    polarity=st.integers(0, 1),
    pulse_height=st.integers(0, 4095),
    pulse_width=st.integers(1, 400),
    sense_pulse_height=st.integers(0, 255).map(lambda v: v << 2),
    sense_pulse_width=st.integers(0, 255),
    discharge_time=st.integers(0, 255),
    hv513_num=st.integers(0, 4),
)


def _walker(c: dict[str, int | list[int]], prior_scans: int) -> tuple[list[tuple[int, int, int]], int]:
    n = int(c["electrode_num"])  # type: ignore[arg-type]
    cfg = FirmwareScanConfig(
        electrode_num=n,
        stim_pattern=list(c["pattern"])[:n],  # type: ignore[arg-type]
        pulse_width=c["pulse_width"],  # type: ignore[arg-type]
        discharge_time=c["discharge_time"],  # type: ignore[arg-type]
        polarity=c["polarity"],  # type: ignore[arg-type]
        hv513_num=c["hv513_num"],  # type: ignore[arg-type]
        sense_pulse_height=c["sense_pulse_height"],  # type: ignore[arg-type]
        sense_pulse_width=c["sense_pulse_width"],  # type: ignore[arg-type]
        pulse_height=c["pulse_height"],  # type: ignore[arg-type]
        prior_scans=prior_scans,
    )
    trace = trace_scan(cfg, V1_2)
    events = []
    for t_us, kind, pin, value in trace.events:
        if kind == "DAC":
            events.append((round(t_us * 1000), int(Signal.DAC), int(value)))
        elif pin in PIN_SIGNAL:
            events.append((round(t_us * 1000), int(PIN_SIGNAL[pin]), int(value)))
    return events, round(trace.isr_return_us * 1000)


def _engine(tmpl: ScanTemplate, offset_ns: int = 0) -> list[tuple[int, int, int]]:
    t, sig, val = tmpl.events()
    return [(int(a) - offset_ns, int(b), int(v)) for a, b, v in zip(t, sig, val, strict=True) if b in LOGGED]


@settings(max_examples=150, deadline=None)
@given(c=configs)
def test_the_engine_is_the_walker_compiled(c: dict[str, int | list[int]]) -> None:
    n = int(c["electrode_num"])  # type: ignore[arg-type]
    cfg = ScanConfig(
        n,
        int(c["polarity"]),  # type: ignore[arg-type]
        int(c["pulse_height"]),  # type: ignore[arg-type]
        int(c["pulse_width"]),  # type: ignore[arg-type]
        int(c["sense_pulse_height"]),  # type: ignore[arg-type]
        int(c["sense_pulse_width"]),  # type: ignore[arg-type]
        int(c["discharge_time"]),  # type: ignore[arg-type]
        20_000,
        int(c["hv513_num"]),  # type: ignore[arg-type]
        bytes(list(c["pattern"])[:n]),  # type: ignore[arg-type]
    )
    engine = ScanEngine(DEFAULT_MODEL, DEFAULT_SKIN, physical_outputs("compact", 1))
    first = engine.template(cfg, POWER_ON_CHAIN)
    events, isr_ns = _walker(c, prior_scans=0)
    assert _engine(first) == events
    assert first.duration_ns == isr_ns
    second = engine.template(cfg, first.chain_end)  # the chain as the first scan left it
    events, isr_ns = _walker(c, prior_scans=1)
    assert _engine(second) == events
    assert second.duration_ns == isr_ns
