"""Firmware v2 in time: its parser on the command timer, its scans on the stimulation timer, a link.

The same pieces as the v1.2 timed model, with v2's rules: the main loop sleeps one RTOS tick only after a
call that made no progress (:class:`~.parser_v2.ParserV2`), the parser reads Timer2 (µs) for the 2 s
command timeout, 0xF5 disables the stimulation alarm while it senses the stack (a scan due meanwhile
fires when the alarm is re-enabled; as on v1.2, the stimulation timer starts ``timer_start_us`` after
boot and the RTOS ticks run from boot shifted by ``tick_phase_us``), and each scan is the v2 interrupt of
:mod:`.firmware_scan`: parameters snapshotted at its start, a DAC code per channel, the mode choosing the
waveform, no DAC write in the discharge.  The interrupt pre-empts the parser, never the reverse: a parser
call costs its overhead plus one byte time per byte read (the timing model's assumptions), plus the
duration of each scan whose alarm falls inside it, whatever the call does (an idle poll then sleeps from
the scans' end; 0xF6 lets in the old alarm's scan before ``setPeriodUs`` re-arms the timer, 0xF5 those due
before its ``timerAlarmDisable``, and its detection ends with ``hv513Init``'s pin writes), and an alarm
inside the call that copies a pattern scans the elements copied so far at their new heights and the rest
at their old ones (a :data:`~.hazards.HazardKind.TORN_PATTERN`; v2's window is the copy, not the transfer
— and only in modes 0 and 1: a scan in mode 2 uses no height of the pattern, so it cannot be torn).  A
scan that overruns (a period or more) never gives the processor back: the call it interrupts stops for
good at the first of ``runEtactileKit``'s read points at or after the alarm (:class:`InterruptedCallsV2`),
with what it read and stored before that point and nothing after.

Served on the wall clock (:class:`~.realtime.RealtimeEmulator` with ``firmware="v2"``) it tells the
runner when it next does something a host could notice (:meth:`TimedEmulatorV2.next_event_us`: not the
idle polls, which change nothing), resets, and records a command a new host connection inherits
(:meth:`TimedEmulatorV2.new_client`).  As on v1.2, :meth:`~.base.TimedModelBase.state` is exact at the
granularity of a parser call: a call's effects show from its start (``applied`` and ``commands`` are
stamped with it), a few µs before the firmware stores the register it has read.  Scan shapes are walked
once per configuration: on v2 a channel's timing does not depend on its height (:func:`_scan_shape`).

Every scan is recorded (:class:`ScanRecordV2`) with the parameters it ran and when each channel's
current started, so safety can be judged on the pulses delivered; mode 2 with a zero pattern that
still drives the sense current is a :data:`~.hazards.HazardKind.MODE_SENSE_ALL` hazard.  A channel at or past
the stack's last HV513 output (:attr:`TimedEmulatorV2.outputs`) is clocked out of the chain's end: its DAC
code is written, but no pulse is delivered (as v1.2's physical chain; the count of chips the firmware
believes in is not modelled beyond that: extra ones left in a longer chain are v1.2's alone).  The same
judgement as on v1.2 needs the same books, kept here in v1.2's shapes: ``reports.pulse_table()`` (every
pulse as numpy columns), ``losses`` (:class:`~.reports.LossReport`: bytes that never took effect — a full
queue, a reboot, a command the 2 s timeout discarded) and ``commands`` (each command applied, with
whether it is the command the host wrote at that offset: the host's stream is read with the v2 table as
it is written).
"""

from __future__ import annotations

import heapq
from bisect import bisect_right
from collections.abc import Callable
from dataclasses import dataclass, replace
from functools import lru_cache
from itertools import repeat
from typing import Any

import numpy as np

from tactdeform_hw.emulator.core import Emulator
from tactdeform_hw.emulator.firmware.board import Board
from tactdeform_hw.emulator.firmware.firmware_scan import (
    BL,
    CLK,
    DEFAULT_CONVENTIONS,
    DIN,
    LE,
    POL,
    FirmwareScanConfig,
    ScanConventions,
    trace_scan,
)
from tactdeform_hw.emulator.firmware.hazards import Hazard, HazardKind
from tactdeform_hw.emulator.firmware.models import entry_part
from tactdeform_hw.emulator.firmware.parser_v2 import CallCut, ParserV2, ReadPoint
from tactdeform_hw.emulator.firmware.registers import V2_SCAN_REGISTERS, RegistersV2
from tactdeform_hw.emulator.firmware.scan import Signal, physical_outputs, pulse_kind_of
from tactdeform_hw.emulator.firmware.skin import DEFAULT_SKIN, SkinModel
from tactdeform_hw.emulator.records.reports import EventRun, LossReport, RowPulseTable
from tactdeform_hw.emulator.timed.base import TimedModelBase
from tactdeform_hw.emulator.timed.link import (
    ByteBurst,
    Delivery,
    LinkModel,
    Scheduled,
    expanded,
    make_link,
    next_key,
    reply_link,
    unread_after,
)
from tactdeform_hw.emulator.timed.model_v1_2 import hv513_count_ns
from tactdeform_hw.emulator.timed.timing import DEFAULT_MODEL, TimingModel
from tactdeform_hw.errors import ConfigurationError, LimitError
from tactdeform_hw.protocol.constants import OUTPUTS_PER_HV513
from tactdeform_hw.protocol.firmware import V2, FirmwareSpec, OpcodeV2
from tactdeform_hw.protocol.state import BoardState
from tactdeform_hw.protocol.units import DEFAULT_TRANSFER, CurrentTransfer

#: StimulationMode 2 (impedance only): every channel gets the sense pulse, the pattern's heights unused.
_MODE_IMPEDANCE = 2
#: A time the main loop never reaches (it hangs: :meth:`TimedEmulatorV2.stop_reading`).
_NEVER = 1 << 62


@dataclass(frozen=True)
class ScanRecordV2:
    """One v2 scan: when it ran, what it snapshotted, and each channel's current onset."""

    index: int
    start_ns: int
    duration_ns: int
    electrode_num: int
    stim_mode: int
    polarity: int
    pulse_width: int
    sense_pulse_height: int
    sense_pulse_width: int
    heights: tuple[int, ...]  # the pattern as read per channel (mode 2: ignored)
    onset_ns: tuple[int, ...]  # per channel, relative to start_ns: the first DAC edge
    codes: tuple[int, ...]  # per channel, the DAC code of its (first) pulse
    pulses: tuple[PulseRow, ...] = ()  # every non-zero current: (channel, onset ns, code, width ns, POL)

    @property
    def end_ns(self) -> int:
        return self.start_ns + self.duration_ns

    def live_channels(self) -> list[int]:
        """Channels that received a non-zero current in this scan."""
        return [ch for ch, code in enumerate(self.codes) if code]


#: One delivered pulse of a scan: (channel, onset ns after the alarm, DAC code, width ns, POL level).
PulseRow = tuple[int, int, int, int, int]


def _pulse_rows(events: list[list[Any]], starts: list[float]) -> tuple[PulseRow, ...]:
    """Every non-zero DAC level of a scan, from its edge to the next DAC edge, with the POL level then
    (times in ns)."""
    rows: list[PulseRow] = []
    pol = 1
    ch = -1
    open_: tuple[int, int, int, int] | None = None
    for t, kind, pin, value in events:
        while ch + 1 < len(starts) and t >= starts[ch + 1]:
            ch += 1
        if kind == "GPIO" and pin == 3:
            pol = value
        elif kind == "DAC":
            t_ns = t
            if open_ is not None:
                c0, t0, code, p0 = open_
                rows.append((c0, t0, code, t_ns - t0, p0))
                open_ = None
            if value:
                open_ = (ch, t_ns, value, pol)
    return tuple(rows)


@lru_cache(maxsize=1024)
def _shape(
    cfg: FirmwareScanConfig, conv: ScanConventions
) -> tuple[int, tuple[int, ...], tuple[int, ...], tuple[int, ...], tuple[PulseRow, ...]]:
    """(duration, onsets, codes, voltages, pulses) of one scan, from the statement walker (in ns)."""
    tr = trace_scan(cfg, "v2", conv, times_ns=True)
    starts = tr.channel_start_us  # (ns: times_ns)
    dacs = [(e[0], e[3]) for e in tr.events if e[1] == "DAC"]
    onsets: list[int] = []
    codes: list[int] = []
    k = 0
    for s in starts:
        while k < len(dacs) and dacs[k][0] < s:
            k += 1
        onsets.append(dacs[k][0] if k < len(dacs) else 0)
        codes.append(dacs[k][1] if k < len(dacs) else 0)
    return (
        int(tr.isr_return_us),
        tuple(onsets),
        tuple(codes),
        tuple(tr.voltage),
        _pulse_rows(tr.events, starts),
    )


