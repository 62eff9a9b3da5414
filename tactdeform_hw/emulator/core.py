"""The emulated eTactileKit device: parser, registers and board behind one byte-stream API."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from .board import Board
from .hazards import Hazard
from .parser import CallResult, Parser
from .registers import Registers


class Emulator:
    """The firmware's observable behaviour, untimed: every byte fed reaches the parser at once.

    The 256-byte receive queue, its losses and all timing belong to the timed model
    (:mod:`tactdeform_hw.emulator.timed`), which drives the same :class:`Parser` one firmware call at a
    time.  ``scan`` is the seam for the stimulation scan: when set, it is called with this emulator to
    refresh ``registers.voltage`` before a measure reply is written.
    """

    def __init__(self, board: str | Board = "compact", switching_boards: int = 1, *, stack_reading: float | None = None) -> None:
        self.board = board if isinstance(board, Board) else Board(board, switching_boards, stack_reading)
        self.hazards: list[Hazard] = []
        self.scan: Callable[[Emulator], None] | None = None
        self._power_on()

    def _power_on(self) -> None:
        self.registers = Registers(hv513_num=self.board.detect_hv513())
        self.parser = Parser(self.registers, self.hazards, self.board.detect_hv513)

    def reset(self) -> None:
        """Power cycle: registers, pattern buffer, receive buffer and parser back to power-on.

        Hazards recorded so far are kept (they are history, not state)."""
        self._power_on()

    def feed(self, data: bytes) -> bytes:
        """Deliver bytes to the device; return the bytes it writes back."""
        if self.scan is not None:
            self.scan(self)
        self.parser.receive(bytes(data))
        self.parser.run()
        return self.parser.take_tx()

    def call(self) -> CallResult:
        """Run exactly one firmware parser call (for timed models)."""
        return self.parser.call()

    def state(self) -> dict[str, Any]:
        snap = self.registers.snapshot()
        snap["rx_pending"] = self.parser.pending
        return snap

    @property
    def locked(self) -> bool:
        return self.parser.locked

    @property
    def voltage(self) -> list[int]:
        return list(self.registers.voltage)
