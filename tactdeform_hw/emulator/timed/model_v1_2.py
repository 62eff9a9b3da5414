"""The emulated controller on a simulated clock: link, receive queue, parser rhythm, scans, watchdog.

The same :class:`~tactdeform_hw.emulator.firmware.parser.Parser` and registers as the untimed
:class:`~tactdeform_hw.emulator.core.Emulator`, driven one firmware call at a time:

* **Link** — host writes go through a link model (:mod:`.link`) and reach the 256-byte receive queue as
  chunks at their delivery times; a chunk that does not fit loses its rest (a :class:`LossReport`).
* **Main loop** — the parser's calls happen between scans (the Arduino loop task and the timer interrupt
  share core 1, so the interrupt pre-empts the parser — the parser never runs during a scan).  A call
  costs ``parser_call_us`` per ``Serial.available()`` its code makes and ``parser_byte_us`` per byte read
  (:func:`call_reads_ns`; 0xF5 reads its byte before the stack detection); one that reads a command with a
  payload (or reads nothing) ends with ``vTaskDelay(1)`` and resumes at the next RTOS tick — or, when that
  tick falls inside a scan, when the scan ends.  Calls that answer 0xFF/0xF5 or skip an unknown byte return
  at once.  A u16 with one byte waiting spins until the other arrives.  A call reading a payload goes on
  while bytes keep arriving: runEtactileKit()'s ``while (isDataAvailable() > 0 && bytesRead <
  requiredBytes)`` checks the queue again after every read, so a byte that arrived during the call is read
  by it, and the call ends only at a check that finds nothing.  Replies are written at once and travel
  back over ``tx_link``.  A scan finds stored the bytes whose read had ended by its alarm; a read under
  way then has taken its bytes from the queue (:func:`call_read_starts_ns`) and stores them after the
  scan; the rest are read when the call resumes after the scan, with what has arrived by then -- which is
  how a pattern gets torn.
* **Scans** — on each alarm the handler runs a :class:`~.scan.ScanTemplate` of the registers at that
  moment (the parser cannot change them mid-scan); the next alarm follows the overrun policy.  Long
  stretches without host traffic are simulated as one :class:`~.reports.ScanRun` (a template repeated at
  a stride), which is exact because nothing a scan depends on changes inside the stretch.
* **Watchdog** — a handler longer than ``watchdog_us`` reboots the device to its power-on state at that
  moment; bytes in the queue and bytes arriving during ``boot_us`` are lost and reported.

Time is integer nanoseconds inside; the public API speaks µs.  It answers *when did each command take
effect* (``CommandReport.effect_us``) and *when did the first pulse with the new pattern reach each
channel* (``CommandReport.channels``).

Two consequences worth knowing.  When scans fill the period, the parser runs only in the gaps: at most
one command with a payload per period.  When scans overrun under the default policy they run back to
back and the main loop never runs again: nothing more is read until a reset.  (A modelling choice that
is an assumption: RTOS ticks and USB frames are phase-aligned at boot unless ``tick_phase_us`` says
otherwise.)

:meth:`state` is exact at the granularity of a parser call: a call's effects (the bytes it reads, the
register it stores, its reply in ``tx_log``) show from the call's start, while the firmware stores the
register when it has read the payload — ``CommandReport.effect_us`` is that later moment (the call's
last byte read; the firmware's own store follows within a microsecond).  Between a call's start and its
end, a few µs, ``state()`` is ahead of the firmware; holding the old registers back until
``effect_us`` would cost a copy of the registers on every call for that window alone.

``stimulation=False`` leaves the stimulation timer stopped: the link and the parser's rhythm alone.

Hooks for fault injection: pass a :class:`~.link.LinkFilter` as ``link`` (or ``tx_link``), inject bytes
with :meth:`deliver`, power-cycle with :meth:`reset`, hang the main loop with :meth:`stop_reading`.

For drivers there is a pyserial-like face: :meth:`write` (optionally at a future time),
:meth:`advance_to` / :meth:`run_until`, :meth:`read_tx`, :attr:`in_waiting`, :attr:`now_us`.
"""

from __future__ import annotations

import copy
import heapq
import math
from bisect import bisect_left, bisect_right
from collections.abc import Container
from itertools import repeat
from typing import TYPE_CHECKING, Any

from tactdeform_hw.emulator.core import Emulator
from tactdeform_hw.emulator.firmware.board import Board
from tactdeform_hw.emulator.firmware.hazards import Hazard, HazardKind
from tactdeform_hw.emulator.firmware.models import entry_part, model_entry
from tactdeform_hw.emulator.firmware.parser import CallResult, Parser
from tactdeform_hw.emulator.firmware.registers import Registers
from tactdeform_hw.emulator.firmware.scan import (
    POWER_ON_CHAIN,
    ChainState,
    ScanConfig,
    ScanEngine,
    physical_outputs,
)
from tactdeform_hw.emulator.firmware.skin import DEFAULT_SKIN, SkinModel
from tactdeform_hw.emulator.records.reports import (
    CommandReport,
    LossReport,
    ScanRun,
    TimingReports,
)
from tactdeform_hw.emulator.timed.base import TimedModel, TimedModelBase
from tactdeform_hw.emulator.timed.books_v1_2 import (
    CommandBooks,
    HostLedger,
    MainLoop,
    Records,
    ScanBooks,
    ns_of,
    us_of,
)
from tactdeform_hw.emulator.timed.link import (
    ByteBurst,
    Delivery,
    LinkModel,
    ReceiveQueue,
    Scheduled,
    make_link,
    next_key,
    reply_link,
    unread_after,
)
from tactdeform_hw.emulator.timed.timing import DEFAULT_MODEL, TimingModel
from tactdeform_hw.errors import ConfigurationError, LimitError
from tactdeform_hw.protocol.constants import OUTPUTS_PER_HV513, Opcode
from tactdeform_hw.protocol.decoder import StreamDecoder
from tactdeform_hw.protocol.firmware import V1_2, FirmwareSpec

_INF = math.inf
_PATTERN = int(Opcode.PATTERN)
_HV513 = int(Opcode.HV513_COUNT)
#: each opcode's name, for the report of every command read (an enum lookup per command costs more)
_OPCODE_NAMES = {int(o): o.name for o in Opcode}

_WAIT_TICK, _WAIT_STUCK, _WAIT_LOCKED = "tick", "stuck", "locked"


def _ignored_run(
    buf: bytearray,
    stops: Container[int],
    tc: int,
    step_ns: int,
    before: float,
    target: int,
    alarm: float,
) -> tuple[int, int]:
    """How many calls from ``tc`` on each read one waiting non-command byte, and when the last ends: each
    call must start before anything else happens (``before``: the next delivery or alarm; the run's
    ``target``) -- the event loop would take that first -- and end before the next alarm, which would
    interrupt it (the full path times that call).  ``stops``: the bytes such a run ends at
    (:func:`_stop_bytes`)."""
    k, t = 0, tc
    for b in buf:
        if b in stops:
            break
        if k and not (t < before and t <= target):
            break
        end = t + step_ns
        if alarm < end:
            break
        k, t = k + 1, end
    return k, t


_STOP_BYTES: dict[type, frozenset[int]] = {}


