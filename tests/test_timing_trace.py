"""Waveform traces: VCD, CSV and JSON event lists, recording while serving, the missing-pyvcd error."""

from __future__ import annotations

import builtins
import csv
import json
import time
from pathlib import Path

import pytest

from tactdeform_hw.emulator.firmware.scan import ScanConfig, Signal
from tactdeform_hw.emulator.records.trace import CsvSink, JsonSink, LiveTrace, MemorySink, VcdSink, open_trace
from tactdeform_hw.emulator.timed.model_v1_2 import TimedEmulator, timed_emulator
from tactdeform_hw.errors import ConfigurationError, MissingDependencyError
from tactdeform_hw.protocol import commands as c
from tactdeform_hw.protocol.firmware import FIRMWARES

from .scan_reference import reference_scan

CFG = ScanConfig.make(4, [1, 2, 0, 1], sense_height_raw=2, sense_width_us=20, rate_hz=500)


def record(*sinks: object, until_us: float = 6_500) -> TimedEmulator:
    emu = TimedEmulator()
    for s in sinks:
        emu.attach(s)
    emu.configure(CFG)
    emu.write(c.encode_discharge(45), 3_000)
    emu.advance_to(until_us)
    for s in sinks:
        s.close()  # type: ignore[attr-defined]
    return emu


def test_event_lists_agree_with_each_other_and_the_scans(tmp_path: Path) -> None:
    mem = MemorySink()
    csv_path, json_path = tmp_path / "t.csv", tmp_path / "t.json"
    emu = record(mem, CsvSink(csv_path), JsonSink(json_path))
    rows = list(csv.DictReader(csv_path.open()))
    items = json.loads(json_path.read_text())
    assert len(rows) == len(items) == len(mem.events)
    assert [int(r["time_ns"]) for r in rows] == [e["t_ns"] for e in items] == [e[0] for e in mem.events]
    times = [e[0] for e in mem.events]
    assert times == sorted(times)
    # the scans' events, shifted to their alarms, in order
    sig = [(t, n, v) for t, n, v in mem.events if not n.startswith("MARK") and t > 0]
    starts = [r.start_ns + j * r.stride_ns for r in emu.runs for j in range(r.count)]
    assert starts == [2_000_000, 4_000_000, 6_000_000]
    ref = reference_scan(CFG)
    assert sig[: len(ref.events)] == [(2_000_000 + t, Signal(s).name, v) for t, s, v in ref.events]
    # the discharge command lands between two scans, as a marker
    marks = [(t, n, v) for t, n, v in mem.events if n == "MARK:command"]
    assert len(marks) == 1 and marks[0][2]["name"] == "DISCHARGE" and 3_000_000 < marks[0][0] < 6_000_000
    assert any(r["kind"] == "command" and r["name"] == "DISCHARGE" for r in rows)


def test_vcd_opens_with_the_signals_and_changes(tmp_path: Path) -> None:
    pytest.importorskip("vcd")
    path = tmp_path / "scan.vcd"
    record(VcdSink(path), until_us=4_500)
    text = path.read_text()
    assert "$timescale 1 ns $end" in text
    for name in ("BL", "LE", "POL", "CLK", "DIN", "DAC", "SEL", "ADC", "event"):
        assert f" {name} $end" in text
    # the first DAC change of the first scan: 2000 us + 2 us + 6 GPIO writes + 3.3 us; code 100 in binary
    assert "#2005600\nb1100100 " in text
    assert "bx " in text  # SEL: no output latched at power-on
    from vcd.reader import TokenKind, tokenize

    with path.open("rb") as f:
        kinds = {t.kind for t in tokenize(f)}
    assert TokenKind.CHANGE_TIME in kinds and TokenKind.CHANGE_VECTOR in kinds