#: The scan's GPIO pins as traced signals (the chip selects are not traced, as on v1.2).
_TRACED_PINS = {BL: Signal.BL, LE: Signal.LE, POL: Signal.POL, CLK: Signal.CLK, DIN: Signal.DIN}


@lru_cache(maxsize=256)
def _trace_events(
    cfg: FirmwareScanConfig, conv: ScanConventions
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(time ns after the alarm, Signal, value) of one v2 scan, for trace sinks: the statement walker's
    GPIO and DAC events in its order, plus the signals v1.2's traces derive — ``SEL`` (the lowest HV513
    output latched on, -1 for none) at each rising LE, from the shift register the CLK/DIN edges fill
    (8 outputs per HV513, ``hv513_num`` chips), and ``ADC`` (the reading the handler stores for a
    channel) at the channel's last DAC write, the exchange that reads it.  Walked only while a sink is
    attached."""
    tr = trace_scan(cfg, "v2", conv)
    starts = tr.channel_start_us + [tr.clear_start_us]
    last_dac: dict[int, int] = {}
    rows: list[tuple[int, int, int]] = []
    mask = (1 << (OUTPUTS_PER_HV513 * cfg.hv513_num)) - 1
    bits, din, clk, ch = 0, 0, 0, -1
    for t_us, kind, pin, value in tr.events:
        t_ns = round(t_us * 1000)
        while ch + 1 < len(starts) and t_us >= starts[ch + 1]:
            ch += 1
        if kind == "DAC":
            rows.append((t_ns, int(Signal.DAC), int(value)))
            if 0 <= ch < cfg.electrode_num:
                last_dac[ch] = len(rows)
            continue
        sig = _TRACED_PINS.get(pin)
        if sig is None:
            continue
        rows.append((t_ns, int(sig), int(value)))
        if sig is Signal.DIN:
            din = value
        elif sig is Signal.CLK:
            if value and not clk:
                bits = ((bits << 1) | din) & mask
            clk = value
        elif sig is Signal.LE and value:
            rows.append((t_ns, int(Signal.SEL), (bits & -bits).bit_length() - 1))
    for c, k in sorted(last_dac.items(), key=lambda kv: -kv[1]):
        if c < len(tr.voltage):
            rows.insert(k, (rows[k - 1][0], int(Signal.ADC), int(tr.voltage[c])))
    arr = np.array(rows, dtype=np.int64).reshape(-1, 3)
    return arr[:, 0], arr[:, 1].astype(np.int8), arr[:, 2]


def adc_readings(
    skin: SkinModel, n: int, pulses: tuple[PulseRow, ...], outputs: int, into_exchange_ns: int
) -> tuple[int, ...]:
    """What each of ``n`` channels' ``AD = DAAD(0)`` reads: the skin model's ADC reading of the channel's
    last pulse (biphasic: the second phase), sampled ``into_exchange_ns`` after the DAC change of the
    exchange that ends it, on the channel's own output — none at or past the stack's ``outputs``, where
    the source meets no electrode and reads its compliance.  A channel with no current (height 0) reads
    0.  Stored whole, as v2 stores it (v1.2 keeps ``raw >> 2``)."""
    last: dict[int, PulseRow] = {row[0]: row for row in pulses}  # rows are in time order
    readings = [0] * n
    for ch, (_, _, code, width_ns, _) in last.items():
        if ch < n:
            on = (ch,) if ch < outputs else ()
            readings[ch] = skin.pulse(on, code, max(0.0, (width_ns + into_exchange_ns) / 1000.0)).adc_raw
    return tuple(readings)


def _with_readings(
    events: tuple[np.ndarray, np.ndarray, np.ndarray], volts: tuple[int, ...]
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A scan's trace events with the ``ADC`` rows (one per channel, in channel order) holding the
    readings stored, when they come from the skin model rather than the walker's loop-back."""
    times, signals, values = events
    at = np.flatnonzero(signals == int(Signal.ADC))
    values = values.copy()
    values[at] = np.asarray(volts[: at.size], dtype=values.dtype)
    return times, signals, values


#: (duration ns, onsets, codes, voltages, pulses) of one scan.
ScanShape = tuple[int, tuple[int, ...], tuple[int, ...], tuple[int, ...], tuple[PulseRow, ...]]


def _scan_shape(cfg: FirmwareScanConfig, conv: ScanConventions) -> ScanShape:
    """:func:`_shape` without walking the statements again for every new pattern.

    On v2 a channel's timing does not depend on its height (a height of 0 is still a DAC write of 0 for
    the pulse width), so the walk of a pattern of ones gives every edge; the heights only fill in the DAC
    codes (the ADC reading is the code held when the second exchange starts: the height again), and a
    height of 0 delivers no pulse.  Mode 2 ignores the pattern.  Equal to :func:`_shape` for every
    pattern (tested).  The walk is keyed only by what the handler reads in the scan's mode (modes 0 and 1:
    not the sense pulse; mode 2: not the pulse width; never the rate), so scans
    that differ elsewhere share it."""
    n = cfg.electrode_num
    if cfg.stim_mode not in (0, 1):
        walked = replace(cfg, stim_pattern=(0,) * n, pulse_width=0, frequency_hz=None)
        return _shape(walked, conv)
    heights = cfg.stim_pattern
    walked = replace(
        cfg,
        stim_pattern=(1,) * n,
        sense_pulse_height=0,
        sense_pulse_width=0,
        frequency_hz=None,
    )
    duration, onsets, _, _, rows = _shape(walked, conv)
    pulses = tuple((ch, t0, heights[ch], w, pol) for ch, t0, _, w, pol in rows if heights[ch])
    return duration, onsets, tuple(heights), tuple(heights), pulses


@dataclass(frozen=True)
class CommandRecordV2:
    """A command the v2 parser applied: when, which, where in the host's stream, and whether the host
    wrote that command there (``in_sync``; False for a payload that swallowed a command byte, a command
    byte read out of a payload, bytes of no known host offset)."""

    time_us: float
    opcode: int
    host_offset: int
    in_sync: bool


class ReportsV2(RowPulseTable):
    """The v2 model's delivered pulses in the columns of the v1.2 reports (``pulse_table``): every non-zero
    pulse (``cycle, channel, kind, start_us, width_us, code, pol``, then ``current_ua, charge_nc``).
    ``kind`` is v1.2's :class:`~.scan.PulseKind`: mode 0 monophasic, mode 1 the phase by its POL level,
    mode 2 sense."""

    row_columns = ("cycle", "channel", "kind", "start_us", "width_us", "code", "pol")
    _owner: TimedEmulatorV2

    def _rows(self, t0_us: float | None, t1_us: float | None) -> list[tuple[float, ...]]:
        lo = None if t0_us is None else round(t0_us * 1000)
        hi = None if t1_us is None else round(t1_us * 1000)
        rows: list[tuple[float, ...]] = []
        for s in self._owner.scans:
            for ch, onset, code, width, pol in s.pulses:
                t = s.start_ns + onset
                if (lo is not None and t < lo) or (hi is not None and t >= hi):
                    continue
                kind = pulse_kind_of(s.stim_mode, pol)
                rows.append((s.index, ch, int(kind), t / 1000.0, width / 1000.0, code, pol))
        return rows


class _HostStream:
    """The host's bytes read with the v2 table as they are written: where each command starts (host
    offset → opcode), so a command the parser applies can be told in step or not.  The host's electrode
    count is the last 0xFC it wrote (its pattern length)."""

    def __init__(self) -> None:
        self.starts: dict[int, int] = {}
        self._need = 0  # payload bytes of the host's current command still to come
        self._op = 0
        self._payload = bytearray()
        self._num = 0

    def feed(self, data: bytes, offset: int) -> None:
        i, n = 0, len(data)
        while i < n:
            if self._need:
                take = min(self._need, n - i)
                if self._op == OpcodeV2.ELECTRODE_NUM:
                    self._payload += data[i : i + take]
                self._need -= take
                i += take
                if not self._need and self._op == OpcodeV2.ELECTRODE_NUM:
                    self._num = int.from_bytes(self._payload, "little")
                continue
            op = data[i]
            size = V2.size_of(op, self._num)
            if size is not None:
                self.starts[offset + i] = op
                self._op, self._need = op, size
                self._payload = bytearray()
            i += 1

    def forget_before(self, offset: int) -> None:
        if len(self.starts) > 65536:
            self.starts = {k: v for k, v in self.starts.items() if k >= offset}


