"""The firmware's serial parser, byte-exact, defects included.

The firmware's main loop calls the parser over and over.  One call (see the protocol reference):

1. no command in progress and a byte waiting → read it as the command; 0xFF/0xF5 reply and return at
   once; an unknown byte returns at once; otherwise the command is now in progress, needing the payload
   size (for 0xFE: ``electrode_num`` *now*);
2. command in progress → consume payload while bytes wait and fewer than needed were read; a u16 is read
   only when both bytes wait (with one waiting the call spins); the completion check is inside that loop,
   so a command that needs 0 bytes never completes (the locked parser);
3. sleep one RTOS tick and return.

:meth:`Parser.step` is exactly one such call and tells the timed model what happened in v1.2's own terms
(:class:`CallResult`: the timed model needs to know a call spins on a half u16); :meth:`Parser.call` is the
same call in the contract every version's parser keeps (:class:`~.contract.CallOutcome`);
:meth:`Parser.run` is the untimed fast path, equivalent to calling ``step`` until nothing changes (a
property test holds the two together).
"""

from __future__ import annotations

from collections.abc import Callable
from enum import Enum

from tactdeform_hw.emulator.firmware.contract import CallOutcome, ParserBase
from tactdeform_hw.emulator.firmware.hazards import Hazard, HazardKind, UnknownRuns
from tactdeform_hw.emulator.firmware.registers import Registers
from tactdeform_hw.protocol import firmware_math as fm
from tactdeform_hw.protocol.commands import encode_measure_reply
from tactdeform_hw.protocol.constants import OUTPUTS_PER_HV513, Opcode
from tactdeform_hw.protocol.firmware import V1_2, FirmwareSpec
from tactdeform_hw.protocol.reader import u16_at

_FIRMWARE = V1_2
_COMMAND_BYTE_MIN = _FIRMWARE.command_byte_min
_MEASURE = int(Opcode.MEASURE)
_PATTERN = int(Opcode.PATTERN)
_HV513 = int(Opcode.HV513_COUNT)
# opcode -> payload bytes needed (pattern resolved at run time); unknown opcodes absent
_SIZE = _FIRMWARE.size_table()
_SPEC = _FIRMWARE.by_opcode


def _stored(op: int, value: int) -> int:
    """The register value the firmware stores for a complete payload (its table's clamp and shift)."""
    v = _SPEC[op].stored(value)
    assert v is not None
    return v


_REGISTER = {
    Opcode.POLARITY: "polarity",
    Opcode.ELECTRODE_NUM: "electrode_num",
    Opcode.PULSE_HEIGHT: "pulse_height",
    Opcode.PULSE_WIDTH: "pulse_width",
    Opcode.SENSE_HEIGHT: "sense_pulse_height",
    Opcode.SENSE_WIDTH: "sense_pulse_width",
    Opcode.DISCHARGE: "discharge_time",
    Opcode.FREQUENCY: "period_us",
}


def register_after(op: int, regs: Registers) -> tuple[str, object]:
    """The register a u8/u16 command writes and the value it holds now (after the command completed:
    clamped, or unchanged where the firmware ignores a 0)."""
    name = _REGISTER[Opcode(op)]
    return name, getattr(regs, name)


class CallResult(Enum):
    """What one parser call did; ``slept`` says whether it ended with the 1 ms RTOS sleep."""

    IDLE = ("idle", True)  # nothing to do
    REPLIED = ("replied", False)  # 0xFF or 0xF5 answered
    IGNORED = ("ignored", False)  # unknown command byte consumed
    PROGRESS = ("progress", True)  # payload consumed, command not complete yet
    COMPLETED = ("completed", True)  # a command with a payload completed
    STUCK_U16 = ("stuck_u16", False)  # spinning on a half-received u16: the call has not returned
    LOCKED = ("locked", True)  # 0xFE with electrode_num 0 in progress forever

    @property
    def slept(self) -> bool:
        return self.value[1]


