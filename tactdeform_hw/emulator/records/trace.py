"""Waveform traces of the emulated controller: VCD for GTKWave, and CSV / JSON event lists.

A trace sink is attached to a :class:`~.timed.TimedEmulator` (``emu.attach(sink)``) and receives every
scan run and every marker (command effects, losses, resets) as the emulator simulates them.  Sinks write
in time order: a scan's events are held until the next scan starts — by then every marker that falls
inside it has arrived (the parser never runs during a scan and deliveries are processed in time order).

Signals: ``BL LE POL CLK DIN`` (1 bit), ``DAC`` (12-bit code), ``SEL`` (the lowest HV513 output latched
on, ``x`` when none), ``ADC`` (the 12-bit reading the firmware stores), and, in VCD, a string variable
``event`` carrying the markers.  Time resolution 1 ns.  A VCD has no ``$date``: the same session gives
the same bytes.

:class:`LiveTrace` runs a timed emulator against the wall clock, for recording while a session is served
(``tactdeform-hw emulate --pty --trace FILE``).  The VCD writer needs ``pyvcd`` (extra ``trace``),
imported only when a VCD is written.
"""

from __future__ import annotations

import csv
import heapq
import json
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import IO, Any

import numpy as np

from tactdeform_hw.emulator.firmware.board import Board
from tactdeform_hw.emulator.firmware.scan import POWER_ON_LEVELS, SIGNAL_BITS, Signal
from tactdeform_hw.emulator.records.reports import EventRun, ScanRun
from tactdeform_hw.emulator.timed.link import LinkModel
from tactdeform_hw.emulator.timed.timing import TimingModel
from tactdeform_hw.errors import ConfigurationError, MissingDependencyError

SIGNAL_NAMES = {s: s.name for s in Signal}
#: The clock every trace counts, named in a VCD's header: the one ``emulate`` prints its times in (µs).
TIME_BASE = "time: the emulated board's virtual time since its clock started (emulate: since serving began)"


def run_events(run: ScanRun | EventRun) -> Iterator[tuple[int, int, int]]:
    """(absolute time ns, Signal, value) of every event of every scan in ``run``."""
    if isinstance(run, EventRun):
        T, S, V = run.events
        yield from zip((T + run.start_ns).tolist(), S.tolist(), V.tolist())
        return
    T, S, V = run.template.events()
    if run.cut_ns is not None:
        keep = T < run.cut_ns
        T, S, V = T[keep], S[keep], V[keep]
    s_l, v_l = S.tolist(), V.tolist()
    for j in range(run.count):
        base = run.start_ns + j * run.stride_ns
        yield from zip((T + base).tolist(), s_l, v_l)


class TraceSink:
    """Base sink: merges scan events and markers in time order and hands them to :meth:`_signal` and
    :meth:`_marker`."""

    def __init__(self) -> None:
        self._held: list[ScanRun | EventRun] = []
        self._markers: list[tuple[int, int, str, dict[str, Any]]] = []
        self._seq = 0
        self._closed = False

    # --- what the emulator calls ------------------------------------------------------------------------

    def begin(self, t_ns: int) -> None:
        for sig, val in POWER_ON_LEVELS.items():
            self._signal(t_ns, int(sig), val)

    def scan_run(self, run: ScanRun | EventRun) -> None:
        self._flush(run.start_ns)
        self._held.append(run)

    def marker(self, t_ns: int, kind: str, detail: dict[str, Any]) -> None:
        self._seq += 1
        heapq.heappush(self._markers, (t_ns, self._seq, kind, detail))

    def close(self) -> None:
        if self._closed:
            return
        self._flush(None)
        self._finish()
        self._closed = True

    def __enter__(self) -> TraceSink:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # --- merging ------------------------------------------------------------------------------------------

    def _flush(self, before: int | None) -> None:
        """Write everything held, and every marker earlier than ``before`` (all when None)."""
        marks = self._markers
        for run in self._held:
            for t, s, v in run_events(run):
                while marks and marks[0][0] <= t:
                    m = heapq.heappop(marks)
                    self._marker(m[0], m[2], m[3])
                self._signal(t, s, v)
        self._held = []
        while marks and (before is None or marks[0][0] < before):
            m = heapq.heappop(marks)
            self._marker(m[0], m[2], m[3])

    # --- what subclasses write ------------------------------------------------------------------------------

    def _signal(self, t_ns: int, sig: int, value: int) -> None:
        raise NotImplementedError

    def _marker(self, t_ns: int, kind: str, detail: dict[str, Any]) -> None:
        raise NotImplementedError

    def _finish(self) -> None:
        pass


