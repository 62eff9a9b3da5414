"""The v2 firmware's command parser (upstream 71adee21), byte-exact, defects included.

v2 parses a command only when its whole payload is queued, so a cut command never changes anything; it
stays pending and swallows whatever is sent next (the desynchronisation of v1.2, now bounded): if the
payload has not completed 2 s after the command byte was read, the next poll discards *every* queued
byte and the parser is free again.  The loop sleeps one RTOS tick only when a call made no progress.

Time is the firmware's command timer (Timer2, 1 µs ticks) and enters through :meth:`ParserV2.call`'s
``now_us``: the parser reads it when a payload command starts and while one is pending, nowhere else.

The receive queue is the ESP32-S3 HWCDC one: 1024 bytes, each USB packet (≤ 64 bytes) copied byte by
byte, the rest of a packet dropped silently at the first byte that does not fit.

A call goes through ``runEtactileKit``'s read points (:class:`ReadPoint`: its ``Serial.available`` checks,
the command byte's read, each payload read, its timer reads and reply writes), the places where an
interrupt takes the processor.  A timed model that knows an interrupt there never gives it back (scans
that overrun starve the loop) passes ``reach`` and the call stops there, leaving the queue, the registers
and the parser exactly as the firmware leaves them (:attr:`ParserV2.cut`).
"""

from __future__ import annotations

import re
from collections.abc import Callable
from dataclasses import dataclass
from enum import Enum
from functools import lru_cache

from tactdeform_hw.emulator.firmware.contract import CallOutcome, ParserBase
from tactdeform_hw.emulator.firmware.hazards import Hazard, HazardKind, UnknownRuns
from tactdeform_hw.emulator.firmware.registers import RegistersV2
from tactdeform_hw.protocol import firmware_math as fm
from tactdeform_hw.protocol.commands import encode_measure_reply
from tactdeform_hw.protocol.constants import OUTPUTS_PER_HV513
from tactdeform_hw.protocol.firmware import V2, CommandSpec, FirmwareSpec


@lru_cache(maxsize=8)
def _unknown_run(spec: FirmwareSpec) -> re.Pattern[bytes]:
    """Matches a run of bytes no command of ``spec`` starts with."""
    unknown = [b for b in range(256) if b not in spec.by_opcode]
    return re.compile(b"[" + b"".join(b"\\x%02x" % b for b in unknown) + b"]*")


class ReadPoint(Enum):
    """A call into the Arduino core inside ``runEtactileKit`` (etk.cpp:154-277): where the host build runs a
    due interrupt, before the call does anything.  What the point does happens only if the processor comes
    back."""

    #: ``isDataAvailable()``: once before a command byte, once before a payload (``call_ns`` each)
    AVAILABLE = "Serial.available"
    #: ``readInt_8()``/``readInt_16()``: the command byte, a payload, one pattern element (``byte_ns`` a byte)
    READ = "Serial.read"
    #: ``timerRead(Timer2)`` (a command's start, the timeout check) or 0xF5's ``timerAlarmDisable`` (free)
    TIMER = "timer"
    #: ``writeInt_8()``/``writeBytes()``: a reply (free; 0xFF has set ``SendingVoltages`` before it)
    WRITE = "Serial.write"


#: Asked before each of a call's read points with the point and the bytes it reads: False when an interrupt
#: taken there never gives the processor back, so the call stops before the point does anything.
Reach = Callable[[ReadPoint, int], bool]


@dataclass(frozen=True)
class CallCut:
    """Where a call stopped for good (:meth:`ParserV2.call`'s ``reach`` said no).

    ``op``: the command byte the call had read (None: it read none, so that byte is still queued);
    ``torn``: a pattern cut inside its copy, as (elements stored, the clamped heights it had still to
    store), else None."""

    point: ReadPoint
    op: int | None
    torn: tuple[int, tuple[int, ...]] | None = None


def _always(point: ReadPoint, nbytes: int) -> bool:
    """No interrupt keeps the processor: every read point is passed."""
    return True