class _QueueView:
    """The receive path as a real-time server sees it: bytes waiting (``len``) and room (``free``)."""

    def __init__(self, owner: TimedEmulatorV2) -> None:
        self._owner = owner

    def __len__(self) -> int:
        return self._owner.queued_bytes()

    @property
    def free(self) -> int:
        return int(self._owner.emulator.parser.spec.rx_queue_bytes) - len(self)


class DeliveredV2:
    """What the v2 model's scans delivered, per pulse (a mixin of :class:`TimedEmulatorV2`, which keeps
    ``scans``)."""

    scans: Any

    def delivered(
        self, transfer: CurrentTransfer = DEFAULT_TRANSFER, since_us: float = 0.0
    ) -> list[dict[str, Any]]:
        """Every pulse the scans delivered from ``since_us`` on: time, channel, DAC code, current, width,
        charge, polarity (anodic / cathodic)."""
        out: list[dict[str, Any]] = []
        since = round(since_us * 1000)
        for s in self.scans:
            if s.start_ns < since:
                continue
            for ch, onset, code, width, pol in s.pulses:
                ua = transfer.to_ua(code)
                out.append(
                    {
                        "scan": s.index,
                        "t_us": (s.start_ns + onset) / 1000,
                        "channel": ch,
                        "code": code,
                        "current_ua": ua,
                        "width_us": width / 1000,
                        "charge_nc": ua * width / 1e6,
                        "polarity": "anodic" if pol else "cathodic",
                    }
                )
        return out

    def peak_current_ua(
        self, transfer: CurrentTransfer = DEFAULT_TRANSFER, since_us: float = 0.0
    ) -> dict[int, float]:
        """The highest current each channel received (channels that received none are absent)."""
        peak: dict[int, float] = {}
        for row in self.delivered(transfer, since_us):
            peak[row["channel"]] = max(peak.get(row["channel"], 0.0), row["current_ua"])
        return peak


class _ReadClock:
    """Which read points of one main-loop call the loop gets past (``reach`` of :meth:`ParserV2.call`).

    The scan due at ``alarm`` takes the processor inside the read point whose work the alarm falls in, or
    at the first point that starts at or after it, before that point stores anything (the firmware stores
    a value after its read returns; the host build's shim runs a due interrupt at its alarm inside a
    ``Serial`` call, as the chip does).  If that scan, of the registers as the call has left them there,
    overruns (``overruns``), the loop never gets the processor back: the call stops at that point, and a
    read the alarm came in has taken its bytes from the queue (``taken``) without storing them.  Each
    point costs what :meth:`TimedEmulatorV2._main_call` counts for it: ``call_ns`` a queue check,
    ``byte_ns`` a byte read, nothing for a timer read or a write.  ``asked``: whether the alarm came
    inside the call's read points.  ``starts``: when each byte read leaves the firmware's queue (a
    read's bytes at its start: a u16's two together), before any scan inside the call moves them
    (``_NEVER``: no alarm inside the call)."""

    def __init__(self, t: int, alarm: int, model: TimingModel, overruns: Callable[[], bool]) -> None:
        self.clock_ns = t
        self.alarm_ns = alarm
        self.call_ns = model.call_ns
        self.byte_ns = model.byte_ns
        self.overruns = overruns
        self.asked = False
        self.taken = 0
        self.starts: list[int] = []

    def __call__(self, point: ReadPoint, nbytes: int) -> bool:
        cost = 0
        if point is ReadPoint.AVAILABLE:
            cost = self.call_ns
        elif point is ReadPoint.READ:
            cost = nbytes * self.byte_ns
        if not self.asked and (self.alarm_ns <= self.clock_ns or self.alarm_ns < self.clock_ns + cost):
            self.asked = True
            if self.overruns():
                if point is ReadPoint.READ and self.clock_ns < self.alarm_ns:
                    self.taken = nbytes
                return False
        if point is ReadPoint.READ:
            self.starts.extend(repeat(self.clock_ns, nbytes))
        self.clock_ns += cost
        return True


