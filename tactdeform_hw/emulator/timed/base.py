"""The outer API every firmware version's timed model keeps.

A server (the real-time board, the emulated USB device, the pty and TCP servers), the fault layer and the
campaigns drive a timed model without asking which version it runs: they write bytes at a time, run the
model to a time, read the replies that reached the host, reset it, and read its state and its records of
what it delivered.  :class:`TimedModel` is that API; the timed model of each version
(:class:`~.model_v1_2.TimedEmulator`, :class:`~.model_v2.TimedEmulatorV2`) keeps it, and the registry
(:data:`~tactdeform_hw.emulator.firmware.models.MODELS`) names which class runs which version.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any, Protocol

from tactdeform_hw.emulator.firmware.board import Board
from tactdeform_hw.emulator.firmware.hazards import Hazard
from tactdeform_hw.emulator.firmware.skin import SkinModel
from tactdeform_hw.emulator.records.reports import LossReport
from tactdeform_hw.emulator.timed.link import LinkModel
from tactdeform_hw.emulator.timed.timing import TimingModel
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
        """The model a server runs, from the options every server passes to every version."""
        ...

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


__all__ = ["ReceivePath", "TimedModel"]