def _stop_bytes(p: Parser) -> frozenset[int]:
    """The bytes a run of ignored-byte calls ends at: the commands ``p`` knows (whose reading is not a
    skip) and 0xF5 (whose detection times the call otherwise).  What a parser knows is its firmware's
    table, the same for every parser of a class, so the set is made once per class and looked up per
    byte (a method call per byte of a resync's zeros cost more than the rest of the run)."""
    kind = type(p)
    stops = _STOP_BYTES.get(kind)
    if stops is None:
        stops = _STOP_BYTES[kind] = frozenset(b for b in range(256) if p.is_command(b) or b == _HV513)
    return stops


def hv513_count_ns(m: TimingModel, detected: int) -> int:
    """0xF5's work before its reply: stackSense()'s 50 ``analogRead`` calls, then hv513Init() on the
    ``detected`` count: four pin writes (POL, LE, CLK, BL), DIN low, and a CLK high and low per output
    (``gpio_write_us`` each; upstream switching.cpp)."""
    return m.hv513_detect_ns + (5 + 2 * OUTPUTS_PER_HV513 * detected) * m.gpio_ns


def init_interrupted(
    chain: ChainState,
    outputs: int,
    m: TimingModel,
    call_end: int,
    ta: int,
    detected: int,
    edges_before: int | None,
) -> tuple[ChainState, int] | None:
    """The chain a scan at ``ta`` starts from when it interrupts an 0xF5 call ending at ``call_end``, and the
    CLK rising edges hv513Init() has made by then; ``None`` while still in stackSense()'s analogRead calls.
    hv513Init()'s ``5 + 16 x detected`` pin writes end the call (POL, LE low, CLK low, BL, DIN low, then a
    CLK high and low per output); the interrupt comes between two writes, after every write begun before
    ``ta``: the zeros clocked in so far are in the shift register, and CLK is high when it came between a
    CLK high and its CLK low (the scan's first CLK pulse then shifts nothing in: it lights no output)."""
    g = m.gpio_ns
    total = 5 + 2 * OUTPUTS_PER_HV513 * detected
    start = call_end - total * g
    if ta <= start:
        return None
    clocks = max(0, min(total, -(-(ta - start) // g)) - 5)
    edges = (clocks + 1) // 2
    bits = (chain.bits << (edges - (edges_before or 0))) & ((1 << outputs) - 1)
    return ChainState(chain.position, bits, chain.latched, clocks % 2 == 1), edges


def init_finished(chain: ChainState, outputs: int, edges_left: int) -> ChainState:
    """The chain once an interrupted hv513Init() has clocked its last ``edges_left`` zeros: the scan left LE
    high, so the outputs follow the shift register."""
    bits = (chain.bits << max(0, edges_left)) & ((1 << outputs) - 1)
    return ChainState(chain.position, bits, bits)


_U16_SIZE = 2


def u16_waiting(p: Parser, queued: bytearray, t: int) -> Hazard:
    """The hazard of a parser spinning on a u16's missing byte, from ``t`` (ns)."""
    detail = {
        "command": Opcode(p.cmd).name if p.cmd is not None else None,
        "low_byte": queued[0] if queued else None,
    }
    return Hazard(HazardKind.U16_WAITING, p.offset, detail, t / 1000)


def payload_unit(cmd: int | None, buf: bytearray) -> int:
    """The payload unit of the command a parser call works on (the one in progress, ``cmd``, else the
    queue's first byte): 2 for a u16 (the firmware waits for both bytes and reads them together), else 1;
    from the version's table."""
    op = cmd if cmd is not None else buf[0] if buf else None
    spec = V1_2.by_opcode.get(op) if op is not None else None
    return _U16_SIZE if spec is not None and spec.kind == "u16" else 1


def call_reads_ns(m: TimingModel, lead: bool, payload_size: int, reads: int) -> list[int]:
    """When each of a parser call's first ``reads`` byte reads ends, in ns from the call's start, as
    runEtactileKit()'s code spends them: ``Serial.available()`` (``call_ns``) before the command byte (a
    call that ``lead`` s with one) and at every check of the payload loop -- before each payload byte, and a
    second time before a u16 (``isDataAvailable() >= 2``), whose two bytes are read together -- and
    ``byte_ns`` per byte read.  ``payload_size`` is the command's payload unit (2 for a u16, else 1)."""
    a, b = m.call_ns, m.byte_ns
    out: list[int] = []
    t = 0
    if lead:
        t = a + b
        out.append(t)
    while len(out) < reads:
        if payload_size == _U16_SIZE:
            t += 2 * a + 2 * b
            out += [t, t]
        else:
            t += a + b
            out.append(t)
    return out[:reads]


def call_read_starts_ns(m: TimingModel, lead: bool, payload_size: int, reads: int) -> list[int]:
    """When each of a parser call's first ``reads`` byte reads begins, in ns from the call's start: the
    ends of :func:`call_reads_ns` less the read's own ``byte_ns`` (a u16's two bytes: one read of both,
    ``Serial.read(arr, 2)``).

    Which bytes have left the queue when a scan comes: those whose read had begun before its alarm.  The
    interrupt takes the processor at its alarm, inside a ``Serial`` call under way as the chip does (and
    the host build's shim), and the firmware stores a byte only when its read has returned: the scan
    finds stored the reads ended by its alarm (:func:`call_reads_ns`), and a read under way then has
    taken its bytes, which are stored after the scan (the v2 model's ``_ReadClock`` reads it the same
    way)."""
    b = m.byte_ns
    ends = call_reads_ns(m, lead, payload_size, reads)
    return [
        e - (2 * b if payload_size == _U16_SIZE and not (lead and i == 0) else b) for i, e in enumerate(ends)
    ]


class ArrivalRuns:
    """Where the v1.2 model's event loop would take one byte or one call at a time for long stretches,
    the stretch in one go, exactly as one at a time (a mixin of :class:`TimedEmulator`, which keeps the
    state): a burst's bytes that arrive before anything else happens, and a run of calls that each
    ignore one non-command byte with the bytes arriving meanwhile."""

    fw: MainLoop
    host: HostLedger
    queue: ReceiveQueue
    emulator: Emulator
    model: TimingModel
    next_alarm: float
    now_ns: int

    @property
    def parser(self) -> Parser:
        raise NotImplementedError

    def _deliver(self, d: Delivery) -> None:
        raise NotImplementedError

    def _skip_unknown(self, tc: int, alarm: float, target: int) -> bool:
        """Run the calls that each read and ignore one non-command byte (a resync's zeros: most calls of a
        session) in one go, exactly as :meth:`_main_call` would one by one (see :func:`_ignored_run`).
        Bytes of a burst arriving meanwhile land with them when nothing they do depends on when
        (:meth:`_arrivals_alike`); else the run stops at the next delivery, which the event loop takes
        first.  False (nothing done) when the next call is not such a call."""
        fw = self.fw
        p = self.parser
        if fw.call is not None or p.cmd is not None or fw.checking or fw.check_left_ns is not None:
            return False  # (the loop goes on with a call or a check first)
        if fw.period_pending is not None:
            return False  # (setPeriodUs() first, as the loop resumes)
        q = self.queue
        stops = _stop_bytes(p)
        if not q.buf or q.buf[0] in stops:  # (the common case: a command waits, or nothing does)
            return False
        step_ns = self.model.call_ns + self.model.byte_ns
        dq = self.host.deliveries
        k, t = _ignored_run(q.buf, stops, tc, step_ns, alarm, target, alarm)
        if k == 0:
            return False
        arriving = 0
        if dq and dq[0][0] <= t - step_ns:  # something lands before the run's last call
            arriving = self._arrivals_alike(tc, t - step_ns)
            if not arriving:
                k, t = _ignored_run(q.buf, stops, tc, step_ns, min(dq[0][0], alarm), target, alarm)
        queued = len(q.buf)
        dev0 = fw.parser_base + p.offset
        p.receive(q.take(k))
        p.ignore_unknown(k)
        fw.call_end_ns, fw.call_dev_last, fw.main_next = t, dev0 + k - 1, t  # fw.call stays None
        fw.read_starts = [t - step_ns + self.model.call_ns]  # the last call's read (see _taken_unread)
        if arriving:
            self._land_during_run(tc, step_ns, k, queued, arriving)
        return True  # (an ignored byte writes no reply)

    def _arrivals_alike(self, tc: int, last: int) -> int:
        """How many bytes land from ``tc`` to ``last`` (the start of a run's last call) when they may
        land after the run instead of between its calls, else 0: they are the next bytes of the burst at
        the head of the delivery heap and nothing else arrives meanwhile, no reboot is under way, the
        parser is not locked and the queue has room for all of them even if no call read a byte."""
        dq = self.host.deliveries
        _, seq, b = dq[0]
        key = next_key(dq)
        if not isinstance(b, ByteBurst) or (key is not None and key[0] <= last):
            return 0
        if b.t_ns < self.fw.booting_until or self.emulator.parser.locked:
            return 0
        n = b.end_before(last, key, seq) - b.pos
        return n if len(self.queue.buf) + n <= self.queue.capacity else 0

    def _land_during_run(self, tc: int, step_ns: int, calls: int, queued: int, n: int) -> None:
        """The ``n`` next bytes of the head burst, which arrived during a run of ``calls`` ignored-byte
        calls from ``tc`` (``queued`` bytes waited before it): they join the queue, each with its own
        arrival time in the books, and the queue's high-water mark is what it was at each arrival (the
        bytes waiting then: those queued, minus one per call started before it, plus the arrivals)."""
        dq = self.host.deliveries
        _, seq, b = dq[0]
        assert isinstance(b, ByteBurst)  # (_arrivals_alike counted its bytes)
        k0 = b.pos
        times = b.times[k0 : k0 + n]
        peak = max(queued - min(calls, -(-(a - tc) // step_ns)) + i + 1 for i, a in enumerate(times))
        hosts = b.host_offsets(k0 + n)
        hl = self.host
        dev0 = hl.dev_total
        self.queue.join(b.take(k0 + n), peak)
        devs = range(dev0, dev0 + n)
        hl.seg_dev.extend(devs)
        hl.segments.extend(zip(devs, repeat(-1) if hosts is None else hosts, repeat(1), times))
        hl.dev_total = dev0 + n
        if len(b):
            heapq.heapreplace(dq, (b.t_ns, seq, b))
        else:
            heapq.heappop(dq)

    def _taken_unread(self, t: int) -> int:
        """Bytes the last parser call took from the queue whose read the firmware begins at ``t`` or later
        (``MainLoop.read_starts``): runEtactileKit() reads a payload one byte at a time (a u16's two
        together), so a byte arriving while it reads finds those still in the firmware's queue, and may not
        fit.  (The host build moves an arrival into the queue at the firmware's next call into the
        platform: before a read that starts at or after it, after one under way.)"""
        return unread_after(self.fw.read_starts, t)

    def _deliver_burst(self, dq: list[tuple[int, int, Any]], target: int) -> None:
        """The burst at the head of the delivery heap: its next byte as a delivery of its own (it may
        wake the main loop, be lost, ...), then at once the bytes after it that arrive before anything
        else happens -- an alarm, a parser call (a delivery comes first on a tie), ``target``, another
        delivery -- as long as each would simply join the queue (no reboot under way, no locked parser,
        room for all of them); what a byte at a time does then is what :meth:`_deliver` does for each."""
        _, seq, b = dq[0]
        self._deliver(b.pop())
        fw = self.fw
        if len(b) and b.t_ns >= fw.booting_until and not self.emulator.parser.locked:
            bound = min(self.next_alarm, fw.main_next if fw.main_next is not None else _INF, target)
            if fw.read_starts and fw.read_starts[-1] >= b.t_ns:  # a byte at a time while a call reads
                bound = min(bound, fw.read_starts[-1] + 1)
            j = b.end_before(bound, next_key(dq), seq)
            q = self.queue
            j = min(j, b.pos + q.capacity - len(q.buf))
            if j > b.pos:
                hl = self.host
                k0 = b.pos
                hosts = b.host_offsets(j)
                times = b.times[k0:j]
                dev0 = hl.dev_total
                q.offer(b.take(j))
                devs = range(dev0, dev0 + j - k0)
                hl.seg_dev.extend(devs)
                hl.segments.extend(zip(devs, repeat(-1) if hosts is None else hosts, repeat(1), times))
                hl.dev_total = dev0 + j - k0
        if len(b):
            heapq.heapreplace(dq, (b.t_ns, seq, b))
        else:
            heapq.heappop(dq)

    def _push_delivery(self, d: Scheduled) -> None:
        if isinstance(d, ByteBurst):
            if d.t_ns < self.now_ns:  # (a link's bursts never start in the past) each byte as a delivery
                for one in d.deliveries():
                    self._push_delivery(one)
                return
        elif d.t_ns < self.now_ns:
            d = Delivery(self.now_ns, d.data, d.host_offset, d.sent_ns)
        self.host.seq += 1
        heapq.heappush(self.host.deliveries, (d.t_ns, self.host.seq, d))


class Hv513Reinit:
    """0xF5's hv513Init() and the chain the scans see (a mixin of :class:`TimedEmulator`, which keeps the
    state): cleared when it ran whole, as far as it got when a scan interrupted it."""

    fw: MainLoop
    chain: ChainState
    engine: ScanEngine
    model: TimingModel
    emulator: Emulator

    def _on_hv513_reinit(self) -> None:
        fw = self.fw
        if fw.init_edges is None:
            self.chain = ChainState(self.chain.position, 0, 0)
        else:
            left = OUTPUTS_PER_HV513 * self.emulator.registers.hv513_num - fw.init_edges
            self.chain = init_finished(self.chain, self.engine.outputs, left)
            fw.init_edges = None

    def _init_interrupted(self, call_end: int, ta: int, detected: int) -> None:
        """An alarm at ``ta`` interrupts an 0xF5 call ending at ``call_end``: see :func:`init_interrupted`."""
        fw = self.fw
        got = init_interrupted(
            self.chain, self.engine.outputs, self.model, call_end, ta, detected, fw.init_edges
        )
        if got is not None:
            self.chain, fw.init_edges = got


class CallEnds:
    """What the main loop does once a parser call has read what it could (a mixin of
    :class:`TimedEmulator`, which keeps the state)."""

    fw: MainLoop
    rec: Records
    model: TimingModel
    next_alarm: float
    hazards: list[Hazard]
    queue: ReceiveQueue
    stimulation: bool

    if TYPE_CHECKING:  # (TimedEmulator's and CommandBooks' own)

        @property
        def parser(self) -> Parser: ...

        @property
        def registers(self) -> Registers: ...

        def _tick_after(self, t: int) -> int: ...

        def _delivered_at(self, dev_offset: int) -> int | None: ...

    def _end_call(self, outcome: CallResult, end: int, cpu: int, k: int, lead: bool) -> None:
        """What the main loop does after a call whose last read ends at ``end`` (``cpu`` ns and ``k`` bytes
        into the call) -- a scan due before then is taken first, and pushes what follows to its end."""
        fw = self.fw
        fw.call = None
        if outcome is CallResult.IGNORED or outcome is CallResult.REPLIED:
            fw.main_next = end
        elif outcome is CallResult.STUCK_U16:
            fw.call_lead = lead
            self._enter_stuck(end, cpu, k)
        elif outcome is CallResult.LOCKED:
            fw.main_next = None
            fw.main_wait = _WAIT_LOCKED
            if self.rec.cur is not None:
                self.rec.cur.note = "locks the parser: pattern command with electrode_num 0"
                self.rec.cur.arrival_us = us_of(self._delivered_at(fw.call_dev_last))
                self.rec.commands.append(self.rec.cur)
                self.rec.cur = None
        elif outcome is CallResult.PROGRESS or self.next_alarm <= end:
            # runEtactileKit()'s payload loop checks Serial.available() again when its last read ends: the
            # bytes that arrived meanwhile are read by this same call (_main_call goes on at that check);
            # a call that has read its command sleeps after that check, and after the scan its alarm
            # brings first (the host build takes a due interrupt at the check)
            fw.call = (cpu, k)
            fw.call_lead = lead
            fw.checking = True
            fw.main_next = end
        else:  # the payload loop's last check (Serial.available()), then vTaskDelay(1)
            self._last_check(end)

    def _read_nothing(self, tc: int, outcome: CallResult, checking: bool, lead: bool, unit: int) -> None:
        """A call at ``tc`` that finds nothing to read: the loop waits for a reset (a locked parser), for a
        u16's second byte, or polls and sleeps to the next tick (``vTaskDelay(1)``)."""
        fw = self.fw
        cpu0, k0 = fw.call if fw.call is not None else (0, 0)
        fw.call = None
        fw.main_next = None
        if outcome is CallResult.LOCKED:
            fw.main_wait = _WAIT_LOCKED
        elif checking and outcome is CallResult.PROGRESS:
            # the payload loop's check found nothing: it costs its Serial.available(), then vTaskDelay(1)
            self._last_check(tc)
        elif outcome is CallResult.STUCK_U16:
            done = call_reads_ns(self.model, lead, unit, k0)
            fw.call_lead = lead
            self._enter_stuck(tc, max(cpu0, done[-1] if done else 0), k0)
        elif self.next_alarm <= tc + self.model.call_ns:
            # a poll (Serial.available(), then vTaskDelay(1)) the alarm pre-empts: the loop sleeps to the
            # tick after the scan and the rest of the poll, not as the scan returns
            self._last_check(tc)
        else:
            fw.main_wait = _WAIT_TICK

    def _last_check(self, t: int, work_ns: int | None = None) -> None:
        """The payload loop's last ``Serial.available()`` check from ``t`` finds nothing to read, then
        runEtactileKit() calls ``vTaskDelay(1)``: the loop sleeps to the next RTOS tick after the check.  An
        alarm due before the check returns pre-empts it, so ``vTaskDelay`` is called only after the scan,
        with what was left of the check (``work_ns``, the whole check's ``call_ns`` by default), and the
        tick the loop sleeps to is the one after that -- not the tick inside the scan the check's own end
        would give, which would let the loop read again as the scan returns.  The rest may be pre-empted
        again: where the period leaves the loop a sliver between scans, a check spans many of them."""
        fw = self.fw
        check_end = t + (self.model.call_ns if work_ns is None else work_ns)
        ta = self.next_alarm
        if ta <= check_end:
            fw.check_left_ns = check_end - int(ta)
            fw.main_next = ta  # the scan at ta pushes this to its end
        else:
            fw.main_next = self._tick_after(check_end)

    def _retime_alarm(self, t: int, by_call: bool = False) -> None:
        """The parser wrote a new alarm value: an alarm the running counter has passed fires at once.

        setPeriodUs() runs after the frequency's read, and its first call into the platform is where a
        due interrupt is taken: an alarm due by ``t`` (a read that ended on it or ran across it) fires
        first, with the old alarm -- the handler re-enables that one as it returns -- and setPeriodUs()
        writes the new one only when the main loop gets the processor back (:meth:`_scan`): never, if
        that scan overruns the old period and the scans run back to back (``StimulationTimePeriod`` is
        stored before the call, ``period_us`` shows it)."""
        regs = self.registers
        if not self.stimulation:
            return
        if self.next_alarm <= t:
            if by_call:
                self.fw.period_pending = regs.timer_alarm_ticks
                regs.timer_alarm_ticks = self.fw.ticks_before_call
            return
        period = self.model.alarm_period_ns(regs.timer_alarm_ticks)
        if t - self.fw.last_reload >= period:
            self.next_alarm = t
        else:
            self.next_alarm = self.fw.last_reload + period

    def _spin_sees(self, t: int) -> None:
        """The spin on a half u16 (``while (isDataAvailable() > 0 ...)`` then ``if (isDataAvailable() >=
        2)``, ``call_ns`` each, pre-empted by the scans) when the second byte has arrived by ``t``, outside
        any scan: the call goes on from ``t``, with the spin's phase in its progress, so the first check
        for two bytes that begins at or after ``t`` finds them and the read follows."""
        fw = self.fw
        a = self.model.call_ns
        phase = (t - fw.spin_from - fw.spin_scanned_ns) % (2 * a)  # into the current pair of checks
        cpu, k = fw.call if fw.call is not None else (0, 0)
        # begun before the arrival, the check for two bytes found one: the next pair's is the one
        fw.call = (cpu + (phase if phase <= a else phase - 2 * a), k)

    def _enter_stuck(self, t: int, cpu: int, k: int) -> None:
        self.fw.call = (cpu, k)
        self.fw.main_next = None
        self.fw.main_wait = _WAIT_STUCK
        self.fw.spin_from, self.fw.spin_scanned_ns = t, 0
        if not self.fw.stuck_reported:
            self.fw.stuck_reported = True
            self.fw.stuck_at = t
            self.hazards.append(u16_waiting(self.parser, self.queue.buf, t))


class TimedEmulator(Hv513Reinit, CallEnds, ArrivalRuns, CommandBooks, ScanBooks, TimedModelBase):
    """The eTactileKit controller in simulated time.  See the module documentation."""

    firmware: FirmwareSpec = V1_2

    def __init__(
        self,
        board: str | Board = "compact",
        switching_boards: int = 1,
        *,
        link: str | LinkModel = "usb",
        tx_link: str | LinkModel | None = None,
        model: TimingModel | None = None,
        skin: SkinModel | None = None,
        stack_reading: float | None = None,
        stimulation: bool = True,
    ) -> None:
        self.stimulation = stimulation
        #: Bytes written to the board since power-on (0: no program can have left a command in its parser).
        self.received_bytes = 0
        self.model = model if model is not None else DEFAULT_MODEL
        self.skin = skin if skin is not None else DEFAULT_SKIN
        self.emulator = Emulator(board, switching_boards, stack_reading=stack_reading, firmware=V1_2)
        self.emulator.meant_as_command = self._meant_as_command
        self.emulator.parser.meant_as_command = self._meant_as_command
        self.board = self.emulator.board
        self.hazards: list[Hazard] = self.emulator.hazards
        self.link = make_link(link)
        self.tx_link = make_link(tx_link) if tx_link is not None else reply_link(self.link)
        self.queue = ReceiveQueue(self.model.rx_queue_bytes)
        self.engine = ScanEngine(
            self.model, self.skin, physical_outputs(self.board.kind, self.board.switching_boards)
        )
        self.now_ns = 0
        self.host = HostLedger(decoder=StreamDecoder(self.registers.electrode_num))
        self.rec = Records()
        self.next_alarm: float = _INF  # the timer (set by _boot, with the main loop's state)
        self.fw = MainLoop()
        self._boot(0, first=True)

    # --- public API -----------------------------------------------------------------------------------------

    @property
    def registers(self) -> Registers:
        return entry_part(self.emulator.registers, Registers)

    # --- the records, by their public names ---

    @property
    def runs(self) -> list[ScanRun]:
        """Every stretch of scans simulated (kept since the last :meth:`discard_history`)."""
        return self.rec.runs

    @property
    def commands(self) -> list[CommandReport]:
        """A report per command the parser read: when it arrived, took effect and was first felt."""
        return self.rec.commands

    @property
    def tx_log(self) -> list[tuple[float, bytes]]:
        """Every reply the firmware wrote: (device time µs, bytes)."""
        return self.rec.tx_log

    @property
    def reboots(self) -> int:
        return self.rec.reboots

    @property
    def interrupted_calls(self) -> int:
        """Parser calls an alarm interrupted mid-read."""
        return self.rec.interrupted_calls

    @property
    def scans(self) -> int:
        """Scans the timer has run in this session (reboots included)."""
        return self.rec.scan_index

    @property
    def parser(self) -> Parser:
        return entry_part(self.emulator.parser, Parser)

    @property
    def reports(self) -> TimingReports:
        return TimingReports(self)

    @property
    def losses(self) -> list[LossReport]:
        """Every loss so far; those not followed by a command in step yet say what the parser does now."""
        now = self.parser_status() + f" at {self.now_us:.1f} us"
        for lo in self.rec.open_losses:
            lo.parser_now = now
        return self.rec.losses

    def scan_rate(self, at_us: float) -> tuple[int, float]:
        """Scans since power-up and the current scan rate in Hz (0 when the scans stopped)."""
        if self.runs:
            last = self.runs[-1]
            if last.end_ns >= at_us * 1000 - 2 * last.stride_ns and last.stride_ns > 0:
                return self.scans, 1e9 / last.stride_ns
        return self.scans, 0.0

    def current_pulse_starts_us(self, since_us: float, now_us: float) -> list[float]:
        """The start times of the delivered pulses that carried current between the two times."""
        table = self.reports.pulse_table(since_us, now_us)
        return [float(t) for t, ua in zip(table["start_us"], table["current_ua"], strict=True) if ua > 0]

    def new_client(self, name: str) -> None:
        """A new host connection starts: nothing changes on v1.2 (its parser has no timeout, so a cut
        command takes the new host's bytes as payload whatever the time: recorded as any desync is)."""

    def write(self, data: bytes, at_us: float | None = None) -> int:
        """The host writes ``data`` at ``at_us`` (default: now).  Writes must come in time order; a write
        in the future is scheduled and happens as the clock gets there.  Returns the byte count."""
        data = bytes(data)
        self.received_bytes += len(data)
        t = self.now_ns if at_us is None else ns_of(at_us)
        if t < self.now_ns:
            raise LimitError("at_us", at_us, f">= now ({self.now_us} us)")
        if t < self.host.last_write_ns:
            raise LimitError("at_us", at_us, f">= the previous write ({self.host.last_write_ns / 1000} us)")
        self.host.last_write_ns = t
        if not data:
            return 0
        off = self.host.offset
        self.host.writes.append((off, len(data), t))
        self.host.write_starts.append(off)
        for start, op, end in self.host.decoder.feed_spans(data):
            self.host.intended[start] = (op, end)
            self.host.intended_starts.append(start)
        self.host.offset += len(data)
        for d in self.link.schedule_bursts(data, t, off):
            self._push_delivery(d)
        return len(data)

    def deliver(self, data: bytes, at_us: float | None = None, host_offset: int = -1) -> None:
        """Bytes that reach the device's receive path at ``at_us`` without passing the link model (noise,
        a second host, a fault layer's own traffic)."""
        t = self.now_ns if at_us is None else ns_of(at_us)
        if t < self.now_ns:
            raise LimitError("at_us", at_us, f">= now ({self.now_us} us)")
        self._push_delivery(Delivery(t, bytes(data), host_offset, t))

    def advance_to(self, t_us: float) -> None:
        """Run the device until ``t_us``."""
        target = ns_of(t_us)
        if target < self.now_ns:
            raise LimitError("t_us", t_us, f">= now ({self.now_us} us)")
        self._run(target)
        self.now_ns = target

    run_until = advance_to

    def next_event_us(self, scans: bool = True) -> float:
        """When the device next does something (a delivery lands, the main loop calls the parser, a reply
        reaches the host, and with ``scans`` an alarm fires); ``inf`` when nothing is scheduled.  A
        runner locked to the wall clock sleeps until then."""
        t = min(
            self.host.deliveries[0][0] if self.host.deliveries else _INF,
            self.host.tx_deliveries[0][0] if self.host.tx_deliveries else _INF,
            self.fw.main_next if self.fw.main_next is not None else _INF,
            self.next_alarm if scans else _INF,
        )
        return t / 1000.0

    @property
    def host_offset(self) -> int:
        """Bytes the host has written so far (the offset its next byte will have)."""
        return self.host.offset

    def configure(self, cfg: ScanConfig) -> None:
        """Set the scan registers directly, as if a host had configured the device without link or parser
        time (for budgets, traces and latency experiments).  The alarm follows the new period like a
        frequency command would."""
        regs = self.registers
        regs.electrode_num = cfg.electrode_num
        regs.polarity = cfg.polarity
        regs.pulse_height = cfg.pulse_height
        regs.pulse_width = cfg.pulse_width
        regs.sense_pulse_height = cfg.sense_pulse_height
        regs.sense_pulse_width = cfg.sense_pulse_width
        regs.discharge_time = cfg.discharge_time
        regs.stim_pattern[: cfg.electrode_num] = cfg.pattern
        regs.hv513_num = cfg.hv513_num
        self.host.decoder.electrode_num = cfg.electrode_num
        if regs.timer_alarm_ticks != cfg.alarm_ticks:
            regs.timer_alarm_ticks = cfg.alarm_ticks
            regs.period_us = cfg.alarm_ticks * self.model.timer_tick_us
            self._retime_alarm(self.now_ns)

    def stop_reading(self) -> None:
        """The main loop hangs: nothing is read any more (the queue fills, the scans go on) until a reset."""
        self.fw.call = None
        self.fw.checking = False
        self.fw.check_left_ns = None
        self.fw.period_pending = None
        self.fw.held = b""
        self.fw.main_next = None
        self.fw.main_wait = _WAIT_LOCKED

    def reset(self, reason: str = "reset") -> None:
        """Power-cycle the device now (registers, queue, parser to power-on; the links stay)."""
        self._reboot(self.now_ns, reason, boot_delay=True)

    # --- boot -----------------------------------------------------------------------------------------------

    def _boot(self, t: int, first: bool = False, boot_delay: bool = False) -> None:
        if not first:
            self.emulator.reset()
        p = self.emulator.parser
        p.on_command = self._on_command
        p.on_hv513_reinit = self._on_hv513_reinit
        self.chain: ChainState = POWER_ON_CHAIN
        start = t + (self.model.boot_ns if boot_delay else 0)
        regs = self.registers
        last_reload = start + self.model.timer_start_ns
        self.next_alarm = last_reload + self.model.alarm_period_ns(regs.timer_alarm_ticks)
        if not self.stimulation:
            self.next_alarm = _INF
        self.fw = MainLoop(
            parser_base=self.host.dev_total,
            booting_until=start,
            tick_base=start,
            last_reload=last_reload,
            main_next=start,
            call_end_ns=start,
            call_dev_last=self.host.dev_total,
        )
        rec = self.rec
        rec.cur, rec.cur_written, rec.cur_first, rec.cur_old, rec.last_rep = None, {}, {}, b"", None

    def _reboot(self, t: int, reason: str, boot_delay: bool = True) -> None:
        self.rec.reboots += 1
        self.received_bytes = 0  # power-on: no command can be pending
        left = self.queue.clear()
        if left:
            self._loss(t, left, self._host_of(self.fw.parser_base + self.parser.offset), "reboot")
        for pend in self.rec.awaiting:
            pend.report.note = (
                pend.report.note + "; " if pend.report.note else ""
            ) + f"not felt: {reason} at {t / 1000:.1f} us"
            if pend.channels:
                for cl in pend.channels.values():
                    cl.note = reason
        self.rec.awaiting.clear()
        if self.rec.cur is not None:
            self.rec.cur.note = f"incomplete at {reason}"
        for lo in self.rec.open_losses:
            lo.followed.append(
                {
                    "name": reason.upper(),
                    "value": None,
                    "host_offset": -1,
                    "in_sync": False,
                    "time_us": t / 1000,
                }
            )
        self.rec.open_losses.clear()
        self._mark(t, "reset", {"reason": reason})
        self._boot(t, boot_delay=boot_delay)

    # --- the event loop -------------------------------------------------------------------------------------

    def _run(self, target: int) -> None:
        dq = self.host.deliveries
        while True:
            td = dq[0][0] if dq else _INF
            ta = self.next_alarm
            tm = self.fw.main_next
            if tm is None:
                tm = _INF
            t = td if td <= ta else ta  # min(td, ta, tm), the first of equals as min takes it
            if tm < t:
                t = tm
            if t > target:
                return
            if td == t:
                head = dq[0][2]
                if isinstance(head, ByteBurst):
                    self._deliver_burst(dq, target)
                else:
                    heapq.heappop(dq)
                    self._deliver(head)
            elif ta == t:
                self._scan(int(ta), target)
            elif not self._skip_unknown(int(tm), ta, target):
                self._main_call(int(tm))

    # --- deliveries and the queue ---------------------------------------------------------------------------

    def _deliver(self, d: Delivery) -> None:
        t = d.t_ns
        if t < self.fw.booting_until:
            self._loss(t, d.data, d.host_offset, "rebooting")
            return
        took = self.queue.offer(d.data, self._taken_unread(t))
        if took:
            hl = self.host
            hl.seg_dev.append(hl.dev_total)
            hl.segments.append((hl.dev_total, d.host_offset, took, t))
            hl.dev_total += took
            if self.emulator.parser.locked:
                self.hazards.append(
                    Hazard(
                        HazardKind.UNREAD_WHILE_LOCKED,
                        self.host.dev_total - took - self.fw.parser_base,
                        {"bytes": took, "pending": len(self.queue)},
                        t / 1000,
                    )
                )
        if took < len(d.data):
            self._loss(t, d.data[took:], d.host_offset + took if d.host_offset >= 0 else -1, "queue_full")
        fw = self.fw
        if took and fw.main_wait is not None and fw.main_wait != _WAIT_LOCKED:
            if fw.main_wait == _WAIT_TICK:
                nxt = self._tick_at_or_after(t)
                if (
                    fw.busy_from <= t <= fw.busy_until
                    and self._tick_at_or_after(fw.busy_from) < fw.busy_until
                ):
                    # the idle loop's poll of a tick inside the scan runs as the scan returns: it finds
                    # the bytes that arrived during the scan
                    nxt = fw.busy_until
            else:  # spinning on a u16: the next check for both bytes to begin at or after the arrival
                nxt = max(t, fw.busy_until) if fw.busy_from <= t else t
                self._spin_sees(nxt)
            if fw.busy_from <= nxt < fw.busy_until:
                nxt = fw.busy_until
            fw.main_next = nxt
            fw.main_wait = None

    def parser_status(self) -> str:
        """What the parser is doing, in words."""
        p = self.parser
        if p.locked:
            return "locked (pattern with electrode_num 0)"
        if p.cmd is None:
            return "between commands"
        return f"reading {Opcode(p.cmd).name} payload {p.count}/{p.needed}"

    # --- RTOS ticks -----------------------------------------------------------------------------------------

    def _tick_at_or_after(self, t: int) -> int:
        base = self.fw.tick_base + self.model.tick_phase_ns
        if t <= base:
            return base
        tick = self.model.rtos_tick_ns
        return base + -(-(t - base) // tick) * tick

    def _tick_after(self, t: int) -> int:
        return self._tick_at_or_after(t + 1)

    # --- the main loop --------------------------------------------------------------------------------------

    def _main_call(self, tc: int) -> None:
        m = self.model
        fw = self.fw
        p = self.parser
        buf = self.queue.buf
        cpu0, k0 = fw.call if fw.call is not None else (0, 0)
        if fw.period_pending is not None:  # setPeriodUs() as the loop resumes (see _retime_alarm)
            self.registers.timer_alarm_ticks, fw.period_pending = fw.period_pending, None
            self._retime_alarm(tc)
        if fw.check_left_ns is not None:  # the rest of a check a scan pre-empted, then vTaskDelay(1)
            left, fw.check_left_ns = fw.check_left_ns, None
            self._last_check(tc, left)
            return
        checking, fw.checking = fw.checking, False
        if checking and p.cmd is None:  # a read command's last check, after the scan that came first
            fw.call = None
            self._last_check(tc)  # then vTaskDelay(1)
            return
        if fw.held:  # the bytes this call read before the alarm (a 0xF5 goes on with its stack detection)
            buf[0:0] = fw.held
            fw.held = b""
        lead, unit = fw.call_lead if fw.call is not None else p.cmd is None, payload_unit(p.cmd, buf)
        n, outcome = p.plan(buf)
        if n == 0:
            self._read_nothing(tc, outcome, checking, lead, unit)
            return
        hv513 = p.cmd is None and buf[0] == _HV513
        detected = self.parser.hv513_detect() if hv513 else 0
        extra = hv513_count_ns(self.model, detected) if hv513 else 0
        start = tc - cpu0
        ends = [start + t for t in call_reads_ns(m, lead, unit, k0 + n)[k0:]]
        ta = self.next_alarm
        j = n
        if ta < ends[-1] + extra:
            j = taken = 0
            begun = [start + t for t in call_read_starts_ns(m, lead, unit, k0 + n)[k0:]]
            if not hv513:
                # the scan finds stored the reads ended by its alarm; a read under way at the alarm has
                # taken its bytes from the queue (call_read_starts_ns) and stores them after the scan
                j = p.read_before_interrupt(buf, bisect_right(ends, ta))
                taken = p.read_before_interrupt(buf, bisect_left(begun, ta))
        if j < n:
            if j:
                fw.read_starts = begun[:j]
                self._feed(j, ends[:j], None)
            if hv513 and begun[0] < ta:
                # runEtactileKit() reads the 0xF5 before stackSense(): the byte has left the queue when the
                # alarm interrupts its read or the detection, though the reply and the chain's re-init
                # come after it
                fw.held = self.queue.take(1)
            elif taken > j:  # out of the queue, in the firmware's hands until the call resumes
                fw.held = self.queue.take(taken - j)
            if hv513:
                self._init_interrupted(ends[-1] + extra, int(ta), detected)
            self.rec.interrupted_calls += 1
            self.fw.call = (cpu0 + int(ta) - tc, k0 + j)
            self.fw.call_lead = lead
            self.fw.main_next = ta  # the scan at ta pushes this to its end
            self.fw.main_wait = None
            return
        fw.read_starts = [start + t for t in call_read_starts_ns(m, lead, unit, k0 + n)[k0:]]
        if hv513:
            ends[-1] += extra  # the reply is written after the detection
        self._feed(n, [min(e, int(ta)) for e in ends] if ta < ends[-1] else ends, outcome)
        self._end_call(outcome, ends[-1], ends[-1] - start, k0 + n, lead)

    def _feed(self, j: int, ends: list[int], outcome: CallResult | None) -> None:
        """Hand ``j`` bytes to the parser and run one call over them (times: ``ends``)."""
        p = self.parser
        fw = self.fw
        rec = self.rec
        data = self.queue.take(j)
        dev0 = fw.parser_base + p.offset
        if p.cmd is None:
            op = data[0]
            if p.is_command(op):
                host = self._host_of(dev0)
                rep = CommandReport(dev0, host, op, _OPCODE_NAMES[op], sent_us=us_of(self._sent_at(host)))
                rec.cur = rep
                fw.stuck_reported = False
                fw.stuck_at = None
                if op == _PATTERN:
                    regs = self.registers
                    rec.cur_old = bytes(regs.stim_pattern[: regs.electrode_num])
                    rec.cur_written = {}
                    rec.cur_first = {}
                first_ch, skip = 0, 1
            else:
                first_ch, skip = 0, j
        else:
            first_ch, skip = p.count, 0
        if (
            rec.cur is not None
            and rec.cur.opcode == _PATTERN
            and (p.cmd == _PATTERN or (p.cmd is None and data[0] == _PATTERN))
        ):
            rec.cur_written.update(zip(range(first_ch, first_ch + j - skip), ends[skip:j]))
        fw.call_end_ns = ends[-1]
        fw.call_dev_last = dev0 + j - 1
        fw.ticks_before_call = self.registers.timer_alarm_ticks
        p.receive(data)
        r = p.step()
        if p.pending and not p.locked:  # pragma: no cover - the plan hands over whole units only
            raise AssertionError(f"parser left {p.pending} byte(s) unread")
        if outcome is not None and r is not (
            CallResult.PROGRESS if outcome is CallResult.STUCK_U16 else outcome
        ):
            raise AssertionError(f"parser call {r} does not match its plan {outcome}")  # pragma: no cover
        tx = p.take_tx()
        if tx:
            self._send_tx(tx, ends[-1])

    def _send_tx(self, data: bytes, t: int) -> None:
        self.rec.tx_log.append((t / 1000, data))
        last = 0
        for d in self.tx_link.schedule_bursts(data, t, -1):
            self.host.seq += 1
            heapq.heappush(self.host.tx_deliveries, (d.t_ns, self.host.seq, d))
            last = max(last, d.times[-1] if isinstance(d, ByteBurst) else d.t_ns)
        rep = self.rec.last_rep
        if rep is not None and rep.opcode in (Opcode.MEASURE, Opcode.HV513_COUNT) and rep.reply_us is None:
            rep.reply_us = last / 1000

    def _host_replies(self) -> bytearray:
        return self.host.rx

    def _deliveries(self) -> list[tuple[int, int, Scheduled]]:
        return self.host.deliveries

    def _idle(self) -> bool:
        """Nothing left to land or read: the loop waits (for a tick, a u16's byte, a reset), or polls a
        queue that stays empty (a poll the scans pre-empt, so the loop never settles into waiting)."""
        if self.host.deliveries:
            return False
        fw = self.fw
        return fw.main_wait is not None or (
            not self.queue.buf and fw.call is None and not fw.held and fw.period_pending is None
        )

    def _rx_pending(self) -> int:
        return len(self.queue)

    def _collect_tx(self) -> None:
        q = self.host.tx_deliveries
        now = self.now_ns
        while q and q[0][0] <= now:
            _, seq, d = q[0]
            if isinstance(d, ByteBurst):  # its bytes up to now, and before any other reply's
                self.host.rx += d.take(d.end_before(now, next_key(q), seq))
                if len(d):
                    heapq.heapreplace(q, (d.t_ns, seq, d))
                    continue
            else:
                self.host.rx += d.data
            heapq.heappop(q)

    # --- scans ----------------------------------------------------------------------------------------------

    def _scan(self, ta: int, target: int) -> None:
        m = self.model
        regs = self.registers
        cfg = ScanConfig.from_registers(regs)
        tmpl = self.engine.template(cfg, self.chain)
        period = m.alarm_period_ns(regs.timer_alarm_ticks)
        dur = tmpl.duration_ns
        wd = m.watchdog_ns
        torn = self._torn_info(cfg.electrode_num)
        self._check_sense(cfg)
        if wd is not None and dur > wd:
            run = ScanRun(self.rec.scan_index, ta, dur, 1, tmpl, period, dur > period, False, torn, wd)
            self._record(run)
            self._torn_hazard(run)
            self._resolve(ta, tmpl, cut=wd)
            v = regs.voltage
            for ch in range(cfg.electrode_num):
                if tmpl.voltage_at_ns[ch] < wd:
                    v[ch] = int(tmpl.voltages[ch])
            self.hazards.append(
                Hazard(
                    HazardKind.WATCHDOG_RESET,
                    self.parser.offset,
                    {
                        "scan_us": dur / 1000,
                        "watchdog_us": m.watchdog_us,
                        "electrode_num": cfg.electrode_num,
                        "pulse_width": cfg.pulse_width,
                    },
                    (ta + wd) / 1000,
                )
            )
            self._reboot(ta + wd, "watchdog", boot_delay=True)
            return
        overrun = dur > period
        if m.overrun_policy == "immediate" or period == 0:
            stride = period if dur <= period else dur
        else:
            stride = period * max(1, -(-dur // period))
        starved = stride <= dur
        self._resolve(ta, tmpl)
        count = 1
        if tmpl.steady:
            limit = target + 1  # scans starting at or before target
            if self.host.deliveries:
                limit = min(limit, self.host.deliveries[0][0])  # a delivery comes first on a tie
            if self.fw.main_next is not None and not starved:
                limit = min(limit, int(self.fw.main_next) + 1)
            if limit > ta + stride:
                count = max(1, (limit - ta - 1) // stride + 1)
        run = ScanRun(self.rec.scan_index, ta, stride, count, tmpl, period, overrun, starved, torn)
        self._record(run)
        self._torn_hazard(run)
        if overrun:
            detail = {
                "cycles": count,
                "first_cycle": run.first_index,
                "scan_us": dur / 1000,
                "period_us": period / 1000,
                "policy": m.overrun_policy,
                "main_loop_starved": starved,
            }
            self._stretch_hazard(
                Hazard(HazardKind.OVERRUN, self.parser.offset, detail, ta / 1000), (dur, period)
            )
        n = cfg.electrode_num
        regs.voltage[:n] = tmpl.voltages[:n].tolist()  # (one conversion, not one numpy scalar per channel)
        self.chain = tmpl.chain_end
        last = ta + (count - 1) * stride
        self.fw.last_reload = last
        self.fw.busy_from = last
        self.fw.busy_until = last + dur
        if self.fw.main_wait == _WAIT_STUCK:
            self.fw.spin_scanned_ns += count * dur
        self.next_alarm = last + stride
        if self.fw.main_next is not None and self.fw.main_next < self.fw.busy_until:
            self.fw.main_next = self.fw.busy_until
        if starved:  # the loop never resumes: an 0xF6 call's setPeriodUs() never runs (see _retime_alarm)
            self.fw.period_pending = None

    # --- traces ---------------------------------------------------------------------------------------------


def configuration_bytes(cfg: ScanConfig, rate_hz: int | None = None) -> bytes:
    """The command bytes that bring a power-on device to ``cfg`` (``rate_hz`` when the alarm must come
    from a specific rate).

    The order keeps the parser from starving while it is configured: the electrode number first (the
    pattern's length depends on it), the pattern last but one; the frequency first when its period is at
    least the power-on 10 ms (so the long scans of the new settings already run at the slow rate), and
    last otherwise (so a fast rate only starts once everything else has been read)."""
    from tactdeform_hw.protocol import commands as c
    from tactdeform_hw.protocol import firmware_math as fm
    from tactdeform_hw.protocol.constants import POWER_ON_PERIOD_US

    if rate_hz is None:
        rate_hz = _rate_for_ticks(cfg.alarm_ticks)
    if fm.alarm_ticks(fm.period_us_from_rate(rate_hz)) != cfg.alarm_ticks:
        raise ConfigurationError(f"no rate gives alarm_ticks={cfg.alarm_ticks}; pass rate_hz")
    slow = fm.period_us_from_rate(rate_hz) >= POWER_ON_PERIOD_US
    freq = c.encode_frequency(rate_hz)
    out = freq if slow else b""
    out += c.encode_electrode_num(cfg.electrode_num)
    out += c.encode_polarity(cfg.polarity)
    out += c.encode_pulse_height(cfg.pulse_height)
    if cfg.pulse_width:
        out += c.encode_pulse_width(cfg.pulse_width)
    out += c.encode_sense_height(cfg.sense_pulse_height >> 2)
    out += c.encode_sense_width(cfg.sense_pulse_width)
    out += c.encode_discharge(cfg.discharge_time)
    if cfg.electrode_num:
        out += c.encode_pattern(cfg.pattern)
    if not slow:
        out += freq
    return out


def _rate_for_ticks(ticks: int) -> int:
    from tactdeform_hw.protocol import firmware_math as fm

    guess = max(1, min(65535, round(2e6 / ticks))) if ticks else 1
    for r in (guess, guess - 1, guess + 1):
        if 1 <= r <= 65535 and fm.alarm_ticks(fm.period_us_from_rate(r)) == ticks:
            return r
    raise ConfigurationError(f"no rate gives alarm_ticks={ticks}")


def pattern_latency(
    cfg: ScanConfig,
    link: str | LinkModel = "usb",
    *,
    model: TimingModel | None = None,
    phases: int = 16,
    board: str | Board = "compact",
    switching_boards: int = 1,
) -> dict[str, Any]:
    """Latency of one pattern update on a device already running ``cfg``, over ``link``.

    The same pattern (so the scan cost does not change) is written at ``phases`` moments spread over one
    timer period; each run reports the wire time (write → last byte in the queue), the wait for
    the main loop (→ the parser stored the last byte), the wait for the scan (→ channel 0's next pulse)
    and the latency to the first and to the last channel.  Returns min / mean / max of each, in µs
    (``None`` for what never happens: with a starved main loop the bytes arrive — the wire time is
    reported — but the parser never reads them, so the rest is ``None``)."""
    from tactdeform_hw.protocol.commands import encode_pattern

    if cfg.electrode_num == 0:
        raise ConfigurationError("pattern_latency needs at least one electrode")
    if not isinstance(phases, int) or phases < 1:
        raise LimitError("phases", phases, "an integer >= 1")
    m = model if model is not None else DEFAULT_MODEL
    period_us = m.alarm_period_ns(cfg.alarm_ticks) / 1000
    data = encode_pattern(cfg.pattern)
    rows: list[dict[str, float | None]] = []
    link_name = make_link(link).name
    for i in range(phases):
        # each run gets a link in its idle state (a model instance carries its busy/frame state)
        run_link = link if isinstance(link, str) else copy.deepcopy(link)
        emu = TimedEmulator(board, switching_boards, link=run_link, model=m)
        emu.configure(cfg)
        # a low-discrepancy spread over the period (golden ratio), so no phase lines up with the USB
        # frames or the RTOS ticks by construction
        t = 50_000.0 + round(period_us * ((i * 0.6180339887498949) % 1.0), 3)
        rows.append(_latency_run(emu, data, t, t + 4 * period_us + 4 * m.rtos_tick_us + 50_000.0))

    return {
        "link": link_name,
        "electrodes": cfg.electrode_num,
        "bytes": len(data),
        "period_us": period_us,
        "phases": phases,
        "felt": sum(1 for row in rows if row["first_channel_us"] is not None),
        # runs whose first channel was felt from a scan inside the pattern's copy (their scan wait is None)
        "mid_copy": sum(1 for row in rows if row["mid_copy"]),
        **{
            k: _stats(rows, k)
            for k in ("wire_us", "loop_wait_us", "scan_wait_us", "first_channel_us", "last_channel_us")
        },
        "runs": rows,
    }


def _latency_run(emu: TimedEmulator, data: bytes, t: float, until_us: float) -> dict[str, float | None]:
    """Write the pattern ``data`` at ``t``, run to ``until_us`` and say when it was felt."""
    emu.advance_to(t)
    first = emu.host_offset
    emu.write(data, t)
    emu.advance_to(until_us)
    reps = [c for c in emu.commands if c.opcode == Opcode.PATTERN]
    if not reps:
        # never read (a starved main loop): the bytes still crossed the wire unless they were lost
        arrived = emu.arrival_us(first + len(data) - 1)
        return {
            "sent_us": t,
            "wire_us": None if arrived is None else arrived - t,
            "loop_wait_us": None,
            "scan_wait_us": None,
            "mid_copy": False,
            "first_channel_us": None,
            "last_channel_us": None,
        }
    r = reps[-1]
    last = r.last_channel_us
    # the firmware stores a pattern byte by byte as it reads it: a scan that takes the processor during the
    # copy lights channel 0 with its new height before the last byte is stored -- no wait for a scan at all
    scan_wait = r.scan_wait_us
    mid_copy = scan_wait is not None and scan_wait < 0
    return {
        "sent_us": t,
        "wire_us": r.wire_us,
        "loop_wait_us": r.loop_wait_us,
        "scan_wait_us": None if mid_copy else scan_wait,
        "mid_copy": mid_copy,
        "first_channel_us": r.latency_us,
        "last_channel_us": None if last is None or r.sent_us is None else last - r.sent_us,
    }


def _stats(rows: list[dict[str, float | None]], key: str) -> dict[str, float | None]:
    vals: list[float] = [v for row in rows if (v := row[key]) is not None]
    if not vals:
        return {"min": None, "mean": None, "max": None}
    return {"min": min(vals), "mean": sum(vals) / len(vals), "max": max(vals)}


def timed_emulator(
    board: str | Board = "compact",
    switching_boards: int = 1,
    *,
    firmware: str | FirmwareSpec = "v1.2",
    **kwargs: Any,
) -> TimedModel:
    """The timed model of ``firmware`` (its entry in :data:`~..firmware.models.MODELS`: :class:`TimedEmulator`
    for v1.2, :class:`~.model_v2.TimedEmulatorV2` for v2, each with its own scan engine and reports)."""
    return model_entry(firmware).timed(board, switching_boards, **kwargs)
