"""Waveform traces of the v2 timed model: the scans' events as the firmware's own walk, and markers."""

from __future__ import annotations

import csv
import json
from pathlib import Path

from tactdeform_hw.emulator.firmware.firmware_scan import HOST_BUILD
from tactdeform_hw.emulator.firmware.skin import DEFAULT_SKIN, SkinModel
from tactdeform_hw.emulator.records.trace import CsvSink, MemorySink
from tactdeform_hw.emulator.timed.model_v2 import TimedEmulatorV2
from tactdeform_hw.protocol.commands import V2_COMMANDS as c

from .conftest import DATA

GOLDEN = "tactdeform_32mono_h100_w200_d45_125hz"
SETUP = (
    c.encode_electrode_num(32)
    + c.encode_stim_mode(0)
    + c.encode_pulse_width(200)
    + c.encode_discharge(45)
    + c.encode_frequency(125)
    + c.encode_pattern([100] * 32)
)
#: the golden traces' GPIO pins by the traced signal's name (the chip selects are not traced)
PINS = {1: "BL", 2: "LE", 3: "POL", 4: "CLK", 5: "DIN"}


def _golden() -> dict:
    lines = (DATA / "scan_traces_v2.jsonl").read_text().splitlines()
    return next(g for g in map(json.loads, filter(None, lines)) if g["name"] == GOLDEN)


def _record(*sinks: object, skin: SkinModel | None = None) -> TimedEmulatorV2:
    """The golden setting on the host build's conventions; ``skin=None``: the ADC reads back the DAC code
    as the host build's SPI stub does (what the golden traces hold)."""
    emu = TimedEmulatorV2(conventions=HOST_BUILD, skin=skin)
    for s in sinks:
        emu.attach(s)
    emu.write(SETUP, 0.0)
    emu.advance_to(30_000.0)
    for s in sinks:
        s.close()  # type: ignore[attr-defined]
    return emu


def test_v2_trace_holds_each_scan_as_the_firmware_walks_it(tmp_path: Path) -> None:
    """A scan of the golden TactDeform setting: every BL/LE/POL/CLK/DIN/DAC event of the firmware's
    trace, in order and value, shifted to the scan's alarm; SEL follows the latched output, ADC stores
    the heights; the commands arrive as markers; the CSV carries the same rows."""
    golden = _golden()
    mem = MemorySink()
    path = tmp_path / "v2.csv"
    emu = _record(mem, CsvSink(path))
    scan = next(s for s in emu.scans if s.electrode_num == 32)
    assert scan.heights == tuple(golden["config"]["stim_pattern"])
    assert scan.duration_ns == round(golden["isr_return_us"] * 1000)
    inside = [e for e in mem.events if scan.start_ns <= e[0] <= scan.end_ns and not e[1].startswith("MARK")]
    want = [
        (scan.start_ns + round(t * 1000), PINS[pin] if kind == "GPIO" else "DAC", value)
        for t, kind, pin, value in golden["events"]
        if kind == "DAC" or pin in PINS
    ]
    assert [e for e in inside if e[1] not in ("SEL", "ADC")] == want
    assert [v for _, n, v in inside if n == "SEL"] == [*range(32), -1]
    assert [v for _, n, v in inside if n == "ADC"] == golden["voltage"]
    commands = [d["name"] for _, n, d in mem.events if n == "MARK:command"]
    assert commands[:2] == ["ELECTRODE_NUM", "STIM_MODE"] and "PATTERN" in commands[-1]
    rows = list(csv.DictReader(path.open()))
    assert len(rows) == len(mem.events)
    assert [int(r["time_ns"]) for r in rows] == [e[0] for e in mem.events]


def test_emulate_trace_records_a_served_v2_board(tmp_path: Path) -> None:
    """``emulate --pty --firmware v2 --trace FILE --spy``: a client's setting is scanned into the trace
    (its DAC codes, the command markers), and the spy stamps bytes with the board's µs."""
    import signal
    import subprocess
    import sys
    import time

    import serial

    path = tmp_path / "served.csv"
    proc = subprocess.Popen(
        [sys.executable, "-m", "tactdeform_hw.cli", "emulate", "--pty", "--firmware", "v2", "--quiet"]
        + ["--spy", "--trace", str(path)],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        device = proc.stdout.readline().strip()  # type: ignore[union-attr]
        with serial.Serial(device, timeout=1) as port:
            port.write(SETUP)
            time.sleep(0.3)
    finally:
        proc.send_signal(signal.SIGINT)
        _, err = proc.communicate(timeout=20)
    assert proc.returncode == 0, err
    assert f"trace written to {path}" in err and "Traceback" not in err
    assert any(line.startswith("t=") and "us host->dev f" in line for line in err.splitlines())
    rows = list(csv.DictReader(path.open()))
    assert {r["value"] for r in rows if r["name"] == "DAC"} >= {"100", "0"}
    names = [r["name"] for r in rows if r["kind"] == "command"]
    assert names[:2] == ["ELECTRODE_NUM", "STIM_MODE"]


def test_v2_trace_adc_holds_the_readings_the_measure_reply_returns() -> None:
    """With the skin model the ADC rows are the readings stored, so a trace and a measure reply agree."""
    mem = MemorySink()
    emu = _record(mem, skin=DEFAULT_SKIN)
    scan = next(s for s in emu.scans if s.electrode_num == 32)
    inside = [e for e in mem.events if scan.start_ns <= e[0] <= scan.end_ns]
    assert [v for _, n, v in inside if n == "ADC"] == emu.registers.voltage[:32]