class Parser(ParserBase, UnknownRuns):
    """Receive buffer + command state + the effects on :class:`Registers`.

    ``hv513_detect`` is the board's detection (called on 0xF5); ``on_hv513_reinit`` lets the scan engine
    clear its chain model; ``on_command`` (optional) is told ``(opcode, value, offset)`` at completion.
    """

    #: the table this parser reads (a class attribute: a parser is copied, its table never is)
    spec: FirmwareSpec = _FIRMWARE

    def __init__(
        self,
        regs: Registers,
        hazards: list[Hazard],
        hv513_detect: Callable[[], int],
        *,
        on_hv513_reinit: Callable[[], None] | None = None,
        on_command: Callable[[int, object, int], None] | None = None,
    ) -> None:
        super().__init__(hazards, hv513_detect, on_hv513_reinit, on_command)
        self.regs = regs
        self.cmd: int | None = None
        self.cmd_offset = 0
        self.needed = 0
        self.count = 0
        self.locked = False
        self._unknown_start = -1  # offset where the current run of unknown bytes began
        self._unknown_len = 0
        self._u16_reported_at = -1
        self._unread_reported_to = 0  # absolute offset up to which unread-while-locked bytes were reported

    # --- buffer -------------------------------------------------------------------------------------------

    def receive(self, data: bytes) -> int:
        """Queue an arrival whole (the 256-byte queue and its losses are the timed model's); returns 0,
        the bytes dropped."""
        self._drop_read()
        self.rx += data
        return 0

    @property
    def dropped(self) -> int:
        """Always 0: this parser's buffer is unbounded; the receive queue's losses are the timed
        model's."""
        return 0

    @property
    def processing(self) -> bool:
        """A command's byte was read and its payload is not complete (or never will be: locked)."""
        return self.cmd is not None

    # --- what the next call will do -------------------------------------------------------------------------

    def is_command(self, byte: int) -> bool:
        """Whether the firmware reads ``byte`` as a command it knows (else it skips it)."""
        return byte in _SIZE

    def plan(self, waiting: bytes | bytearray) -> tuple[int, CallResult]:
        """What :meth:`call` would do if ``waiting`` (bytes not yet handed to the parser) were in its
        buffer: how many of them it reads, and how it ends.  The timed model asks this before a call, to
        time each byte read and to find where a scan interrupts the call; :meth:`call` on exactly those
        bytes then does it (``STUCK_U16`` becomes ``PROGRESS``: the half u16 stays waiting).  The premise
        is the timed model's: the parser holds no byte it has not read (bytes wait in the receive queue
        until a call reads them)."""
        avail = len(waiting)
        if self.cmd is None:
            if avail == 0:
                return 0, CallResult.IDLE
            size = _SIZE.get(waiting[0])
            if size is None:
                return 1, CallResult.IGNORED
            if size == 0:
                return 1, CallResult.REPLIED
            if size < 0:
                size = self.regs.electrode_num
                if size == 0:
                    return 1, CallResult.LOCKED
                take = min(avail - 1, size)
                return 1 + take, CallResult.COMPLETED if take == size else CallResult.PROGRESS
            if size == 1:
                return (2, CallResult.COMPLETED) if avail >= 2 else (1, CallResult.PROGRESS)
            if avail >= 3:
                return 3, CallResult.COMPLETED
            return 1, CallResult.STUCK_U16 if avail == 2 else CallResult.PROGRESS
        if self.locked:
            return 0, CallResult.LOCKED
        if self.cmd == _PATTERN:
            take = min(avail, self.needed - self.count)
            if take == 0:
                return 0, CallResult.PROGRESS
            return take, CallResult.COMPLETED if self.count + take == self.needed else CallResult.PROGRESS
        if self.needed == 1:
            return (1, CallResult.COMPLETED) if avail else (0, CallResult.PROGRESS)
        if avail >= 2:
            return 2, CallResult.COMPLETED
        return 0, CallResult.STUCK_U16 if avail == 1 else CallResult.PROGRESS

    def read_before_interrupt(self, waiting: bytes | bytearray, j: int) -> int:
        """Of the bytes a call reads from ``waiting``, how many it has taken when an interrupt comes after
        its ``j``-th byte time: a u16 is read only when both bytes wait, so it is taken whole or not at
        all."""
        if self.cmd is None:
            if j == 2 and _SIZE.get(waiting[0]) == 2:
                return 1
        elif self.cmd != _PATTERN and self.needed == 2 and j == 1:
            return 0
        return j

    # --- one firmware call ---------------------------------------------------------------------------------

    def call(self, now_us: int) -> CallOutcome:
        """One call in the contract all versions keep; v1.2's parser reads no timer (``now_us`` unused)."""
        before, wrote = self.offset, len(self.tx)
        result = self.step()
        return CallOutcome(self.offset - before, len(self.tx) - wrote, result.slept)

    def step(self) -> CallResult:
        """One call, and what it did in v1.2's terms (the timed model's)."""
        rx = self.rx
        if self.cmd is None:
            if self.pos >= len(rx):
                return CallResult.IDLE
            op = rx[self.pos]
            self.pos += 1
            size = _SIZE.get(op)
            if size is None:
                self._note_unknown(self.base + self.pos - 1)
                return CallResult.IGNORED
            self._flush_unknown()
            if size == 0:
                self._reply(op, self.base + self.pos - 1)
                return CallResult.REPLIED
            self._start(op, size, self.base + self.pos - 1)
        return self._consume_payload()

    def ignore_unknown(self, count: int) -> None:
        """``count`` calls that each read one non-command byte and ignore it, in one go: what ``count``
        calls of :meth:`step` do on them (the timed model's fast path for a resync's zeros)."""
        start, end = self.pos, self.pos + count
        if self.cmd is not None or end > len(self.rx) or not _SIZE.keys().isdisjoint(self.rx[start:end]):
            raise AssertionError("ignore_unknown: not a run of non-command bytes between commands")
        if count > 0:
            self._note_unknown(self.base + start)
            self._unknown_len += count - 1
            self.pos = end

    # --- untimed fast path ---------------------------------------------------------------------------------

    def poll_until(self, to_us: int, settle: bool) -> None:
        """Nothing: v1.2's parser has no timer, so polls without an arrival change nothing."""

    def note_pending(self, now_us: int) -> None:
        """Nothing: a v1.2 command waits for its payload forever; :meth:`run` records a half u16 and a
        locked parser itself."""

    def run(self, now_us: int = 0) -> None:
        """Consume everything the firmware would consume from what is waiting (no timing; ``now_us``
        unused: v1.2's parser reads no timer)."""
        rx = self.rx
        n = len(rx)
        while True:
            if self.cmd is not None:
                r = self._consume_payload()
                if r is not CallResult.COMPLETED:
                    break
                continue
            pos = self.pos
            if pos >= n:
                break
            op = rx[pos]
            size = _SIZE.get(op)
            if size is None:
                # a run of unknown bytes: skip it in one go, one hazard for the run
                j = pos + 1
                while j < n and rx[j] < _COMMAND_BYTE_MIN:
                    j += 1
                if self._unknown_len == 0:
                    self._unknown_start = self.base + pos
                self._unknown_len += j - pos
                self.pos = j
                continue
            self._flush_unknown()
            self.pos = pos + 1
            if size == 0:
                self._reply(op, self.base + pos)
            else:
                self._start(op, size, self.base + pos)
        self._flush_unknown()
        if self.locked:
            self._report_unread()
        elif self.cmd is not None and self.needed == 2 and self.count == 0 and self.pending == 1:
            at = self.offset
            if self._u16_reported_at != at:
                self._u16_reported_at = at
                self.hazards.append(
                    Hazard(
                        HazardKind.U16_WAITING,
                        at,
                        {"command": Opcode(self.cmd).name, "low_byte": self.rx[self.pos]},
                    )
                )

    # --- pieces --------------------------------------------------------------------------------------------

    def _report_unread(self) -> None:
        """Every byte a locked parser will never read is reported once, by offset."""
        end = self.base + len(self.rx)
        start = max(self._unread_reported_to, self.offset)
        if end > start:
            self.hazards.append(
                Hazard(HazardKind.UNREAD_WHILE_LOCKED, start, {"bytes": end - start, "pending": self.pending})
            )
            self._unread_reported_to = end

    def _reply(self, op: int, offset: int) -> None:
        regs = self.regs
        if op == _MEASURE:
            n = regs.electrode_num
            self.tx += encode_measure_reply(regs.voltage[:n])
        else:  # 0xF5
            regs.hv513_num = self.hv513_detect()
            self.tx.append(regs.hv513_num & 0xFF)
            self.hazards.append(Hazard(HazardKind.HV513_REINIT, offset, {"hv513_num": regs.hv513_num}))
            if self.on_hv513_reinit is not None:
                self.on_hv513_reinit()
        if self.on_command is not None:
            self.on_command(op, None, offset)

    def _start(self, op: int, size: int, offset: int) -> None:
        self.cmd = op
        self.cmd_offset = offset
        self.count = 0
        if size < 0:  # pattern: electrode_num at the moment the command byte is read
            size = self.regs.electrode_num
            if size == 0:
                self.locked = True
                self.hazards.append(
                    Hazard(
                        HazardKind.PARSER_LOCKED,
                        offset,
                        {"reason": "pattern command with electrode_num 0; the parser never reads again"},
                    )
                )
        self.needed = size

    def _consume_payload(self) -> CallResult:
        op = self.cmd
        assert op is not None
        rx = self.rx
        avail = len(rx) - self.pos
        if op == _PATTERN:
            if self.needed == 0:
                self._report_unread()
                return CallResult.LOCKED
            take = min(avail, self.needed - self.count)
            if take:
                start = self.count
                payload = rx[self.pos : self.pos + take]
                self.regs.stim_pattern[start : start + take] = payload
                if max(payload) >= _COMMAND_BYTE_MIN:
                    i = next(i for i, b in enumerate(payload) if b >= _COMMAND_BYTE_MIN)
                    self._hazard(
                        HazardKind.PATTERN_HOLDS_COMMAND_BYTE,
                        self.base + self.pos + i,
                        command_offset=self.cmd_offset,
                        channel=start + i,
                        value=payload[i],
                        command="PATTERN",
                        swallowed=Opcode(payload[i]).name,
                        register=f"stim_pattern[{start + i}]",
                        stored=payload[i],
                    )
                self.pos += take
                self.count += take
            if self.count == self.needed:
                self._complete(op, None)
                return CallResult.COMPLETED
            return CallResult.PROGRESS
        if self.needed == 1:
            if avail < 1:
                return CallResult.PROGRESS
            value = rx[self.pos]
            self.pos += 1
        else:
            if avail < 2:
                return CallResult.STUCK_U16 if avail == 1 else CallResult.PROGRESS
            value = u16_at(rx, self.pos)
            self.pos += 2
        cmd_offset = self.cmd_offset
        self._complete(op, value)
        if rx[self.pos - 1] >= _COMMAND_BYTE_MIN or (
            self.needed == 2 and rx[self.pos - 2] >= _COMMAND_BYTE_MIN
        ):
            self._swallowed(op, cmd_offset, self.needed)
        return CallResult.COMPLETED

    def _swallowed(self, op: int, cmd_offset: int, size: int) -> None:
        """A command byte read as the payload of ``op``: the host meant a command, the firmware stored a
        value (``fb`` then ``fc 08`` sets pulse height 0x08FC = 2300)."""
        first = self.pos - size
        i = next(k for k in range(size) if self.rx[first + k] >= _COMMAND_BYTE_MIN)
        meant = None if self.meant_as_command is None else self.meant_as_command(self.base + first + i)
        field, stored = register_after(op, self.regs)
        value = self.rx[first] if size == 1 else u16_at(self.rx, first)
        self._hazard(
            HazardKind.PAYLOAD_HOLDS_COMMAND_BYTE,
            self.base + first + i,
            command=Opcode(op).name,
            command_offset=cmd_offset,
            swallowed=Opcode(self.rx[first + i]).name,
            payload_byte=i,
            value=value,
            register=field,
            stored=stored,
            meant_as_command=meant,
        )

    def _complete(self, op: int, value: int | None) -> None:
        regs = self.regs
        offset = self.cmd_offset
        self.cmd = None
        if op == _PATTERN:
            pass
        elif value is None:  # pragma: no cover - every other command has a value
            raise AssertionError(op)
        elif op == Opcode.POLARITY:
            regs.polarity = _stored(op, value)
            if value > 1:
                self._hazard(HazardKind.CLAMPED, offset, field="polarity", value=value, stored=1)
        elif op == Opcode.ELECTRODE_NUM:
            old = regs.electrode_num
            regs.electrode_num = value
            if value > old:
                stale = {ch: regs.stim_pattern[ch] for ch in range(old, value) if regs.stim_pattern[ch]}
                if stale:
                    self._hazard(HazardKind.STALE_CHANNELS, offset, old=old, new=value, channels=stale)
            if value > regs.hv513_num * OUTPUTS_PER_HV513:
                self._hazard(
                    HazardKind.CHANNELS_BEYOND_HV513,
                    offset,
                    electrode_num=value,
                    hv513_num=regs.hv513_num,
                    channels_driven=regs.hv513_num * OUTPUTS_PER_HV513,
                )
        elif op == Opcode.PULSE_HEIGHT:
            regs.pulse_height = _stored(op, value)
            if value > regs.pulse_height:
                self._hazard(
                    HazardKind.CLAMPED, offset, field="pulse_height", value=value, stored=regs.pulse_height
                )
        elif op == Opcode.PULSE_WIDTH:
            if _SPEC[op].stored(value) is not None:
                regs.pulse_width = value
            else:
                self._hazard(HazardKind.IGNORED_ZERO, offset, field="pulse_width")
        elif op == Opcode.SENSE_HEIGHT:
            regs.sense_pulse_height = _stored(op, value)
        elif op == Opcode.SENSE_WIDTH:
            regs.sense_pulse_width = value
        elif op == Opcode.DISCHARGE:
            regs.discharge_time = value
        elif op == Opcode.FREQUENCY:
            if _SPEC[op].stored(value) is not None:
                regs.period_us = fm.period_us_from_rate(value)
                regs.timer_alarm_ticks = fm.alarm_ticks(regs.period_us)
            else:
                self._hazard(HazardKind.IGNORED_ZERO, offset, field="frequency")
        if self.on_command is not None:
            self.on_command(op, value, offset)

    def _hazard(self, kind: HazardKind, offset: int, **detail: object) -> None:
        self.hazards.append(Hazard(kind, offset, dict(detail)))
