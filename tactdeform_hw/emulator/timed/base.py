"""The outer API every firmware version's timed model keeps, and the part of it they share.

A server (the real-time board, the emulated USB device, the pty and TCP servers), the fault layer and the
campaigns drive a timed model without asking which version it runs: they write bytes at a time, run the
model to a time, read the replies that reached the host, reset it, and read its state and its records of
what it delivered.  :class:`TimedModel` is that API; the timed model of each version
(:class:`~.model_v1_2.TimedEmulator`, :class:`~.model_v2.TimedEmulatorV2`) keeps it, and the registry
(:data:`~tactdeform_hw.emulator.firmware.models.MODELS`) names which class runs which version.
:class:`TimedModelBase` holds what both implement alike (the clock in µs, stepping it, reading the
replies that reached the host, running until idle, the typed state), so each model keeps only what its
firmware does differently.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any, Protocol

from tactdeform_hw.emulator.firmware.board import Board
from tactdeform_hw.emulator.firmware.hazards import Hazard
from tactdeform_hw.emulator.firmware.skin import SkinModel
from tactdeform_hw.emulator.records.reports import LossReport
from tactdeform_hw.emulator.timed.link import LinkModel
from tactdeform_hw.emulator.timed.timing import TimingModel
from tactdeform_hw.errors import LimitError
from tactdeform_hw.protocol.firmware import FirmwareSpec
from tactdeform_hw.protocol.state import BoardState

if TYPE_CHECKING:
    from tactdeform_hw.emulator.core import Emulator


class ReceivePath(Protocol):
    """The receive queue as a server sees it: bytes waiting (``len``) and room (``free``)."""

    def __len__(self) -> int: ...

    @property
    def free(self) -> int: ...


class TimedModel(Protocol):
    """A firmware version's board on a simulated clock (see the module documentation)."""

    firmware: FirmwareSpec
    emulator: Emulator
    board: Board
    hazards: list[Hazard]
    model: TimingModel
    link: LinkModel
    received_bytes: int
    reboots: int

    @property
    def now_us(self) -> float: ...

    @property
    def host_offset(self) -> int: ...

    @property
    def queue(self) -> ReceivePath: ...

    @property
    def losses(self) -> list[LossReport]: ...

    @property
    def in_waiting(self) -> int: ...

    @property
    def in_flight(self) -> int: ...

    def state(self) -> BoardState: ...

    def write(self, data: bytes, at_us: float | None = None) -> int: ...

    def advance_to(self, t_us: float) -> None: ...

    def read_tx(self, size: int | None = None) -> bytes: ...

    def next_event_us(self, scans: bool = True) -> float: ...

    def run_until_idle(self, limit_us: float = 60e6, step_us: float = 1000.0) -> bool: ...

    def parser_status(self) -> str: ...

    def reset(self, reason: str = "reset") -> None: ...

    def stop_reading(self) -> None: ...

    def new_client(self, name: str) -> None: ...

    def discard_history(self, before_us: float) -> None: ...

    def attach(self, sink: Any) -> None: ...

    def scan_rate(self, at_us: float) -> tuple[int, float]:
        """Scans since power-up and the current scan rate in Hz (0 when the scans stopped)."""
        ...

    def current_pulse_starts_us(self, since_us: float, now_us: float) -> list[float]:
        """The start times of the delivered pulses that carried current between the two times."""
        ...


class TimedModelBase:
    """What every timed model implements alike.  A subclass keeps the clock in ``now_ns`` and says where
    its replies wait for the host (:meth:`_host_replies`, filled by :meth:`_collect_tx`), which host
    bytes are still on the link (:meth:`_deliveries`), when nothing more will be read (:meth:`_idle`)
    and how many bytes wait in its receive queue (:meth:`_rx_pending`)."""

    firmware: FirmwareSpec
    emulator: Emulator
    now_ns: int

    # --- what a subclass says ---------------------------------------------------------------------------

    def advance_to(self, t_us: float) -> None:
        raise NotImplementedError

    def _collect_tx(self) -> None:
        """Move the replies that have reached the host by now into :meth:`_host_replies`."""
        raise NotImplementedError

    def _host_replies(self) -> bytearray:
        raise NotImplementedError

    def _deliveries(self) -> list[tuple[int, int, Any]]:
        """The host's bytes on their way: a heap of (arrival ns, sequence, delivery)."""
        raise NotImplementedError

    def _idle(self) -> bool:
        """Every delivery has landed and the parser has read all it will read."""
        raise NotImplementedError

    def _rx_pending(self) -> int:
        """Bytes waiting in the receive queue."""
        raise NotImplementedError

    # --- the shared outer API ---------------------------------------------------------------------------

    @classmethod
    def served(
        cls,
        board: str | Board,
        switching_boards: int,
        *,
        link: str | LinkModel,
        tx_link: str | LinkModel | None,
        model: TimingModel | None,
        skin: SkinModel | None,
        stack_reading: float | None,
    ) -> TimedModel:
        """The model a server runs (the real-time board, the emulated USB device): every server passes
        the same options to every version's timed model; :meth:`_served_options` adapts them."""
        make: Any = cls
        options = cls._served_options({"link": link, "tx_link": tx_link, "model": model, "skin": skin})
        built: TimedModel = make(board, switching_boards, stack_reading=stack_reading, **options)
        return built

    @classmethod
    def _served_options(cls, options: dict[str, Any]) -> dict[str, Any]:
        """The model's own keyword arguments for a server's ``link``, ``tx_link``, ``model`` and
        ``skin`` (default: the same names)."""
        return options

    @property
    def now_us(self) -> float:
        return self.now_ns / 1000.0

    def advance(self, dt_us: float) -> None:
        """Run the device for ``dt_us`` more µs."""
        if not (dt_us >= 0):
            raise LimitError("dt_us", dt_us, ">= 0")
        self.advance_to(self.now_us + dt_us)

    def read_tx(self, size: int | None = None) -> bytes:
        """Reply bytes that have reached the host by now (all, or at most ``size``)."""
        self._collect_tx()
        rx = self._host_replies()
        n = len(rx) if size is None else min(size, len(rx))
        out = bytes(rx[:n])
        del rx[:n]
        return out

    @property
    def in_waiting(self) -> int:
        """Reply bytes that have reached the host and were not read yet."""
        self._collect_tx()
        return len(self._host_replies())

    @property
    def in_flight(self) -> int:
        """Bytes written by the host that have not reached the receive queue yet."""
        return sum(len(d[2].data) for d in self._deliveries())

    def run_until_idle(self, limit_us: float = 60e6, step_us: float = 1000.0) -> bool:
        """Advance until every delivery has landed and the parser has read all it will read (a cut v2
        command may stay pending), or ``limit_us`` of device time passed.  Returns whether it got idle."""
        end = self.now_ns + round(limit_us * 1000.0)
        while True:
            if self._idle():
                return True
            if self.now_ns >= end:
                return False
            self.advance_to(min(end, self.now_ns + round(step_us * 1000.0)) / 1000.0)

    def state(self) -> BoardState:
        """The firmware's registers, and the bytes waiting in the receive queue."""
        p = self.emulator.parser
        if self.emulator.entry.parser_owns_queue:
            return self.emulator.registers.board_state(p.pending, p.dropped, p.processing)
        return self.emulator.registers.board_state(self._rx_pending())


__all__ = ["ReceivePath", "TimedModel", "TimedModelBase"]