def test_missing_pyvcd_names_the_extra(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    real_import = builtins.__import__

    def fake_import(name: str, *args: object, **kwargs: object) -> object:
        if name == "vcd" or name.startswith("vcd."):
            raise ImportError("no vcd")
        return real_import(name, *args, **kwargs)  # type: ignore[arg-type]

    monkeypatch.setattr(builtins, "__import__", fake_import)
    with pytest.raises(MissingDependencyError) as exc:
        VcdSink(tmp_path / "x.vcd")
    assert exc.value.package == "pyvcd" and exc.value.extra == "trace"


def test_open_trace_picks_the_format_by_suffix(tmp_path: Path) -> None:
    for suffix, cls in ((".csv", CsvSink), (".json", JsonSink)):
        s = open_trace(tmp_path / f"a{suffix}")
        assert isinstance(s, cls)
        s.close()
    with pytest.raises(ConfigurationError):
        open_trace(tmp_path / "a.txt")


def test_live_trace_records_while_serving(tmp_path: Path) -> None:
    now = [0.0]
    path = tmp_path / "live.csv"
    with LiveTrace(path, link="uart", clock=lambda: now[0]) as live:
        now[0] = 0.001
        assert live.feed(c.encode_electrode_num(2)) == b""
        now[0] = 0.005
        live.poll()
        now[0] = 0.006
        live.feed(c.MEASURE_REQUEST)
        now[0] = 0.030
        reply = live.poll()
        assert reply == c.encode_measure_reply(live.emulator.registers.voltage[:2])
        assert live.emulator.now_us == pytest.approx(30_000)
    rows = list(csv.DictReader(path.open()))
    assert any(r["kind"] == "command" and r["name"] == "MEASURE" for r in rows)
    assert any(r["name"] == "LE" for r in rows)  # scans ran (every 10 ms at power-on)
    assert live.closed


def test_live_trace_as_a_pty_server_hook(tmp_path: Path) -> None:
    pytest.importorskip("vcd")
    import serial

    from tactdeform_hw.emulator import Emulator
    from tactdeform_hw.emulator.serving.pty_server import PtyServer

    path = tmp_path / "served.vcd"
    live = LiveTrace(path, link="usb")
    with PtyServer(Emulator(), hook=live.hook) as server:
        port = serial.Serial(server.path, 921600, timeout=1)
        port.write(c.encode_electrode_num(4) + c.HV513_COUNT_REQUEST)
        assert port.read(1) == b"\x04"  # answered by the served (untimed) emulator
        port.close()
        time.sleep(0.02)  # the recorder's timed model reads one command per 1 ms tick: let a few pass
        live.poll()
    live.close()
    text = path.read_text()
    assert "event" in text and "command:ELECTRODE_NUM" in text and "command:HV513_COUNT" in text
    assert live.emulator.registers.electrode_num == 4


def test_vcd_of_the_same_session_is_byte_identical_and_carries_no_date(tmp_path: Path) -> None:
    """Two recordings of the same input give the same bytes: no wall-clock ``$date`` in the header."""
    pytest.importorskip("vcd")
    first, second = tmp_path / "a.vcd", tmp_path / "b.vcd"
    record(VcdSink(first), until_us=4_500)
    record(VcdSink(second), until_us=4_500)  # pyvcd's own date has microseconds: it would differ
    assert first.read_bytes() == second.read_bytes()
    assert "$date" not in first.read_text()


@pytest.mark.parametrize("sink_class", [CsvSink, JsonSink, VcdSink])
def test_a_sink_leaves_a_passed_stream_open_and_flushed_and_a_file_it_opened_whole(
    sink_class: type[CsvSink] | type[JsonSink] | type[VcdSink], tmp_path: Path
) -> None:
    import io

    if sink_class is VcdSink:
        pytest.importorskip("vcd")
    stream = io.StringIO()
    flushed: list[bool] = []
    stream.flush = lambda: flushed.append(True)  # type: ignore[method-assign]
    path = tmp_path / "t.trace"
    for target in (stream, path):
        sink = sink_class(target)
        sink.begin(0)
        sink.marker(1000, "command", {"name": "MEASURE"})
        sink.close()
    assert not stream.closed and flushed and stream.getvalue()
    assert path.read_bytes().decode("utf-8") == stream.getvalue()  # the whole trace reached the file


@pytest.mark.parametrize("firmware", list(FIRMWARES))
def test_a_trace_marks_a_reset_and_stops_when_detached(firmware: str) -> None:
    """On every version's timed model: a reset is a marker at its time, and a detached sink receives
    nothing more while the board scans on after the reset."""
    mem = MemorySink()
    emu = timed_emulator(firmware=firmware)
    emu.attach(mem)
    emu.write(bytes([0xFC, 4]), 0.0)  # electrode count 4: the same command on every version
    emu.advance_to(10_000.0)  # the power-on 100 Hz: scans at 0 and 10 ms
    scans_at_reset = emu.scan_rate(emu.now_us)[0]
    emu.reset("test")
    emu.detach(mem)
    emu.advance_to(40_000.0)
    mem.close()
    assert [e[0] for e in mem.events if e[1] == "MARK:reset"] == [10_000_000]
    assert any(n == "DAC" for _, n, _ in mem.events)  # the scans before the reset were traced
    assert emu.scan_rate(emu.now_us)[0] > scans_at_reset  # the board scanned again after the reset ...
    assert max(e[0] for e in mem.events) < 10_500_000  # ... into no sink: nothing after the 10 ms scan