class MemorySink(TraceSink):
    """Keeps every event as ``(t_ns, name, value)`` (markers: ``(t_ns, "MARK:<kind>", detail)``)."""

    def __init__(self) -> None:
        super().__init__()
        self.events: list[tuple[int, str, Any]] = []

    def _signal(self, t_ns: int, sig: int, value: int) -> None:
        self.events.append((t_ns, SIGNAL_NAMES[Signal(sig)], value))

    def _marker(self, t_ns: int, kind: str, detail: dict[str, Any]) -> None:
        self.events.append((t_ns, f"MARK:{kind}", detail))


def _open_text(target: str | Path | IO[str]) -> tuple[IO[str], bool]:
    if isinstance(target, (str, Path)):
        return open(target, "w", newline="", encoding="utf-8"), True
    return target, False


def _release_text(f: IO[str], own: bool) -> None:
    """The end of a sink's writing: a file it opened (``own``, from :func:`_open_text`) is closed; a
    stream the caller passed stays open for the caller, flushed so the trace is all in it."""
    if own:
        f.close()
    else:
        f.flush()


class CsvSink(TraceSink):
    """``time_ns,time_us,kind,name,value``: one row per signal change or marker (JSON detail)."""

    def __init__(self, target: str | Path | IO[str]) -> None:
        super().__init__()
        self._f, self._own = _open_text(target)
        self._w = csv.writer(self._f)
        self._w.writerow(["time_ns", "time_us", "kind", "name", "value"])

    def _signal(self, t_ns: int, sig: int, value: int) -> None:
        self._w.writerow([t_ns, f"{t_ns / 1000:.3f}", "signal", SIGNAL_NAMES[Signal(sig)], value])

    def _marker(self, t_ns: int, kind: str, detail: dict[str, Any]) -> None:
        self._w.writerow(
            [t_ns, f"{t_ns / 1000:.3f}", kind, detail.get("name", ""), json.dumps(detail, default=str)]
        )

    def _finish(self) -> None:
        _release_text(self._f, self._own)


class JsonSink(TraceSink):
    """A JSON array of ``{"t_ns", "t_us", "kind", "name", "value"}`` objects, streamed."""

    def __init__(self, target: str | Path | IO[str]) -> None:
        super().__init__()
        self._f, self._own = _open_text(target)
        self._f.write("[")
        self._first = True

    def _write(self, obj: dict[str, Any]) -> None:
        self._f.write(("\n" if self._first else ",\n") + json.dumps(obj, default=str))
        self._first = False

    def _signal(self, t_ns: int, sig: int, value: int) -> None:
        self._write(
            {
                "t_ns": t_ns,
                "t_us": t_ns / 1000,
                "kind": "signal",
                "name": SIGNAL_NAMES[Signal(sig)],
                "value": value,
            }
        )

    def _marker(self, t_ns: int, kind: str, detail: dict[str, Any]) -> None:
        self._write(
            {"t_ns": t_ns, "t_us": t_ns / 1000, "kind": kind, "name": detail.get("name", ""), "value": detail}
        )

    def _finish(self) -> None:
        self._f.write("\n]\n")
        _release_text(self._f, self._own)


class VcdSink(TraceSink):
    """A Value Change Dump (IEEE 1364) that GTKWave opens; needs ``pyvcd``."""

    def __init__(self, target: str | Path | IO[str], scope: str = "etactile") -> None:
        try:
            from vcd import VCDWriter
        except ImportError as exc:
            raise MissingDependencyError("pyvcd", "trace", "writing VCD waveform traces") from exc
        super().__init__()
        self._f, self._own = _open_text(target)
        # no $date (pyvcd's default is the wall clock): a trace is a function of its session alone, so two
        # recordings of the same input are byte-identical and can be compared with cmp or diff
        self._w = VCDWriter(
            self._f,
            timescale="1 ns",
            date="",
            comment=TIME_BASE,
            version="tactdeform_hw emulator",
        )
        self._vars = {}
        for sig in Signal:
            bits = SIGNAL_BITS[sig]
            self._vars[int(sig)] = self._w.register_var(scope, sig.name, "wire", size=bits)
        self._event = self._w.register_var(scope, "event", "string")

    def _signal(self, t_ns: int, sig: int, value: int) -> None:
        var = self._vars[sig]
        if sig == Signal.SEL and value < 0:
            self._w.change(var, t_ns, "x")
        else:
            self._w.change(var, t_ns, value)

    def _marker(self, t_ns: int, kind: str, detail: dict[str, Any]) -> None:
        text = kind if not detail.get("name") else f"{kind}:{detail['name']}"
        self._w.change(self._event, t_ns, text.replace(" ", "_"))

    def _finish(self) -> None:
        self._w.close()
        _release_text(self._f, self._own)