class MainLoopRunsV2:
    """What the v2 model does many times over, done in one go exactly as one at a time (a mixin of
    :class:`TimedEmulatorV2`, which keeps the state): the idle polls, the calls that each skip one unknown
    byte, the arrivals that land meanwhile, the scan the registers give (kept for the next alarm), and a
    call that goes on from the last one's second queue check."""

    model: TimingModel
    conventions: ScanConventions
    skin: SkinModel | None
    outputs: int
    _last_scan_key: tuple[Any, ...] | None
    _last_scan: tuple[FirmwareScanConfig, ScanShape]
    _delivery_heap: list[tuple[int, int, Scheduled]]
    _booting_until: int
    _segments: list[tuple[int, int, int]]
    _frozen: bool
    _voltages_held: bool
    _chain_pos: int  # hv513FastScan's static position, where the last scan's hv513Clear left it
    applied: list[tuple[int, int, object]]
    _hv513_in_call: bool
    _call_time_ns: int
    _applied_in_call: int | None
    _reply_offset: int | None
    _next_call_ns: int
    _second_check_ns: int | None
    scans: list[ScanRecordV2]

    @property
    def parser(self) -> ParserV2:
        raise NotImplementedError

    def _loss(self, t: int, count: int, host_offset: int, reason: str) -> None:
        raise NotImplementedError

    def _call_start(self, t: int) -> int:
        """Where the call due at ``t`` starts: at the last call's second queue check when bytes arrived by
        it (the model ran that call with the bytes landed at its start; they were written later, or in
        flight then): that check counts them, and the call goes on reading them -- the same check and
        read as a call from there (:meth:`_note_second_check`)."""
        cont, self._second_check_ns = self._second_check_ns, None
        heap = self._delivery_heap
        if cont is not None and t == cont + self.model.call_ns and heap and heap[0][0] <= cont:
            return cont
        return t

    def _note_second_check(self, consumed: int, alarm: int, end: int) -> None:
        """A call that read a command byte and found its payload short ends with that second check (at
        ``end`` less a check's cost): remembered for :meth:`_call_start`, unless a scan (the alarm due at
        the call's start) took the processor inside it, after the check had counted."""
        second = end - self.model.call_ns
        parser = self.parser
        if (
            parser.processing
            and consumed == 1
            and parser.checks == 2
            and (alarm >= end or self.scans[-1].start_ns + self.scans[-1].duration_ns <= second)
        ):
            self._second_check_ns = second

    def _tick_after(self, t: int) -> int:
        raise NotImplementedError

    def _idle_polls(self, t: int, alarm: int, target: int) -> bool:
        """Run the idle polls from ``t`` on in one go, exactly as :meth:`_main_call` would one by one:
        with nothing queued, no command pending and no reply, a call changes nothing and the task sleeps
        to the next RTOS tick -- so the polls fall on the ticks, up to the last one before the alarm,
        ``target`` or the next arrival (a poll from then on lands it: the full path).  False (nothing
        done) when the call at ``t`` is not an idle poll."""
        parser = self.parser
        if parser.pending or parser.processing or self._hv513_in_call or parser.tx or self._frozen:
            return False
        heap = self._delivery_heap
        # the latest poll run here: over by the alarm (one the alarm falls into is _main_call's), by
        # ``target`` and before the next arrival
        last = min(alarm - self.model.call_ns, target, heap[0][0] - 1 if heap else target)
        if t > last:
            return False  # a delivery lands at this call
        call_ns = self.model.call_ns
        nxt = self._tick_after(t + call_ns)
        if nxt <= last:  # the next polls fall a whole number of ticks apart, from a tick
            stride = self._tick_after(nxt + call_ns) - nxt
            t = nxt + (last - nxt) // stride * stride
            nxt = self._tick_after(t + call_ns)
        self._call_time_ns = t
        self._applied_in_call = None
        self._reply_offset = None
        self._next_call_ns = nxt
        return True

    def _skip_unknown(self, t: int, alarm: int, target: int) -> bool:
        """Run the calls that each read one unknown byte and skip it (the zeros of a flush: most calls of
        a session) in chunks, exactly as :meth:`_main_call` would one by one: each such call lands what
        has arrived by its start, reads one byte and returns at once (no sleep), so the next call starts
        ``call_ns + byte_ns`` later, if it is over by the alarm and starts by ``target``.  A chunk ends
        where a delivery lands (at the next call's start, as :meth:`_land` would) or the run of unknown
        bytes ends.  False (nothing done) when the call at ``t`` is not such a call."""
        parser = self.parser
        if parser.processing or self._hv513_in_call or parser.tx or self._frozen:
            return False
        m = self.model
        step = m.call_ns + m.byte_ns
        # the latest start of a call that runs now: by ``target``, and over by the alarm (one the alarm
        # falls into is :meth:`_main_call`'s: a scan that starves the loop may cut it before its read)
        limit = min(alarm - step, target)
        if t > limit:
            return False
        self._land(t)
        heap = self._delivery_heap
        calls = 0
        run = 0
        while True:
            if run == 0:
                run = parser.unknown_run()
                if run == 0:
                    break
            count = min(run, (limit - t) // step + 1)
            if heap and heap[0][0] <= t + (count - 1) * step and not self._lands_alike(t, count, step):
                # the calls before the next arrival (it lands at the start of the first call after it)
                count = -(-(heap[0][0] - t) // step)
            parser.skip_unknown(count)
            run -= count
            calls += count
            t += count * step
            self._read_starts = [t - step + m.call_ns]  # the chunk's last call's byte (see _taken_unread)
            self._land(t - step)  # what arrived during the chunk (nothing unless _lands_alike said so)
            if t > limit:
                break
            self._land(t)
        if calls == 0:
            return False
        self._call_time_ns = t - step
        self._applied_in_call = None
        self._reply_offset = None
        self._next_call_ns = t
        return True

    def _land(self, t: int) -> None:
        """Arrivals up to ``t`` into the receive queue (lost while the board boots or the queue is full)."""
        parser = self.parser
        heap = self._delivery_heap
        while heap and heap[0][0] <= t:
            _, seq, item = heap[0]
            if isinstance(item, ByteBurst):
                d = self._land_burst(item, seq, t)
                if len(item):
                    heapq.heapreplace(heap, (item.t_ns, seq, item))
                else:
                    heapq.heappop(heap)
                if d is None:
                    continue
            else:
                heapq.heappop(heap)
                d = item
            if d.t_ns < self._booting_until:  # bytes that came while the board booted are lost
                self._loss(d.t_ns, len(d.data), d.host_offset, "rebooting")
                continue
            start = parser.offset + parser.pending
            lost = parser.receive(d.data, self._taken_unread(d.t_ns))
            if d.host_offset >= 0 and len(d.data) > lost:
                self._segments.append((start, d.host_offset, len(d.data) - lost))
            if lost:
                host = d.host_offset + len(d.data) - lost if d.host_offset >= 0 else -1
                self._loss(d.t_ns, lost, host, "queue_full")

    def _taken_unread(self, t: int) -> int:
        """Bytes the last parser call took from the queue whose read starts at ``t`` or later
        (``_read_starts``): runEtactileKit() reads one byte (a u16's two, a pattern element) at a time,
        so a byte arriving meanwhile finds those still in the firmware's queue, and may not fit; and
        ``rx_pending`` shows them until they are read.  (The host build moves an arrival into the queue
        at the firmware's next call into the platform: before a read that starts at or after it.)"""
        return unread_after(self._read_starts, t)

    def _lands_alike(self, t: int, count: int, step: int) -> bool:
        """Whether the bytes arriving during ``count`` calls from ``t`` (each reading one byte already
        queued) may land after the last of them instead of at each call's start: nothing they do depends
        on when -- no reboot under way, room for all of them even if none were read, and no arrival in
        that time forgets the bytes read (:meth:`~.contract.ByteQueue.keeps_read_bytes`)."""
        parser = self.parser
        if t < self._booting_until or not parser.keeps_read_bytes(count):
            return False
        last = t + (count - 1) * step
        arriving = 0
        for t0, _, item in self._delivery_heap:
            if t0 <= last:
                arriving += (
                    item.end_before(last) - item.pos if isinstance(item, ByteBurst) else len(item.data)
                )
        return parser.pending + arriving <= parser.spec.rx_queue_bytes

    def _land_burst(self, b: ByteBurst, seq: int, t: int) -> Delivery | None:
        """The bytes of a burst that have arrived by ``t`` (before any other delivery's) join the queue at
        once when nothing sets one apart -- no reboot under way, room for all of them: no main-loop call
        runs between their arrivals, so the queue holds what it would after taking them one by one.
        Otherwise the next byte alone, as a delivery for :meth:`_land` (None: the bytes were taken)."""
        parser = self.parser
        j = b.end_before(t, next_key(self._delivery_heap), seq)
        room = parser.spec.rx_queue_bytes - parser.pending - self._taken_unread(b.t_ns)
        if b.t_ns < self._booting_until or j - b.pos > room:
            return b.pop()
        start = parser.offset + parser.pending
        hosts = b.host_offsets(j)
        lost = parser.receive(b.take(j))
        assert lost == 0  # there was room for every byte
        if hosts is not None:
            self._segments.extend(zip(range(start, start + len(hosts)), hosts, repeat(1)))
        return None

    def _scan_of(self, regs: RegistersV2) -> tuple[FirmwareScanConfig, ScanShape]:
        """The scan the registers give (:func:`_scan_shape`), kept for the next alarm: most scans run
        the same registers as the one before."""
        n = regs.electrode_num
        pattern = tuple(regs.stim_pattern[:n])
        # hv513FastScan keeps its chain position in a static: channel 0 resets it, so only a scan of no
        # channel depends on it -- its hv513Clear clocks from where the previous scan's clear left it
        # (nothing at all after the first such scan since boot)
        prior = 1 if n == 0 and self._chain_pos else 0
        # the config's leading fields, in its field order: the cache key is built of the very values the
        # config is, so a register the scan reads cannot be left out of the key
        leading = (
            n,
            pattern,
            regs.pulse_width,
            regs.discharge_time,
            regs.polarity,
            regs.hv513_num,
            regs.sense_pulse_height,
            regs.sense_pulse_width,
        )
        key = (leading, regs.stim_mode, prior, id(self.skin))
        if key != self._last_scan_key:
            cfg = FirmwareScanConfig(*leading, stim_mode=regs.stim_mode, prior_scans=prior)
            shape = _scan_shape(cfg, self.conventions)
            if self.skin is not None:
                duration, onsets, codes, _, pulses = shape
                into_exchange_ns = self.model.adc_at_ns - self.conventions.dac_change_at_ns
                volts = adc_readings(self.skin, n, pulses, self.outputs, into_exchange_ns)
                shape = (duration, onsets, codes, volts, pulses)
            self._last_scan = (cfg, shape)
            self._last_scan_key = key
        return self._last_scan


class InterruptedCallsV2:
    """A scan whose alarm falls inside a v2 main-loop call (a mixin of :class:`TimedEmulatorV2`, which keeps
    the state): what it sees of a command the call is applying, and the loop it starves when it overruns
    -- it takes the processor inside the one of ``runEtactileKit``'s read points its alarm falls in, or at
    the first that starts after it (:class:`_ReadClock`), and never gives it back, so the call is left
    exactly where the firmware leaves it."""

    model: TimingModel
    hazards: list[Hazard]
    scans: list[ScanRecordV2]
    _call_time_ns: int
    _next_alarm_ns: int
    _voltages_held: bool
    _scan_of: Callable[[RegistersV2], tuple[FirmwareScanConfig, ScanShape]]
    _period_ns: Callable[[], int]
    _scan: Callable[[int], None]
    _mark: Callable[[int, str, dict[str, Any]], None]
    stop_reading: Callable[[], None]

    @property
    def parser(self) -> ParserV2:
        raise NotImplementedError

    def _overruns(self) -> bool:
        """Whether a scan of the registers now lasts a period or more: ``Timer1_Stimulate_ISR`` then
        re-enables an alarm the counter has already passed, the next scan starts as it returns, and so on
        -- the main loop never gets the processor back."""
        return self._scan_of(self.parser.regs)[1][0] >= self._period_ns()

    def _starve_at(self, cut: CallCut, alarm: int) -> None:
        """The scan due at ``alarm`` took the processor at the call's read point ``cut`` and overran
        (:meth:`_overruns`): ``runEtactileKit`` never resumes.  What the call read and stored before that
        point stays (a command byte, a pattern's first elements, 0xF6's period without its alarm); the
        rest stays queued and is never read, no reply is written, and 0xFF had set ``SendingVoltages``
        before its write, so no scan stores its readings again.  A pattern cut in its copy is torn for
        good (in modes 0 and 1, where a scan reads it).  The loop stays starved until a reset (the caller
        stops its reading): its registers cannot change, so neither can the scans' length."""
        regs = self.parser.regs
        if cut.op == OpcodeV2.MEASURE:
            self._voltages_held = True
        if cut.torn is not None and regs.stim_mode < _MODE_IMPEDANCE:
            k, rest = cut.torn
            n = regs.electrode_num
            if 0 < k < n and list(rest) != regs.stim_pattern[k:n]:
                self.hazards.append(
                    Hazard(
                        HazardKind.TORN_PATTERN,
                        -1,
                        {"scan": len(self.scans), "new_channels": k, "channels": n, "old_rest": True},
                        alarm / 1000,
                    )
                )
        self._scan(alarm)
        self._mark(self._call_time_ns, "starved", {"op": cut.op, "at": cut.point.value})
        self.stop_reading()

    def _scan_in_idle_call(self, alarm: int, end: int) -> int:
        """The alarm fell inside an idle poll's ``Serial.available()``: the scan takes the processor there,
        and the rest of the check and ``vTaskDelay`` follow it, so the task sleeps from the poll's end a
        scan later (the end returned).  -1 when that scan overruns: the loop never gets the processor
        back."""
        if self._overruns():
            self._scan(alarm)
            self._mark(self._call_time_ns, "starved", {"op": None, "at": "vTaskDelay"})
            self.stop_reading()
            return -1
        while alarm < end:  # each alarm before vTaskDelay's point (a period barely longer than a scan)
            self._scan(alarm)
            end += self.scans[-1].duration_ns
            alarm = self._next_alarm_ns
        return end

    def _preempt(
        self, alarm: int, t: int, consumed: int, op: int, before: dict[str, Any], old: list[int]
    ) -> int:
        """The scan interrupt fires while this call applies a command: the scan sees the registers as
        the copy had left them at that moment (a pattern: the elements copied so far are new, the rest
        old — a torn pattern).  Returns the scan's duration, by which the call finishes later."""
        regs = self.parser.regs
        m = self.model
        after = {f: getattr(regs, f) for f in V2_SCAN_REGISTERS}
        new = list(regs.stim_pattern)
        if op == OpcodeV2.PATTERN:
            n = regs.electrode_num
            width = 2 * m.byte_ns  # one u16 read per element (readInt_16)
            start = t + m.call_ns * self.parser.checks + max(0, consumed - 2 * n) * m.byte_ns
            # the scan takes the processor inside the element read the alarm falls in, or at the next one
            # to start (_ReadClock): the elements whose read ended by the alarm are stored
            k = max(0, min(n, (alarm - start) // width)) if width else n
            regs.stim_pattern[:] = new[:k] + old[k:]
            # in mode 2 the scan gives every channel the sense pulse and discards the height it reads
            # (spec "Stimulation scan", 3c): its pulses are the same whatever the buffer holds, so no scan
            # in mode 2 uses part of an old and part of a new pattern
            reads_pattern = regs.stim_mode < _MODE_IMPEDANCE
            if reads_pattern and 0 < k < n and new[k:n] != old[k:n]:
                self.hazards.append(
                    Hazard(
                        HazardKind.TORN_PATTERN,
                        -1,
                        {
                            "scan": len(self.scans),
                            "new_channels": k,
                            "channels": n,
                            "old_rest": old[k:n] != new[k:n],
                        },
                        alarm / 1000,
                    )
                )
        else:
            for f, v in before.items():
                setattr(regs, f, v)
        self._scan(alarm)
        duration = self.scans[-1].duration_ns
        for f, v in after.items():
            setattr(regs, f, v)
        regs.stim_pattern[:] = new
        return duration

    def _scan_inside(
        self,
        alarm: int,
        t: int,
        consumed: int,
        op: int | None,
        before: dict[str, Any],
        old: list[int],
        held: dict[str, int],
    ) -> int:
        """The scan whose alarm fell inside the call at ``t``: it sees the registers as the firmware has
        them at the alarm (:meth:`_preempt` for a call that applied ``op``; ``held``: registers the call
        stores only after the point where the scan took the processor, at their values before it).
        Returns the scan's duration, by which the call finishes later."""
        regs = self.parser.regs
        after = {f: getattr(regs, f) for f in held}
        for f, v in held.items():
            setattr(regs, f, v)
        try:
            if op is None:  # the registers the call has stored (none, or all it stores before ``held``)
                self._scan(alarm)
                return self.scans[-1].duration_ns
            return self._preempt(alarm, t, consumed, op, before, old)
        finally:
            for f, v in after.items():
                setattr(regs, f, v)

    def _scans_in_call(
        self,
        clock: _ReadClock,
        t: int,
        consumed: int,
        applied: int | None,
        before: dict[str, Any],
        old: list[int],
        held: dict[str, int],
        limit: int,
        tie: bool,
    ) -> int:
        """The scans whose alarms fall inside the call at ``t`` (before ``limit``, or at it with ``tie``),
        each where it takes the processor; returns their time, by which the call's work ends later (its
        reads too: ``_read_starts``)."""
        alarm = clock.alarm_ns
        shift = 0  # the scans' time inside the call so far: the call's work is that much later
        while True:
            duration = self._scan_inside(alarm, t + shift, consumed, applied, before, old, held)
            shift += duration
            # the next alarm may fall inside the call too (a period barely longer than a scan): the scan
            # has the same length (v2's does not depend on the heights), so it does not overrun either;
            # one that did would have been caught where it took the processor (``clock``)
            if self._next_alarm_ns <= alarm + duration:
                raise RuntimeError(
                    f"v2 model: a scan inside the call at {t} ns overran although the call's read "
                    "points found no overrun (the registers a scan sees are inconsistent)"
                )
            alarm = self._next_alarm_ns
            if not (alarm < limit + shift or (tie and alarm == limit + shift)):
                break
        first = clock.alarm_ns  # the reads from the first scan on are that scan (or scans) later
        self._read_starts = [r + shift if r >= first else r for r in clock.starts]
        return shift


class TimedEmulatorV2(DeliveredV2, MainLoopRunsV2, InterruptedCallsV2, TimedModelBase):
    """The v2 board in simulated time.  ``write(data, at_us)`` hands bytes to the link; ``advance_to``
    runs the firmware until then; ``read_tx`` returns what reached the host."""

    firmware: FirmwareSpec = V2

    def __init__(
        self,
        board: str | Board = "compact",
        switching_boards: int = 1,
        *,
        link: str | LinkModel = "usb",
        tx_link: str | LinkModel | None = None,
        model: TimingModel = DEFAULT_MODEL,
        conventions: ScanConventions = DEFAULT_CONVENTIONS,
        stack_reading: float | None = None,
        skin: SkinModel | None = DEFAULT_SKIN,
    ) -> None:
        self.emulator = Emulator(board, switching_boards, firmware=V2, stack_reading=stack_reading)
        #: What the ADC reads at the end of each pulse (``AD = DAAD(0)``, the spec's scan step 3c): the
        #: electrode–skin model v1.2 reads too, stored unshifted as v2 stores it.  ``None``: the DAC code
        #: itself, as the host build's SPI stub loops the exchange back (what its golden traces record).
        self.skin = skin
        self.board = self.emulator.board
        #: HV513 outputs the stack really has: a channel at or past this is clocked out of the chain's end.
        self.outputs = physical_outputs(self.board.kind, self.board.switching_boards)
        self.model = model
        self.conventions = conventions
        self.link = make_link(link)
        self.tx_link = make_link(tx_link) if tx_link is not None else None
        self.now_ns = 0
        self.hazards: list[Hazard] = self.emulator.hazards
        self.scans: list[ScanRecordV2] = []
        self.scan_count = 0  # scans since power-up (``scans`` may have been trimmed)
        # (time ns, opcode, value) when a command took effect
        self.applied: list[tuple[int, int, object]] = []
        self._sinks: list[Any] = []  # trace sinks (:meth:`attach`)
        self.queue = _QueueView(self)
        self.reboots = 0
        #: Bytes written to the board since power-on (0: no program can have left a command in its parser).
        self.received_bytes = 0
        self.replies_dropped = 0  # reply bytes to commands of a host that had gone (see new_client)
        self._reply_offset: int | None = None
        self._delivery_heap: list[tuple[int, int, Scheduled]] = []
        self._seq = 0
        # replies on their way to the host, in the order written: (arrival ns, bytes) or a burst
        self._tx: list[tuple[int, bytes | ByteBurst]] = []
        self._host_rx = bytearray()
        self._host_offset = 0
        self._clients: list[tuple[int, str]] = []  # (device offset where a client's bytes start, its name)
        self.losses: list[LossReport] = []
        self.commands: list[CommandRecordV2] = []
        self.reports = ReportsV2(self)
        self._host_stream = _HostStream()
        # (device offset, host offset, length) of each arrival taken into the queue since power-on
        self._segments: list[tuple[int, int, int]] = []
        self._last_scan_key: tuple[Any, ...] | None = None  # the registers of the last scan, and its shape
        self._boot(0)

    def _boot(self, t: int, boot_delay: bool = False) -> None:
        start = t + (self.model.boot_ns if boot_delay else 0)
        self._booting_until = start
        self._next_call_ns = start
        self._second_check_ns = None
        # as v1.2's model: the stimulation timer starts ``timer_start_us`` after boot (the firmware's
        # setup() runs first), the RTOS ticks from boot at ``tick_phase_us``
        reload = start + self.model.timer_start_ns
        self._tick_base = start + self.model.tick_phase_ns
        self._next_alarm_ns = reload + self._period_ns()
        self._busy_until_ns = 0
        self._last_sense_hazard = False
        self._last_beyond_hazard = False
        self._chain_pos = 0
        self._call_time_ns = start
        self._read_starts: list[int] = []
        self._last_alarm = reload
        self._hv513_in_call = False
        self._applied_in_call: int | None = None
        self._frozen = False
        self._voltages_held = False
        self._segments = []
        self.emulator.parser.on_command = self._on_command

    # --- the host side ---------------------------------------------------------------------------------

    @property
    def registers(self) -> RegistersV2:
        return entry_part(self.emulator.registers, RegistersV2)

    @property
    def parser(self) -> ParserV2:
        return entry_part(self.emulator.parser, ParserV2)

    def scan_rate(self, at_us: float) -> tuple[int, float]:
        """Scans since power-up and the current scan rate in Hz (0 when the scans stopped)."""
        s = self.scans
        if len(s) >= 2:
            stride = s[-1].start_ns - s[-2].start_ns
            if stride > 0 and s[-1].start_ns >= at_us * 1000 - 2 * stride:
                return self.scan_count, 1e9 / stride
        return self.scan_count, 0.0

    def current_pulse_starts_us(self, since_us: float, now_us: float) -> list[float]:
        """The start times of the delivered pulses that carried current between the two times."""
        rows = self.delivered(since_us=since_us)
        return [row["t_us"] for row in rows if row["current_ua"] > 0 and row["t_us"] <= now_us]

    @classmethod
    def _served_options(cls, options: dict[str, Any]) -> dict[str, Any]:
        """The ADC reads the same skin model as on v1.2 (``skin``: default :data:`~.skin.DEFAULT_SKIN`);
        without ``tx_link`` replies travel back over the same kind of link as the host's bytes (as on
        v1.2)."""
        tx_link, model, skin = options["tx_link"], options["model"], options["skin"]
        return {
            "link": options["link"],
            "tx_link": tx_link if tx_link is not None else reply_link(options["link"]),
            "model": model if model is not None else DEFAULT_MODEL,
            "skin": skin if skin is not None else DEFAULT_SKIN,
        }

    def write(self, data: bytes, at_us: float | None = None) -> int:
        self.received_bytes += len(data)
        t = self.now_ns if at_us is None else round(at_us * 1000)
        if t < self.now_ns:
            raise ConfigurationError(f"at_us={at_us} is before the emulator's clock ({self.now_us} us)")
        self.advance_to(t / 1000)
        self._host_stream.feed(bytes(data), self._host_offset)
        for d in self.link.schedule_bursts(bytes(data), t, self._host_offset):
            heapq.heappush(self._delivery_heap, (d.t_ns, self._seq, d))
            self._seq += 1
        self._host_offset += len(data)
        return len(data)

    @property
    def host_offset(self) -> int:
        """Bytes the host has written so far (the offset its next byte will have)."""
        return self._host_offset

    def _host_replies(self) -> bytearray:
        return self._host_rx

    def _deliveries(self) -> list[tuple[int, int, Scheduled]]:
        return self._delivery_heap

    def _idle(self) -> bool:
        p = self.parser
        return not self._delivery_heap and (p.pending == 0 or (p.processing and p.pending < p.required))

    def _rx_pending(self) -> int:
        return self.parser.pending

    def queued_bytes(self) -> int:
        """The bytes in the firmware's receive queue now: those the parser call under way has taken but
        the firmware has not read yet included (see _taken_unread)."""
        return self.parser.pending + self._taken_unread(self.now_ns)

    def state(self) -> BoardState:
        """The firmware's registers, and the bytes waiting in the receive queue (:meth:`queued_bytes`)."""
        st = super().state()
        unread = self._taken_unread(self.now_ns)
        return replace(st, rx_pending=st.rx_pending + unread) if unread else st

    def _collect_tx(self) -> None:
        now = self.now_ns
        if self._tx and self._tx[0][0] <= now:
            keep: list[tuple[int, bytes | ByteBurst]] = []
            for t, b in self._tx:
                if isinstance(b, ByteBurst):  # its bytes that have arrived; the rest stays on its way
                    self._host_rx += b.take(b.end_before(now))
                    if len(b):
                        keep.append((b.t_ns, b))
                elif t <= now:
                    self._host_rx += b
                else:
                    keep.append((t, b))
            self._tx = keep

    # --- what a real-time server needs ---------------------------------------------------------------

    def next_event_us(self, scans: bool = True) -> float:
        """When the board next does something the host could notice: a delivery lands, the parser has
        bytes to read, a cut command's 2 s run out, a reply reaches the host, and with ``scans`` an alarm
        fires.  Idle polls (one per tick, changing nothing) are not events: a runner on the wall clock
        sleeps through them and the model runs them when it catches up."""
        inf = float("inf")
        p = self.parser
        # bytes that landed are read by the parser's next call, not before
        t = min(
            max(self._delivery_heap[0][0], self._next_call_ns) if self._delivery_heap else inf,
            self._tx[0][0] if self._tx else inf,
            self._next_alarm_ns if scans else inf,
        )
        if p.processing:
            if p.pending >= p.required:
                t = min(t, self._next_call_ns)
            else:  # the first poll after the timeout discards it
                t = min(t, max(self._next_call_ns, (p.command_start_us + self._timeout_us() + 1) * 1000))
        elif p.pending:
            t = min(t, self._next_call_ns)
        return t / 1000

    def _timeout_us(self) -> int:
        return self.parser.timeout_us

    def parser_status(self) -> str:
        """What the parser is doing, in words."""
        p = self.parser
        if not p.processing:
            return "between commands"
        name = p.spec.command(p.command).name
        return (
            f"reading {name} payload {min(p.pending, p.required)}/{p.required} (discarded if not complete "
            f"at t={(p.command_start_us + self._timeout_us()) / 1e6:.3f} s)"
        )

    def reset(self, reason: str = "reset") -> None:
        """Power-cycle the board now (registers, queue, parser to power-on; replies and bytes in flight
        are lost); it boots for the timing model's boot time."""
        self.reboots += 1
        self.received_bytes = 0  # power-on: no command can be pending
        p = self.parser
        if p.pending:
            self._loss(self.now_ns, p.pending, self._host_of(p.offset), "reboot")
        in_flight = [
            (d.t_ns, seq, d) for _, seq, item in self._delivery_heap for d in expanded(item)
        ]  # each byte of a burst a delivery of its own, in arrival order
        for _, _, d in sorted(in_flight):
            self._loss(self.now_ns, len(d.data), d.host_offset, "reboot")
        self._delivery_heap.clear()
        self._tx.clear()
        self._host_rx.clear()
        self.emulator.reset()
        self._clients.clear()
        self._boot(self.now_ns, boot_delay=True)
        self._mark(self.now_ns, "reset", {"reason": reason})

    def stop_reading(self) -> None:
        """The main loop hangs: nothing is read any more until a reset, while arrivals keep filling the
        receive queue (the USB stack's interrupt stores them; the rest is lost) and the scans go on."""
        self._frozen = True
        self._next_call_ns = _NEVER

    def _loss(self, t: int, count: int, host_offset: int, reason: str) -> None:
        p = self.parser
        self.losses.append(
            LossReport(t / 1000, host_offset, count, b"", reason, p.pending, self.parser_status())
        )
        self._mark(t, "loss", {"bytes": count, "host_offset": host_offset, "reason": reason})

    def _host_of(self, dev_offset: int) -> int:
        """The host offset of a byte the queue took (-1: unknown, e.g. after a byte fault changed a chunk's
        length)."""
        k = bisect_right(self._segments, (dev_offset, float("inf"), 0)) - 1
        if k < 0:
            return -1
        dev, host, length = self._segments[k]
        return host + dev_offset - dev if dev_offset < dev + length else -1

    def new_client(self, name: str) -> None:
        """A new host connection starts here: its bytes follow the ones already taken.  Nothing in the
        firmware resets the parser on a new connection, so a command the previous host cut takes the new
        host's first bytes as its payload if they complete it within 2 s of its command byte — an
        :data:`~.hazards.HazardKind.INHERITED_COMMAND` hazard naming both hosts' bytes.

        The firmware reads and writes through the one current connection.  Here the bytes the previous
        host got into the receive path before it went are still read (in order, before the new host's:
        the emulator's reading of a connection that closes with bytes unread), but replies to its
        requests are dropped (counted in :attr:`replies_dropped`): that host is gone, and the new one gets
        answers only to what it asked."""
        p = self.parser
        self._clients.append((p.offset + p.pending + self.in_flight, name))
        del self._clients[:-2]

    def attach(self, sink: Any) -> None:
        """Send every scan and marker (command applied, bytes lost, reset) from now on to ``sink`` (see
        :mod:`~tactdeform_hw.emulator.records.trace`), as the v1.2 model does."""
        self._sinks.append(sink)
        if hasattr(sink, "begin"):
            sink.begin(self.now_ns)

    def detach(self, sink: Any) -> None:
        if sink in self._sinks:
            self._sinks.remove(sink)

    def _mark(self, t: int, kind: str, detail: dict[str, Any]) -> None:
        for s in self._sinks:
            s.marker(t, kind, detail)

    def discard_history(self, before_us: float) -> None:
        """Forget scans, applied-command, command and loss records older than ``before_us`` (a board
        served for hours keeps a bounded memory)."""
        t = round(before_us * 1000)
        self.scans = [s for s in self.scans if s.end_ns >= t]
        self.applied = [a for a in self.applied if a[0] >= t]
        self.commands = [c for c in self.commands if c.time_us * 1000 >= t]
        self.losses = [lo for lo in self.losses if lo.time_us * 1000 >= t]
        if self._segments:
            keep = self.parser.offset
            self._segments = [sg for sg in self._segments[:-1] if sg[0] + sg[2] > keep] + self._segments[-1:]

    def advance_to(self, t_us: float) -> None:
        target = round(t_us * 1000)
        if target < self.now_ns:
            return
        self._run(target)
        self.now_ns = target

    # --- the firmware ----------------------------------------------------------------------------------

    def _period_ns(self) -> int:
        return int(self.registers.timer_alarm_ticks) * self.conventions.timer_tick_ns

    def _run(self, target: int) -> None:
        while True:
            call, alarm = self._next_call_ns, self._next_alarm_ns
            if self._frozen:
                self._land(min(alarm, target))
            # the serial driver queues arrivals whatever the loop does: before a scan that comes first (a
            # loop starved by back-to-back scans still overflows); nothing reads them before the call anyway
            if min(call, alarm) > target:
                if alarm <= call:
                    self._land(target)
                return
            if alarm <= call:
                self._land(alarm)
                self._scan(alarm)
            elif not self._idle_polls(call, alarm, target) and not self._skip_unknown(call, alarm, target):
                self._main_call(call)

    def _scan(self, t: int) -> None:
        regs = self.registers
        n = regs.electrode_num
        cfg, (duration, onsets, codes, volts, pulses) = self._scan_of(regs)
        pulses = self._on_outputs(pulses, t)
        rec = ScanRecordV2(
            self.scan_count,
            t,
            duration,
            n,
            regs.stim_mode,
            regs.polarity,
            regs.pulse_width,
            regs.sense_pulse_height,
            regs.sense_pulse_width,
            tuple(cfg.stim_pattern),
            onsets,
            codes,
            pulses,
        )
        self.scans.append(rec)
        self.scan_count += 1
        if self._sinks:
            events = _trace_events(cfg, self.conventions)
            run = EventRun(t, duration, events if self.skin is None else _with_readings(events, volts))
            for sink in self._sinks:
                sink.scan_run(run)
        self._last_alarm = t
        self._chain_pos = OUTPUTS_PER_HV513 * regs.hv513_num  # where the scan's hv513Clear left it
        if not self._voltages_held:
            regs.voltage[:n] = list(volts)
        end = t + duration
        self._check_sense(rec)
        period = self._period_ns()
        if duration > period:
            self.hazards.append(
                Hazard(
                    HazardKind.OVERRUN, -1, {"scan_us": duration / 1000, "period_us": period / 1000}, t / 1000
                )
            )
            self._next_alarm_ns = end
        else:
            self._next_alarm_ns = t + period
        if self._next_call_ns < end:
            self._next_call_ns = end  # the interrupt pre-empts the main loop

    def _on_outputs(self, pulses: tuple[PulseRow, ...], t: int) -> tuple[PulseRow, ...]:
        """The pulses an output delivers: hv513FastScan clocks a channel's bit ``channel`` places down the
        chain, so past the stack's last output it falls off the end and no electrode gets that current
        (as v1.2's physical chain).  A firmware that believes in more chips than the stack has (a miscounted
        0xF5) drives such channels without the parser's :data:`~.hazards.HazardKind.CHANNELS_BEYOND_HV513`
        (raised only past its own count): the scan records it then, once per stretch of such scans."""
        limit = self.outputs
        kept = tuple(row for row in pulses if row[0] < limit)
        beyond = len(kept) < len(pulses)
        if beyond and not self._last_beyond_hazard and self.registers.hv513_num * OUTPUTS_PER_HV513 > limit:
            self.hazards.append(
                Hazard(
                    HazardKind.CHANNELS_BEYOND_HV513,
                    -1,
                    {
                        "electrode_num": self.registers.electrode_num,
                        "hv513_num": self.registers.hv513_num,
                        "channels_driven": limit,
                    },
                    t / 1000,
                )
            )
        self._last_beyond_hazard = beyond
        return kept

    def _check_sense(self, rec: ScanRecordV2) -> None:
        live_zero = rec.stim_mode == 2 and rec.sense_pulse_height > 0 and any(h == 0 for h in rec.heights)
        if live_zero and not self._last_sense_hazard:
            self.hazards.append(
                Hazard(
                    HazardKind.MODE_SENSE_ALL,
                    -1,
                    {
                        "scan": rec.index,
                        "channels": [ch for ch, h in enumerate(rec.heights) if h == 0],
                        "sense_code": rec.sense_pulse_height,
                        "sense_width_us": rec.sense_pulse_width,
                    },
                    rec.start_ns / 1000,
                )
            )
        self._last_sense_hazard = live_zero

    def _main_call(self, t: int) -> None:
        parser = self.parser
        regs = self.registers
        t = self._call_start(t)
        self._land(t)
        m = self.model
        self._call_time_ns = t
        self._applied_in_call = None
        self._reply_offset = None
        pending = parser.pending
        if pending == 0 and not parser.processing and not self._hv513_in_call and not parser.tx:
            self._idle_call(t)
            return
        hazards_before = len(self.hazards)
        # the registers before the call matter only to a scan that can interrupt it: one whose alarm falls
        # before the call's latest possible end (it cannot read more than the bytes waiting)
        latest_end = t + 2 * m.call_ns + pending * m.byte_ns + m.hv513_detect_ns
        before: dict[str, Any] = {}
        old_pattern: list[int] = []
        old_ticks, old_hv513 = regs.timer_alarm_ticks, regs.hv513_num
        alarm = self._next_alarm_ns  # armed when the call starts (0xF6 re-arms it only at the call's end)
        inside = t < alarm < latest_end
        clock = _ReadClock(t, alarm if inside else _NEVER, m, self._overruns)
        if inside:
            before = {f: getattr(regs, f) for f in V2_SCAN_REGISTERS}
            old_pattern = list(regs.stim_pattern)
        out = parser.call(t // 1000, clock)
        self._read_starts = clock.starts
        if parser.cut is not None:
            parser.drop_unstored(clock.taken)
            self._starve_at(parser.cut, alarm)
            return
        for h in self.hazards[hazards_before:]:
            if h.kind is HazardKind.COMMAND_TIMEOUT:
                # the cut command and every byte queued behind it never take effect
                self._loss(t, 1 + int(h.detail["discarded"]), self._host_of(h.offset), "command_timeout")
        # call_ns per Serial.available(): runEtactileKit checks again for the payload of a byte just read
        reads_end = t + m.call_ns * parser.checks + out.consumed * m.byte_ns
        sensed = self._hv513_in_call
        # stackSense(): the detection, then hv513Init() on the count it found.  While it senses the stack
        # the table says whether the stimulation timer is stopped (v2: from the timerAlarmDisable after
        # the byte's read, so no alarm interrupts the detection; one due meanwhile fires at the re-enable)
        end = reads_end + (hv513_count_ns(m, regs.hv513_num) if sensed else 0)
        paused = sensed and self.firmware.hv513_pauses_timer
        self._hv513_in_call = False
        applied = self._applied_in_call
        # 0xF6 calls setPeriodUs (a read point) only for a non-zero rate: 0xF6 0 is ignored
        frequency = applied == OpcodeV2.FREQUENCY and self.applied[-1][2] != 0
        # an alarm inside the call pre-empts it, whatever the call did (a command applied, a byte skipped, a
        # payload still awaited): the call ends the scan's duration later.  0xF6's setPeriodUs and 0xF5's
        # timerAlarmDisable come after the call's reads and are themselves points where a due alarm is
        # taken (the ties); 0xF5's alarm is disabled from then on
        # (the point until which an alarm pre-empts the call, and whether one due there still does)
        limit, tie = (reads_end, True) if paused else (end, frequency)
        if t < alarm and (alarm < limit or (tie and alarm == limit)):
            # the alarm is before the call's end, so before its latest end, and inside its read points
            assert clock.alarm_ns == alarm and clock.asked
            # 0xF6's alarm and 0xF5's count are stored after the point where the scan took the processor
            held = {"timer_alarm_ticks": old_ticks, "hv513_num": old_hv513}
            end += self._scans_in_call(clock, t, out.consumed, applied, before, old_pattern, held, limit, tie)
        if frequency:  # setPeriodUs re-enables the alarm after the call's last read (and the scan it let in)
            self._next_alarm_ns = max(end, self._last_alarm_ns() + self._period_ns())
        self._send_replies(end)
        if paused and self._next_alarm_ns < end:
            self._next_alarm_ns = end  # the alarm was disabled; a passed alarm fires on re-enable
        if out.slept:
            self._next_call_ns = self._tick_after(end)
        else:
            self._next_call_ns = end
            self._note_second_check(out.consumed, alarm, end)

    def _idle_call(self, t: int) -> None:
        """An idle poll (most calls): nothing to read, nothing to write, the task sleeps to the next tick --
        what :meth:`_main_call`'s full path computes for a call that consumes nothing."""
        end = t + self.model.call_ns
        if t < self._next_alarm_ns < end:  # the scan takes the processor before vTaskDelay
            end = self._scan_in_idle_call(self._next_alarm_ns, end)
            if end < 0:
                return
        self._next_call_ns = self._tick_after(end)

    def _send_replies(self, end: int) -> None:
        """The call's replies, written as it ends (through the reply link, if any)."""
        tx = self.parser.take_tx()
        if (
            tx
            and self._reply_offset is not None
            and self._clients
            and self._reply_offset < self._clients[-1][0]
        ):
            # asked by a host that has gone: the firmware writes to the new one's
            # socket only what the new one asked (see new_client)
            self.replies_dropped += len(tx)
            tx = b""
        if tx:
            if self.tx_link is None:
                self._tx.append((end, tx))
            else:
                self._tx += [
                    (d.t_ns, d if isinstance(d, ByteBurst) else d.data)
                    for d in self.tx_link.schedule_bursts(tx, end)
                ]

    def _tick_after(self, t: int) -> int:
        """The first RTOS tick after ``t`` (the ticks run from boot, shifted by ``tick_phase_us``)."""
        base = self._tick_base
        if t < base:
            return base
        tick = self.model.rtos_tick_ns
        return base + ((t - base) // tick + 1) * tick

    def _on_command(self, op: int, value: object, offset: int) -> None:
        self.applied.append((self._call_time_ns, op, value))
        host = self._host_of(offset)
        in_sync = host >= 0 and self._host_stream.starts.get(host) == op
        self.commands.append(CommandRecordV2(self._call_time_ns / 1000, op, host, in_sync))
        if self._sinks:
            name = self.emulator.parser.spec.command(op).name
            shown = list(value) if isinstance(value, (bytes, bytearray)) else value
            self._mark(
                self._call_time_ns,
                "command",
                {"name": name, "value": shown, "host_offset": host, "in_sync": in_sync},
            )
        self._host_stream.forget_before(host)
        for k in range(len(self.hazards) - 1, max(-1, len(self.hazards) - 4), -1):
            h = self.hazards[k]
            if h.kind is HazardKind.PAYLOAD_HOLDS_COMMAND_BYTE and h.offset == offset:
                # a value byte like a command byte is the host's own value when the command is the host's
                # (the hazard comes just before the command's own, e.g. stale channels of a raised count)
                self.hazards[k] = replace(h, detail={**h.detail, "meant_as_command": not in_sync})
                break
        if self._clients:
            self._check_inherited(op, value, offset)
        self._applied_in_call = op
        if value is None:  # a reply command (0xFF, 0xF5, 0xF4)
            self._reply_offset = offset
        if op == OpcodeV2.HV513_COUNT:
            self._hv513_in_call = True
        elif op == OpcodeV2.FREQUENCY and value:
            # setPeriodUs (0xF6 0 is ignored): the new alarm value applies from the current counter
            self._next_alarm_ns = max(self._call_time_ns, self._last_alarm_ns() + self._period_ns())

    def _last_alarm_ns(self) -> int:
        return self._last_alarm

    def _check_inherited(self, op: int, value: object, offset: int) -> None:
        """A command whose byte came from one host and whose payload ended in the next one's bytes."""
        p = self.parser
        end = p.offset
        for k, (start, name) in enumerate(self._clients):
            if offset < start < end:
                rx, base = p.rx, p.base
                old = bytes((op,)) + bytes(rx[max(offset + 1, base) - base : start - base])
                new = bytes(rx[start - base : end - base])
                previous = self._clients[k - 1][1] if k else "the previous host"
                self.hazards.append(
                    Hazard(
                        HazardKind.INHERITED_COMMAND,
                        offset,
                        {
                            "command": p.spec.command(op).name,
                            "cut_by": previous,
                            "cut_bytes": old.hex(" "),
                            "completed_by": name,
                            "completing_bytes": new.hex(" "),
                            "stored": value,
                        },
                        self._call_time_ns / 1000,
                    )
                )
                return


def pattern_in_force_v2(
    heights: list[int],
    *,
    link: str = "usb",
    pulse_width_us: int = 200,
    discharge_us: int = 45,
    rate_hz: int = 125,
    phases: int = 16,
    chunking: str = "whole",
) -> dict[str, Any]:
    """Host write → the first scan using a new pattern, on v2, over ``phases`` write moments.

    ``chunking`` "whole" writes the 0xFE command at once; "upstream" as the upstream Python and Unity
    APIs do (8-byte chunks, 3 ms apart).  Returns min / mean / max of: applied (the parser stored it),
    first channel (its first pulse at the new height), last channel, in µs."""
    from tactdeform_hw.protocol.commands import commands_for

    c2 = commands_for(V2)

    if chunking not in ("whole", "upstream"):
        raise LimitError("chunking", chunking, "whole or upstream")
    n = len(heights)
    if n == 0:
        raise ConfigurationError("pattern_in_force_v2 needs at least one electrode")
    setup = (
        c2.encode_electrode_num(n)
        + c2.encode_stim_mode(0)
        + c2.encode_pulse_width(pulse_width_us)
        + c2.encode_discharge(discharge_us)
        + c2.encode_frequency(rate_hz)
        + c2.encode_pattern([0] * n)
    )
    new = c2.encode_pattern(heights)
    rows: list[dict[str, float]] = []
    for i in range(phases):
        emu = TimedEmulatorV2(link=link)
        emu.write(setup, 0.0)
        t0 = 50_000.0 + round(8000.0 * ((i * 0.6180339887498949) % 1.0), 3)
        emu.advance_to(t0)
        chunks = [new] if chunking == "whole" else [new[k : k + 8] for k in range(0, len(new), 8)]
        for k, chunk in enumerate(chunks):
            emu.write(chunk, t0 + 3000.0 * k)
        emu.advance_to(t0 + 3000.0 * len(chunks) + 50_000.0)
        applied = [t for t, op, v in emu.applied if op == OpcodeV2.PATTERN and list(v) == list(heights)]  # type: ignore[call-overload]
        if not applied:
            raise ConfigurationError("the pattern was never applied")
        ta = applied[0]
        scan = next(s for s in emu.scans if s.start_ns >= ta)
        rows.append(
            {
                "applied_us": (ta - t0 * 1000) / 1000,
                "first_channel_us": (scan.start_ns + scan.onset_ns[0] - t0 * 1000) / 1000,
                "last_channel_us": (scan.start_ns + scan.onset_ns[-1] - t0 * 1000) / 1000,
            }
        )

    def stats(key: str) -> dict[str, float]:
        vals = [r[key] for r in rows]
        return {"min": min(vals), "mean": sum(vals) / len(vals), "max": max(vals)}

    return {
        "firmware": "v2",
        "link": link,
        "chunking": chunking,
        "phases": phases,
        "electrodes": n,
        **{k: stats(k) for k in ("applied_us", "first_channel_us", "last_channel_us")},
    }
