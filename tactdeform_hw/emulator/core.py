"""The emulated eTactileKit device: parser, registers and board behind one byte-stream API."""

from __future__ import annotations

from collections.abc import Callable

from tactdeform_hw.emulator.firmware.board import Board
from tactdeform_hw.emulator.firmware.contract import CallOutcome, FirmwareParser
from tactdeform_hw.emulator.firmware.hazards import Hazard
from tactdeform_hw.emulator.firmware.models import BoardRegisters, model_entry
from tactdeform_hw.protocol.firmware import FirmwareSpec
from tactdeform_hw.protocol.state import BoardState

from ..errors import ConfigurationError


class Emulator:
    """The firmware's observable behaviour, untimed: every byte fed reaches the parser at once.

    ``firmware`` picks the version (a name such as "v1.2", the default, or "v2", or its table): its
    registers and parser come from :data:`~.firmware.models.MODELS`.  Where a version's parser reads a
    timer (v2's 2 s command timeout; its 1024-byte queue is the parser's, since v2's state depends on
    it), time enters through ``feed(..., at_us=)`` and :meth:`advance`.

    The 256-byte receive queue, its losses and all timing belong to the timed model
    (:mod:`tactdeform_hw.emulator.timed.model_v1_2`), which drives the same :class:`Parser` one firmware call
    at a
    time.  ``scan`` is the seam for the stimulation scan: when set, it is called with this emulator to
    refresh ``registers.voltage`` before a measure reply is written.
    """

    def __init__(
        self,
        board: str | Board = "compact",
        switching_boards: int = 1,
        *,
        stack_reading: float | None = None,
        firmware: str | FirmwareSpec = "v1.2",
    ) -> None:
        self.entry = model_entry(firmware)
        self.firmware: FirmwareSpec = self.entry.spec
        self.board = board if isinstance(board, Board) else Board(board, switching_boards, stack_reading)
        self.hazards: list[Hazard] = []
        self.scan: Callable[[Emulator], None] | None = None
        #: handed to every parser this emulator makes (see ``Parser.meant_as_command``)
        self.meant_as_command: Callable[[int], bool] | None = None
        self._power_on()

    def _power_on(self) -> None:
        #: v2's command timer (Timer2, µs) at the last event; v1.2 keeps it only for the API's sake.
        self.now_us = 0
        #: Bytes that reached the board since power-on (0: no program can have left a command in its parser).
        self.received_bytes = 0
        self.registers: BoardRegisters
        self.parser: FirmwareParser
        self.registers, self.parser = self.entry.parts(self.hazards, self.board.detect_hv513)
        self._arrival_start = -1
        # without a host's own intent, a byte that starts an arrival is taken as meant for a command (a
        # driver writes whole commands; a value byte >= 0xF5 inside one is the value it meant)
        self.parser.meant_as_command = self.meant_as_command or self._starts_arrival

    def _starts_arrival(self, offset: int) -> bool:
        return offset == self._arrival_start

    def reset(self) -> None:
        """Power cycle: registers, pattern buffer, receive buffer and parser back to power-on.

        Hazards recorded so far are kept (they are history, not state)."""
        self._power_on()

    def feed(self, data: bytes, at_us: int | None = None) -> bytes:
        """Deliver bytes arriving at ``at_us`` µs on the firmware's command timer (None: now); return the
        bytes the device writes back.

        Where the parser reads a timer (v2), time matters: if ``at_us`` is later than the last event the
        parser first polls at ``at_us - 1`` (the idle polling of every tick, so a cut command times out
        before the arrival if it would have), then the arrival is queued (v2's 1024-byte queue may drop
        part of it) and the parser is called until a call neither consumes nor writes a byte.  v1.2 has
        no timer in its parser: the time only moves the clock."""
        tx = self._advance_clock(at_us)
        self.received_bytes += len(data)
        if self.scan is not None:
            self.scan(self)
        p = self.parser
        self._arrival_start = p.offset + p.pending  # where this arrival starts in the byte stream
        p.receive(bytes(data))
        p.run(self.now_us)
        p.note_pending(self.now_us)
        return tx + p.take_tx()

    def advance(self, to_us: int) -> bytes:
        """Let the firmware poll until ``to_us`` µs (a cut v2 command times out on the way); return the
        bytes it writes (none: only a timeout can happen while nothing arrives)."""
        return self._advance_clock(to_us, settle=True)

    def _advance_clock(self, at_us: int | None, settle: bool = False) -> bytes:
        if at_us is None or at_us <= self.now_us:
            return b""
        if isinstance(at_us, bool) or not isinstance(at_us, int):
            raise ConfigurationError(f"at_us={at_us!r} must be an integer number of microseconds")
        self.parser.poll_until(at_us, settle)
        self.now_us = at_us
        return self.parser.take_tx()

    def call(self) -> CallOutcome:
        """Run exactly one firmware parser call at the current clock (for timed models)."""
        return self.parser.call(self.now_us)

    def state(self) -> BoardState:
        """The firmware's variables and its receive queue; where the parser owns the queue (v2), what it
        dropped and whether a command is in progress."""
        p = self.parser
        if self.entry.parser_owns_queue:
            return self.registers.board_state(p.pending, p.dropped, p.processing)
        return self.registers.board_state(p.pending)

    @property
    def locked(self) -> bool:
        return self.parser.locked

    @property
    def voltage(self) -> list[int]:
        return list(self.registers.voltage)
