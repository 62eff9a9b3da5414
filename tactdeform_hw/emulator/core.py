"""The emulated eTactileKit device: parser, registers and board behind one byte-stream API."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from tactdeform_hw.emulator.firmware.board import Board
from tactdeform_hw.emulator.firmware.hazards import Hazard, HazardKind
from tactdeform_hw.emulator.firmware.parser import CallResult, Parser
from tactdeform_hw.emulator.firmware.parser_v2 import CallOutcome, ParserV2
from tactdeform_hw.emulator.firmware.registers import Registers, RegistersV2

from ..errors import ConfigurationError

#: Firmware versions the emulator runs; v1.2 stays the default.
FIRMWARE_VERSIONS = ("v1.2", "v2")


class Emulator:
    """The firmware's observable behaviour, untimed: every byte fed reaches the parser at once.

    ``firmware`` picks the version: "v1.2" (default) or "v2" (per-electrode u16 heights, whole-payload
    parsing with the 2 s command timeout, its 1024-byte queue, which this class models since v2's state
    depends on it; time enters through ``feed(..., at_us=)`` and :meth:`advance`).

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
        firmware: str = "v1.2",
    ) -> None:
        if firmware not in FIRMWARE_VERSIONS:
            raise ConfigurationError(f"firmware={firmware!r} is not one of {', '.join(FIRMWARE_VERSIONS)}")
        self.firmware = firmware
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
        self.registers: Any
        self.parser: Any
        if self.firmware == "v2":
            self.registers = RegistersV2(hv513_num=self.board.detect_hv513())
            self.parser = ParserV2(self.registers, self.hazards, self.board.detect_hv513)
        else:
            self.registers = Registers(hv513_num=self.board.detect_hv513())
            self.parser = Parser(self.registers, self.hazards, self.board.detect_hv513)
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

        On v2, time matters: if ``at_us`` is later than the last event the parser first polls at
        ``at_us - 1`` (the idle polling of every tick, so a cut command times out before the arrival if
        it would have), then the arrival is queued (the 1024-byte queue may drop part of it) and the
        parser is called until a call neither consumes nor writes a byte.  v1.2 has no timer in its
        parser: the time only moves the clock."""
        tx = self._advance_clock(at_us)
        self.received_bytes += len(data)
        if self.scan is not None:
            self.scan(self)
        if self.firmware == "v2":
            self.parser.receive(bytes(data))
            self.parser.run(self.now_us)
            self._note_pending()
        else:
            p = self.parser
            self._arrival_start = p.base + len(p.rx)  # where this arrival starts in the byte stream
            p.receive(bytes(data))
            p.run()
        out: bytes = tx + self.parser.take_tx()
        return out

    def advance(self, to_us: int) -> bytes:
        """Let the firmware poll until ``to_us`` µs (a cut v2 command times out on the way); return the
        bytes it writes (none: only a timeout can happen while nothing arrives)."""
        return self._advance_clock(to_us, settle=True)

    def _advance_clock(self, at_us: int | None, settle: bool = False) -> bytes:
        if at_us is None or at_us <= self.now_us:
            return b""
        if isinstance(at_us, bool) or not isinstance(at_us, int):
            raise ConfigurationError(f"at_us={at_us!r} must be an integer number of microseconds")
        if self.firmware == "v2":
            self.parser.run(at_us - 1)
            self.now_us = at_us
            if settle:
                self.parser.run(at_us)
        else:
            self.now_us = at_us
        return bytes(self.parser.take_tx())

    def _note_pending(self) -> None:
        p = self.parser
        if p.processing:
            at = p.command_offset
            if (
                not self.hazards
                or self.hazards[-1].kind is not HazardKind.COMMAND_PENDING
                or self.hazards[-1].offset != at
            ):
                self.hazards.append(
                    Hazard(
                        HazardKind.COMMAND_PENDING,
                        at,
                        {
                            "command": p.spec.command(p.command).name,
                            "needed": p.required,
                            "queued": p.pending,
                        },
                        float(self.now_us),
                    )
                )

    def call(self) -> CallResult | CallOutcome:
        """Run exactly one firmware parser call (for timed models); v2's at the current clock."""
        result: CallResult | CallOutcome = (
            self.parser.call(self.now_us) if self.firmware == "v2" else self.parser.call()
        )
        return result

    def state(self) -> dict[str, Any]:
        """The firmware's variables; on v2 with the golden vectors' names, ``rx_dropped`` and
        ``command_in_progress`` included."""
        snap: dict[str, Any] = self.registers.snapshot()
        snap["rx_pending"] = self.parser.pending
        if self.firmware == "v2":
            snap["rx_dropped"] = self.parser.dropped
            snap["command_in_progress"] = self.parser.processing
        return snap

    @property
    def locked(self) -> bool:
        return bool(getattr(self.parser, "locked", False))

    @property
    def voltage(self) -> list[int]:
        return list(self.registers.voltage)
