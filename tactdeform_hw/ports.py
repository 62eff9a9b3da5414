"""What a port may declare, and the base the package's own port classes share.

The driver talks to a pyserial-compatible object and never looks inside it: whatever it needs to treat a
board and an emulator differently, the port says about itself.  A port that declares nothing is treated as
a real board (paced in wall time, reset through RTS, never inspected).  The capabilities:

================  ==========================================================================================
``instant``       ``True`` when every byte is consumed the moment it is written (no waiting can bring more)
``pacing_clock``  the clock (``now``/``sleep``) writes must be paced in: wall time, a clock that never
                  waits, or a simulation's time
``pulse_reset()`` power-cycle the board the way its reset line would
``guardable``     ``True`` when a guardian process may hold the port's file descriptor (``fileno()``)
``reset_line``    ``False`` when the port has no reset line a guardian could pulse (TCP); default: RTS
``board_untouched`` ``True`` while the board behind the port has received no byte since power-on (an
                  in-process emulator just made): no earlier program can have left a command in its parser,
                  so the firmware identification need not wait out v2's command timeout first
``serves_one_client`` ``True`` when the board serves one connection at a time and later ones wait unanswered
                  (the Wi-Fi board): silence to the identification then means "busy"
``board_state()`` the firmware's registers as the board holds them, a
                  :class:`~.protocol.state.BoardState`: what an emulated board can show and a real one cannot
``board_hazards`` the firmware defects the board has hit, as :class:`~.emulator.hazards.Hazard` records
``loses_bytes``   ``True`` when the link can lose, corrupt or duplicate a byte without telling either end
                  (a raw UART, a USB-to-UART bridge: no checksum): the plain encoding is then a risk, since
                  one lost byte can turn a zero into a full-scale value (the driver warns; the
                  loss-tolerant encoding is the remedy).  USB CDC (CRC-checked) and TCP do not declare it
================  ==========================================================================================

This module sits at the package root because the device layer reads these capabilities and the emulator's
ports declare them, and neither may import the other.
"""

from __future__ import annotations

from typing import Any, Protocol, runtime_checkable

from .protocol.state import BoardState


@runtime_checkable
class InspectablePort(Protocol):
    """A port whose board can show its registers (an emulated board)."""

    def board_state(self) -> BoardState: ...


def is_instant(port: Any) -> bool:
    """Whether ``port`` declares that it consumes every byte at once."""
    return bool(getattr(port, "instant", False))


def pacing_clock(port: Any) -> Any:
    """The clock ``port`` declares for pacing, or None (then: wall time)."""
    return getattr(port, "pacing_clock", None)


def board_untouched(port: Any) -> bool:
    """Whether ``port`` declares that its board has received no byte since power-on."""
    return bool(getattr(port, "board_untouched", False))


def loses_bytes(port: Any) -> bool:
    """Whether ``port`` declares a link that can lose a byte without telling (a UART)."""
    return getattr(port, "loses_bytes", False) is True


def serves_one_client(port: Any) -> bool:
    """Whether ``port`` declares a board that serves one connection at a time (the Wi-Fi board)."""
    return bool(getattr(port, "serves_one_client", False))


def board_state(port: Any) -> BoardState | None:
    """The registers of the board behind ``port`` when it declares ``board_state()``, else None."""
    fn = getattr(port, "board_state", None)
    if not callable(fn):
        return None
    state = fn()
    if not isinstance(state, BoardState):
        raise TypeError(
            f"{type(port).__name__}.board_state() returned {type(state).__name__}, not BoardState"
        )
    return state


def board_hazards(port: Any) -> list[Any] | None:
    """The defect records of the board behind ``port`` when it declares ``board_hazards``, else None."""
    hazards = getattr(port, "board_hazards", None)
    return hazards if isinstance(hazards, list) else None


class PortBase:
    """The parts of pyserial's ``Serial`` every in-package port has alike: the open check, an output side
    that holds nothing (a write returns once the bytes are taken), and the context manager.

    A port built on pyserial's ``SerialBase`` lists it first (its context manager opens only a closed
    port) and overrides :meth:`_not_open_error` to raise pyserial's ``PortNotOpenError``."""

    is_open: bool

    def _not_open_error(self) -> Exception:
        from .errors import PortNotOpenError

        return PortNotOpenError(f"{type(self).__name__}: the port is not open")

    def _check_open(self) -> Any:
        if not self.is_open:
            raise self._not_open_error()
        return None

    @property
    def out_waiting(self) -> int:
        """Always 0: a write returns only once the other side has taken every byte."""
        self._check_open()
        return 0

    def reset_output_buffer(self) -> None:
        self._check_open()

    def flush(self) -> None:
        self._check_open()

    def __enter__(self) -> Any:
        if not self.is_open:
            self.open()  # type: ignore[attr-defined]
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()  # type: ignore[attr-defined]


__all__ = [
    "InspectablePort",
    "PortBase",
    "board_hazards",
    "board_state",
    "board_untouched",
    "is_instant",
    "pacing_clock",
    "serves_one_client",
]