TRACE_FORMATS: dict[str, type[VcdSink] | type[CsvSink] | type[JsonSink]] = {
    ".vcd": VcdSink,
    ".csv": CsvSink,
    ".json": JsonSink,
}


def open_trace(path: str | Path) -> TraceSink:
    """A sink for ``path`` chosen by its suffix: ``.vcd``, ``.csv`` or ``.json``."""
    suffix = Path(path).suffix.lower()
    cls = TRACE_FORMATS.get(suffix)
    if cls is None:
        raise ConfigurationError(
            f"trace file {str(path)!r}: unknown suffix {suffix!r}; use .vcd, .csv or .json"
        )
    return cls(path)


class LiveTrace:
    """A timed emulator that follows the wall clock and records a trace while bytes are served.

    ``feed(data)`` delivers host bytes at the current wall time and returns the reply bytes that have
    reached the host by then; ``poll()`` only advances the clock (call it every few ms so replies and
    the trace keep up); ``close()`` finishes the file.  Serve the returned bytes to make the session run
    on the timed model, or keep answering from the untimed emulator and use this purely as a recorder —
    the two differ only where timing matters (lost bytes, overruns, a watchdog reboot).

    :meth:`hook` has the signature of :class:`~tactdeform_hw.emulator.serving.pty_server.PtyServer`'s byte
    hook
    (``hook(direction, data, t)`` with ``time.monotonic()`` timestamps), so a server can feed it directly
    while it keeps answering from its own emulator.  The methods are thread-safe (a server thread feeds,
    the main thread polls).

    A 32-electrode, 125 Hz session writes about 57 000 events (14 per channel) per second of wall time.
    """

    def __init__(
        self,
        path: str | Path,
        *,
        board: str | Board = "compact",
        switching_boards: int = 1,
        link: str | LinkModel = "usb",
        model: TimingModel | None = None,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        from tactdeform_hw.emulator.timed.model_v1_2 import TimedEmulator

        self.emulator = TimedEmulator(board, switching_boards, link=link, model=model)
        self.sink = open_trace(path)
        self.emulator.attach(self.sink)
        self._clock = clock
        self._t0 = clock()
        self._lock = threading.Lock()
        self.closed = False

    def _at_us(self, t: float | None = None) -> float:
        now = self._clock() if t is None else t
        return max(self.emulator.now_us, (now - self._t0) * 1e6)

    def feed(self, data: bytes, t: float | None = None) -> bytes:
        """Host bytes arriving now (or at clock time ``t``); returns the replies that reached the host."""
        with self._lock:
            if self.closed:
                return b""
            at = self._at_us(t)
            self.emulator.advance_to(at)
            self.emulator.write(data, at)
            return self.emulator.read_tx()

    def hook(self, direction: str, data: bytes, t: float) -> None:
        """A pty server's byte hook: host-to-device bytes drive the timed model; replies are its own."""
        if direction == "host->dev":
            self.feed(data, t)

    def poll(self) -> bytes:
        """Advance to now; returns the replies that reached the host meanwhile."""
        with self._lock:
            if self.closed:
                return b""
            self.emulator.advance_to(self._at_us())
            return self.emulator.read_tx()

    def close(self) -> None:
        self.poll()
        with self._lock:
            if self.closed:
                return
            self.emulator.detach(self.sink)
            self.sink.close()
            self.closed = True

    def __enter__(self) -> LiveTrace:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def events_table(sink: MemorySink) -> dict[str, np.ndarray]:
    """A :class:`MemorySink`'s signal events as columns (``t_ns``, ``name``, ``value``)."""
    sig = [(t, n, v) for t, n, v in sink.events if not n.startswith("MARK:")]
    return {
        "t_ns": np.array([e[0] for e in sig], dtype=np.int64),
        "name": np.array([e[1] for e in sig]),
        "value": np.array([e[2] for e in sig], dtype=np.int64),
    }


__all__ = [
    "CsvSink",
    "JsonSink",
    "LiveTrace",
    "MemorySink",
    "TraceSink",
    "VcdSink",
    "events_table",
    "open_trace",
    "run_events",
]