class ParserV2(ParserBase, UnknownRuns):
    """Receive queue + the parser's static state + the effects on :class:`RegistersV2`.

    ``hv513_detect`` is the board's stack sensing (0xF5); ``on_hv513_reinit`` tells a scan model that
    ``hv513Init`` re-clocked the chain; ``on_command`` is told ``(opcode, value, offset)`` when a
    command takes effect (value: the int payload, the clamped height list for 0xFE, None for replies).
    """

    def __init__(
        self,
        regs: RegistersV2,
        hazards: list[Hazard],
        hv513_detect: Callable[[], int],
        *,
        spec: FirmwareSpec = V2,
        on_hv513_reinit: Callable[[], None] | None = None,
        on_command: Callable[[int, object, int], None] | None = None,
    ) -> None:
        super().__init__(hazards, hv513_detect, on_hv513_reinit, on_command)
        self.regs = regs
        self.spec = spec
        if spec.command_timeout_us is None:
            raise ValueError(f"firmware {spec.name} has no command timeout: it is not parsed by ParserV2")
        #: A command not complete this long after its byte was read is discarded (the table's value).
        self.timeout_us: int = spec.command_timeout_us
        self.dropped = 0
        self.processing = False
        self.required = 0
        self.command = 0
        self.command_offset = 0
        self.command_start_us = 0
        self._unknown_start = -1
        self._unknown_len = 0
        self._sense_all = False
        #: ``Serial.available()`` calls the last :meth:`call` made: 2 when it read a command byte that takes
        #: a payload (runEtactileKit checks the queue again for the payload in the same call), else 1
        self.checks = 1
        #: Where the last :meth:`call` stopped for good (None: it ran to its end)
        self.cut: CallCut | None = None

    # --- the receive queue -----------------------------------------------------------------------------

    def receive(self, data: bytes, unread: int = 0) -> int:
        """Queue one arrival packet by packet; return the bytes dropped because the queue was full.
        ``unread``: bytes the parser has taken but the firmware has not read yet when this arrives (a
        timed model's call takes them at its start): they still fill the firmware's queue."""
        self._drop_read()
        capacity = self.spec.rx_queue_bytes
        packet = self.spec.usb_packet_bytes
        lost = 0
        for start in range(0, len(data), packet):
            chunk = data[start : start + packet]
            free = capacity - unread - self.pending
            if free >= len(chunk):
                self.rx += chunk
                continue
            if free > 0:
                self.rx += chunk[:free]
            cut = len(chunk) - max(free, 0)
            lost += cut
            self.hazards.append(
                Hazard(
                    HazardKind.QUEUE_OVERFLOW,
                    self.base + len(self.rx),
                    {"dropped": cut, "queue_size": capacity},
                )
            )
        self.dropped += lost
        return lost

    # --- one main-loop call ----------------------------------------------------------------------------

    def call(self, now_us: int, reach: Reach | None = None) -> CallOutcome:
        """Exactly one ``runEtactileKit()`` call at command-timer time ``now_us``.

        ``reach`` is asked before each read point (:class:`ReadPoint`) in the firmware's order; where it
        says no, the call stops before that point: what it read and stored so far stays (a pattern keeps
        the elements copied), nothing after happens (no byte read, no register stored, no reply, the
        command not ended), and :attr:`cut` says where.  Without it the call runs to its end."""
        go = reach if reach is not None else _always
        self.cut = None
        start = self.pos
        wrote_before = len(self.tx)
        made_progress = False
        self.checks = 1
        if not self.processing:
            if not go(ReadPoint.AVAILABLE, 0):
                return self._stop(ReadPoint.AVAILABLE, None, start, wrote_before)
            if self.pending > 0:
                if not go(ReadPoint.READ, 1):
                    return self._stop(ReadPoint.READ, None, start, wrote_before)
                op = self.rx[self.pos]
                at = self.offset
                self.pos += 1
                made_progress = True
                spec = self.spec.by_opcode.get(op)
                if spec is None or spec.kind is None:
                    if spec is None:
                        self._note_unknown(at)
                    else:
                        self._flush_unknown()
                        point = self._reply(spec, at, go)
                        if point is not None:
                            return self._stop(point, op, start, wrote_before)
                    return CallOutcome(self.pos - start, len(self.tx) - wrote_before, False)
                self._flush_unknown()
                self.command = op
                self.command_offset = at
                self.required = self.spec.size_of(op, self.regs.electrode_num) or 0
                self.processing = True
                if not go(ReadPoint.TIMER, 0):  # commandStartUs = timerRead(Timer2)
                    return self._stop(ReadPoint.TIMER, op, start, wrote_before)
                self.command_start_us = now_us
                self.checks = 2
        if self.processing:
            read_op = self.command if self.pos > start else None
            if not go(ReadPoint.AVAILABLE, 0):
                return self._stop(ReadPoint.AVAILABLE, read_op, start, wrote_before)
            if self.pending >= self.required:
                done, torn = self._apply(go)
                if not done:
                    return self._stop(ReadPoint.READ, read_op, start, wrote_before, torn)
                made_progress = True
            else:
                # the timeout check reads Timer2; its discard loop reads every queued byte (one read point:
                # the timing model counts a byte time each, as it does for the discard)
                if not go(ReadPoint.TIMER, 0):
                    return self._stop(ReadPoint.TIMER, read_op, start, wrote_before)
                if now_us - self.command_start_us > self.timeout_us:
                    if not go(ReadPoint.READ, self.pending):
                        return self._stop(ReadPoint.READ, read_op, start, wrote_before)
                    self._time_out(now_us)
        return CallOutcome(self.pos - start, len(self.tx) - wrote_before, not made_progress)

    def _stop(
        self,
        point: ReadPoint,
        op: int | None,
        start: int,
        wrote_before: int,
        torn: tuple[int, tuple[int, ...]] | None = None,
    ) -> CallOutcome:
        """The call stops at ``point`` for good: say where, and what it had read and written by then."""
        self.cut = CallCut(point, op, torn)
        return CallOutcome(self.pos - start, len(self.tx) - wrote_before, False)

    def drop_unstored(self, count: int) -> None:
        """After a call stopped for good inside a read (:attr:`cut`): the ``count`` bytes that read had
        taken from the queue before the interrupt that never gave the processor back.  They have left the
        queue, and nothing stores them."""
        if self.cut is None or not 0 <= count <= self.pending:
            raise AssertionError(f"drop_unstored({count}): no read under way with that many bytes queued")
        self.pos += count

    def _time_out(self, now_us: int) -> None:
        """The payload did not complete within the timeout: every queued byte is discarded."""
        discarded = self.pending
        self.hazards.append(
            Hazard(
                HazardKind.COMMAND_TIMEOUT,
                self.command_offset,
                {
                    "command": self.spec.command(self.command).name,
                    "needed": self.required,
                    "discarded": discarded,
                    "discarded_hex": bytes(self.rx[self.pos :]).hex(),
                },
                float(now_us),
            )
        )
        self.pos = len(self.rx)
        self.processing = False
        self.command = 0

    def unknown_run(self) -> int:
        """How many calls in a row would each read one unknown byte and skip it: the queued bytes, from
        the next one, that no command starts with (0 while a command waits for its payload)."""
        if self.processing:
            return 0
        m = _unknown_run(self.spec).match(self.rx, self.pos)
        return m.end() - self.pos if m is not None else 0

    def skip_unknown(self, count: int) -> None:
        """``count`` calls that each read one unknown byte and skip it, in one go: what ``count`` calls of
        :meth:`call` do on them (the timed model's fast path for the zeros of a flush)."""
        if count > self.unknown_run():
            raise AssertionError(f"skip_unknown({count}): not a run of unknown bytes between commands")
        if count > 0:
            self._note_unknown(self.offset)
            self._unknown_len += count - 1
            self.pos += count

    def run(self, now_us: int) -> None:
        """Call until a call neither consumes nor writes a byte (the golden vectors' driving rule)."""
        while not self.call(now_us).quiet:
            pass
        self._flush_unknown()

    def poll_until(self, to_us: int, settle: bool) -> None:
        """The idle polls up to ``to_us - 1`` (so a cut command times out before an arrival at ``to_us``
        if it would have), and with ``settle`` the poll at ``to_us``."""
        self.run(to_us - 1)
        if settle:
            self.run(to_us)

    def note_pending(self, now_us: int) -> None:
        """A command left waiting for its payload is a hazard on v2: the 2 s timeout will discard it with
        whatever the host sends meanwhile.  Recorded once per command."""
        if not self.processing:
            return
        at = self.command_offset
        last = self.hazards[-1] if self.hazards else None
        if last is not None and last.kind is HazardKind.COMMAND_PENDING and last.offset == at:
            return
        self.hazards.append(
            Hazard(
                HazardKind.COMMAND_PENDING,
                at,
                {
                    "command": self.spec.command(self.command).name,
                    "needed": self.required,
                    "queued": self.pending,
                },
                float(now_us),
            )
        )

    # --- pieces ----------------------------------------------------------------------------------------

    def _reply(self, spec: CommandSpec, offset: int, go: Reach) -> ReadPoint | None:
        """Answer a reply command; the read point where the call stopped before answering (None: it
        answered).  0xF5 disables the stimulation alarm first (its only read point: no interrupt comes
        while it senses and writes); 0xFF and 0xF4 reach the write."""
        regs = self.regs
        op = spec.opcode
        if spec.reply == "measure":
            if not go(ReadPoint.WRITE, 0):
                return ReadPoint.WRITE
            self.tx += encode_measure_reply(regs.voltage[: regs.electrode_num])
        elif spec.reply == "hv513":
            if not go(ReadPoint.TIMER, 0):
                return ReadPoint.TIMER
            regs.hv513_num = self.hv513_detect()
            self.tx.append(regs.hv513_num & 0xFF)
            self.hazards.append(
                Hazard(
                    HazardKind.HV513_REINIT,
                    offset,
                    {"hv513_num": regs.hv513_num, "timer_paused": self.spec.hv513_pauses_timer},
                )
            )
            if self.on_hv513_reinit is not None:
                self.on_hv513_reinit()
        else:  # sync check
            if not go(ReadPoint.WRITE, 0):
                return ReadPoint.WRITE
            self.tx.append(regs.electrode_num & 0xFF)
        if self.on_command is not None:
            self.on_command(op, None, offset)
        return None

    def _hazard(self, kind: HazardKind, **detail: object) -> None:
        self.hazards.append(Hazard(kind, self.command_offset, dict(detail)))

    def _apply(self, go: Reach) -> tuple[bool, tuple[int, tuple[int, ...]] | None]:
        """The whole payload is queued: read it, apply it by the table, end the command.  (False, torn)
        when the call stopped at a read: before a u8/u16 payload nothing is read; inside a pattern the
        elements read so far are stored (``readInt_16`` then the store, element by element), ``torn``
        giving how many and the heights the rest would have had."""
        cmd = self.spec.command(self.command)
        if cmd.kind == "pattern":
            return self._apply_pattern(cmd, go)
        if not go(ReadPoint.READ, self.required):
            return False, None
        payload = bytes(self.rx[self.pos : self.pos + self.required])
        self.pos += self.required
        if payload and max(payload) >= self.spec.command_byte_min:
            self._hazard(HazardKind.PAYLOAD_HOLDS_COMMAND_BYTE, command=cmd.name, payload=payload.hex())
        ivalue = int.from_bytes(payload, "little")
        if not self._store(cmd, ivalue, go):
            return False, None
        self.processing = False
        self.command = 0
        self._check_sense_all()
        if self.on_command is not None:
            self.on_command(cmd.opcode, ivalue, self.command_offset)
        return True, None

    def _apply_pattern(self, cmd: CommandSpec, go: Reach) -> tuple[bool, tuple[int, tuple[int, ...]] | None]:
        """0xFE's copy loop: one ``readInt_16`` per element, each stored clamped as it is read."""
        regs = self.regs
        limit = cmd.max_value if cmd.max_value is not None else self.spec.dac_max_code
        width = self.spec.pattern_bytes_per_electrode
        payload = bytes(self.rx[self.pos : self.pos + self.required])
        raw = [int.from_bytes(payload[i : i + width], "little") for i in range(0, len(payload), width)]
        copied = len(raw)
        if go is not _always:
            copied = next((k for k in range(len(raw)) if not go(ReadPoint.READ, width)), len(raw))
        done = copied == len(raw)
        self.pos += copied * width
        if done:
            self.processing = False
            self.command = 0
        heights = [min(v, limit) for v in raw]
        regs.stim_pattern[:copied] = heights[:copied]
        over = {ch: v for ch, v in enumerate(raw[:copied]) if v > limit}
        if over:
            self._hazard(HazardKind.CLAMPED, field="stim_pattern", values=over, stored=limit)
        self._check_sense_all()
        if not done:
            return False, (copied, tuple(heights[copied:]))
        if self.on_command is not None:
            self.on_command(cmd.opcode, heights, self.command_offset)
        return True, None

    def _check_sense_all(self) -> None:
        """Mode 2 gives every scanned channel the sense pulse: with a non-zero sense height, channels whose
        height is 0 still carry current.  Recorded when the registers enter that state."""
        regs = self.regs
        n = regs.electrode_num
        zeros = [ch for ch in range(n) if regs.stim_pattern[ch] == 0]
        live = regs.stim_mode == 2 and regs.sense_pulse_height > 0 and bool(zeros)
        if live and not self._sense_all:
            self._hazard(
                HazardKind.MODE_SENSE_ALL,
                channels=zeros,
                sense_code=regs.sense_pulse_height,
                sense_width_us=regs.sense_pulse_width,
            )
        self._sense_all = live

    def _store(self, cmd: CommandSpec, value: int, go: Reach) -> bool:
        """Store a u8/u16 payload by the table.  False when the call stopped at 0xF6's ``setPeriodUs``
        (its ``timerAlarmDisable``, a read point after ``StimulationTimePeriod`` is stored): the period
        is new, the alarm still the old one."""
        regs = self.regs
        stored = cmd.stored(value)
        if stored is None:
            self._hazard(HazardKind.IGNORED_ZERO, field=cmd.register)
            return True
        if stored != value << cmd.shift:
            self._hazard(HazardKind.CLAMPED, field=cmd.register, value=value, stored=stored)
        if cmd.register == "frequency":
            regs.period_us = fm.period_us_from_rate_double(value)
            if not go(ReadPoint.TIMER, 0):
                return False
            regs.timer_alarm_ticks = fm.alarm_ticks(regs.period_us)
            return True
        if cmd.register == "electrode_num":
            old = regs.electrode_num
            if stored > old:
                stale = {ch: regs.stim_pattern[ch] for ch in range(old, stored) if regs.stim_pattern[ch]}
                if stale:
                    self._hazard(HazardKind.STALE_CHANNELS, old=old, new=stored, channels=stale)
            driven = regs.hv513_num * OUTPUTS_PER_HV513
            if stored > driven:
                self._hazard(
                    HazardKind.CHANNELS_BEYOND_HV513,
                    electrode_num=stored,
                    hv513_num=regs.hv513_num,
                    channels_driven=driven,
                )
        elif cmd.register == "pulse_width" and stored < self.spec.timing.pulse_wait_offset_us:
            self._hazard(HazardKind.SHORT_PULSE_WIDTH, field="pulse_width", value=stored)
        assert cmd.register is not None
        setattr(regs, cmd.register, stored)
        return True

    @property
    def command_in_progress(self) -> bool:
        return self.processing

    @property
    def locked(self) -> bool:
        """Never: v2 completes a pattern with electrode_num 0 at once."""
        return False
