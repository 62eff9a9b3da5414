"""A host-built firmware behind the timed models' outer API, so everything that drives a model drives it.

The real-time server, the pty and TCP servers, the ``etactile://`` URL handler and the driver speak to a
timed model through :class:`~tactdeform_hw.emulator.timed.base.TimedModel`: bytes written at a time, the
clock advanced, replies read, a typed :class:`~tactdeform_hw.protocol.state.BoardState`, hazards and the
records of delivered pulses.  :class:`HostBuildTimedModel` gives a :class:`.emulator.HostBuildEmulator`
that face, so a driver cannot tell a host build from the Python model by the API it sees.

What it keeps from the Python model: the host's link (``link``: the same USB or UART timing decides when
the bytes reach the firmware's receive queue).  What is the firmware's own: everything else, read from
the firmware's variables through the tree's state map.  What it cannot know: the parser's progress (a
function-local static in both upstream versions), so ``parser_status`` says so and ``command_in_progress``
is ``None``; the only hazards it records are the link's (bytes the receive queue dropped), since firmware
defects are the Python model's reading of the code, not something the built code reports.

Replies reach the host when the firmware writes them (no reply-link delay).  The model's clock and the
firmware's differ only after a reset: each power-up starts a fresh copy of the firmware at its own time 0
(:attr:`boot_us` is when the current one booted, in the model's time).
"""

from __future__ import annotations

import math
import os
from bisect import bisect_right
from pathlib import Path
from typing import TYPE_CHECKING, Any, cast

import numpy as np

from tactdeform_hw.emulator.firmware.board import Board
from tactdeform_hw.emulator.firmware.hazards import Hazard, HazardKind
from tactdeform_hw.emulator.firmware.models import model_entry
from tactdeform_hw.emulator.firmware.scan import PulseKind
from tactdeform_hw.emulator.hostbuild.delivered import DeliveredPulse
from tactdeform_hw.emulator.hostbuild.emulator import HostBuildEmulator
from tactdeform_hw.emulator.hostbuild.statemap import StateMap, detect
from tactdeform_hw.emulator.records.reports import LossReport
from tactdeform_hw.emulator.timed.link import LinkModel, make_link
from tactdeform_hw.emulator.timed.timing import DEFAULT_MODEL, TimingModel
from tactdeform_hw.errors import ConfigurationError, LimitError
from tactdeform_hw.protocol.firmware import FirmwareSpec, get_firmware
from tactdeform_hw.protocol.state import BoardState

if TYPE_CHECKING:
    from tactdeform_hw.emulator.core import Emulator

#: The registers a state map must name for :meth:`HostBuildTimedModel.state` to give a BoardState.
BOARD_STATE_REGISTERS = (
    "electrode_num",
    "polarity",
    "pulse_width",
    "sense_pulse_height",
    "sense_pulse_width",
    "discharge_time",
    "period_us",
    "hv513_num",
    "stim_pattern",
)

#: When nothing else is due, a server wakes the firmware this often (µs): its replies are found by running
#: it, not announced in advance.
POLL_US = 1000.0


class _Queue:
    """The firmware's receive queue as a server sees it (bytes waiting, room left)."""

    def __init__(self, owner: HostBuildTimedModel) -> None:
        self._owner = owner

    def __len__(self) -> int:
        return int(self._owner.host.state()["rx_pending"])

    @property
    def free(self) -> int:
        snap = self._owner.host.state()
        return max(0, int(snap["rx_capacity"]) - int(snap["rx_pending"]))


class DeliveredReports:
    """The delivered pulses as the campaigns read them (:meth:`pulse_table`): one row per output per pulse."""

    def __init__(self, owner: HostBuildTimedModel) -> None:
        self._owner = owner

    def pulse_table(self, t0_us: float | None = None, t1_us: float | None = None) -> dict[str, np.ndarray]:
        """Columns ``channel`` (the output on the HV513 chain), ``start_us``, ``width_us``, ``code`` (the
        DAC code), ``pol`` (the POL pin), ``kind`` and ``current_ua`` (0: the campaigns convert the code).

        ``kind`` is read from the pins and the registers, since the firmware's pattern at each pulse is
        not recorded: a pulse at the sense height that is not also v1.2's pulse height, both as the
        firmware held them when the pulse started, is a sense pulse (:attr:`PulseKind.SENSE`), any other a
        stimulation pulse (``MONO``).  The registers are sampled at the end of every ``advance_to``
        (:attr:`HostBuildTimedModel.height_history`): a pulse in the same step as a change of them is
        read with the values before it."""
        heights = self._owner.height_history
        times = [t for t, _, _ in heights]
        rows = [
            (out, p.start_us, p.width_us, p.code, p.polarity, _kind(p.code, heights, times, p.start_us))
            for p in self._owner.delivered_pulses()
            if (t0_us is None or p.start_us >= t0_us) and (t1_us is None or p.start_us < t1_us)
            for out in p.outputs
        ]
        cols = list(zip(*rows)) if rows else [(), (), (), (), (), ()]
        return {
            "channel": np.asarray(cols[0], dtype=np.int64),
            "start_us": np.asarray(cols[1], dtype=np.float64),
            "width_us": np.asarray(cols[2], dtype=np.float64),
            "code": np.asarray(cols[3], dtype=np.int64),
            "pol": np.asarray(cols[4], dtype=np.int64),
            "kind": np.asarray(cols[5], dtype=np.int64),
            "current_ua": np.zeros(len(rows), dtype=np.float64),
        }


def _kind(
    code: int, heights: list[tuple[float, int | None, int | None]], times: list[float], t_us: float
) -> int:
    k = bisect_right(times, t_us) - 1
    if k < 0:
        return int(PulseKind.MONO)
    _, sense, height = heights[k]
    if sense is not None and code == sense and code != height:
        return int(PulseKind.SENSE)
    return int(PulseKind.MONO)


class HostBuildTimedModel:
    """A host-built firmware tree as a timed model (see the module documentation).

    ``firmware_src``: the PlatformIO tree.  ``board`` / ``switching_boards``: the board around it (the
    compact board: 4 HV513 chips per switching board, sensed by the firmware's own stack detection).
    ``state_map``: which variables hold the registers and which firmware table the tree speaks (default:
    the shipped map whose unit the tree holds).  ``link``: how the host's bytes travel (``usb``, ``uart``
    or a :class:`LinkModel`).  Other keywords go to :class:`HostBuildEmulator` (``defines``, ``cache``,
    ``compiler``, ``rx_buffer_bytes``, ``chain_outputs``)."""

    def __init__(
        self,
        firmware_src: str | os.PathLike[str],
        board: str | Board = "compact",
        switching_boards: int = 1,
        *,
        state_map: StateMap | None = None,
        link: str | LinkModel = "usb",
        model: TimingModel | None = None,
        stack_reading: float | None = None,
        **host_options: Any,
    ) -> None:
        self.board = board if isinstance(board, Board) else Board(board, switching_boards, stack_reading)
        if self.board.kind != "compact":
            raise ConfigurationError(
                f"board={self.board.kind!r}: a host build runs the compact board's branch only "
                "(pass defines= for another branch and board='compact')"
            )
        self.firmware_src = firmware_src
        self.state_map = state_map if state_map is not None else detect(Path(firmware_src))
        self.firmware: FirmwareSpec | None = (
            get_firmware(self.state_map.firmware, "state map firmware")
            if self.state_map is not None and self.state_map.firmware
            else None
        )
        self.model = model if model is not None else DEFAULT_MODEL
        self.link = make_link(link)
        self._stack_reading = None if stack_reading is None else int(stack_reading)
        self._options = host_options
        self.hazards: list[Hazard] = []
        self._losses: list[LossReport] = []
        self.reboots = 0
        self.received_bytes = 0
        self._host_offset = 0
        self._deliveries: list[tuple[int, bytes, int]] = []  # (arrival ns, data, host offset), time order
        self._replies = bytearray()
        self._tx_seen = 0
        self._drops_seen = 0
        self._stopped = False
        self.boot_ns = 0
        self.now_ns = 0
        self.host = self._power_up()
        #: (model µs, sense height, v1.2 pulse height) whenever a step ended with them changed
        self.height_history: list[tuple[float, int | None, int | None]] = []
        self._sample_heights()
        self.reports = DeliveredReports(self)
        self._pulses: list[DeliveredPulse] = []  # the previous power-ups' pulses, in model time

    def _power_up(self) -> HostBuildEmulator:
        return HostBuildEmulator(
            self.firmware_src,
            hv513_count=self.board.detect_hv513(),
            timing=self.model,
            state_map=self.state_map,
            stack_reading=self._stack_reading,
            **self._options,
        )

    @property
    def emulator(self) -> Emulator:
        """The untimed face servers read (``state()``, ``hazards``): this model itself."""
        return cast("Emulator", self)

    # --- time ---------------------------------------------------------------------------------------------

    @property
    def now_us(self) -> float:
        return self.now_ns / 1000.0

    @property
    def boot_us(self) -> float:
        """When the running copy of the firmware powered up, in the model's time."""
        return self.boot_ns / 1000.0

    def advance_to(self, t_us: float) -> None:
        """Run the firmware until ``t_us``, landing the host's bytes as the link brings them."""
        target = int(round(t_us * 1000))
        if target < self.now_ns:
            raise LimitError("t_us", t_us, f">= now ({self.now_us} us)")
        while self._deliveries and self._deliveries[0][0] <= target:
            t_ns, data, offset = self._deliveries.pop(0)
            self._land(t_ns, data, offset)
        self.host.advance_to((target - self.boot_ns) / 1000.0)
        self.now_ns = target
        self._collect()
        self._sample_heights()

    def _sample_heights(self) -> None:
        sample = self.sense_and_pulse_height()
        if not self.height_history or self.height_history[-1][1:] != sample:
            self.height_history.append((self.now_us, *sample))

    def advance(self, dt_us: float) -> None:
        if not dt_us >= 0:
            raise LimitError("dt_us", dt_us, ">= 0")
        self.advance_to(self.now_us + dt_us)

    def _land(self, t_ns: int, data: bytes, offset: int) -> None:
        if self._stopped:
            return
        at = max(t_ns, self.now_ns, self.boot_ns) - self.boot_ns
        self.host.advance_to(at / 1000.0)
        self.host.write(data, at / 1000.0)
        self.received_bytes += len(data)
        self._collect()

    def _collect(self) -> None:
        """Replies the firmware wrote and the queue's drops, into the host's view and the hazard list."""
        self._replies += self.host.read()
        drops = self.host.rx_drops
        for d in drops[self._drops_seen :]:
            t_us = d.t_us + self.boot_us
            self._losses.append(
                LossReport(t_us, d.host_offset, d.count, b"", "queue_full", d.queued, self.parser_status())
            )
            self.hazards.append(
                Hazard(
                    HazardKind.QUEUE_OVERFLOW,
                    d.host_offset,
                    {"bytes_lost": d.count, "host_offset": d.host_offset, "parser": self.parser_status()},
                    t_us,
                )
            )
        self._drops_seen = len(drops)

    def next_event_us(self, scans: bool = True) -> float:
        """When the model next needs running: a delivery landing, the stimulation timer's alarm (with
        ``scans``), and at the latest :data:`POLL_US` from now (replies are found by running the code)."""
        t = self.now_us + POLL_US
        if self._deliveries:
            t = min(t, self._deliveries[0][0] / 1000.0)
        if scans:
            for num in range(4):
                info = self.host.timer(num)
                if info is not None and info["has_interrupt"] and info["next_alarm_us"] is not None:
                    t = min(t, info["next_alarm_us"] + self.boot_us)
        return max(t, self.now_us)

    def run_until_idle(self, limit_us: float = 60e6, step_us: float = 1000.0) -> bool:
        """Advance until every delivery has landed and the receive queue is empty, or ``limit_us``."""
        end = self.now_ns + round(limit_us * 1000.0)
        while True:
            if not self._deliveries and len(self.queue) == 0:
                self.advance(step_us)  # the firmware's reply to the last bytes it read
                return True
            if self.now_ns >= end:
                return False
            self.advance_to(min(end, self.now_ns + round(step_us * 1000.0)) / 1000.0)

    # --- the host's side ----------------------------------------------------------------------------------

    @property
    def host_offset(self) -> int:
        return self._host_offset

    def write(self, data: bytes, at_us: float | None = None) -> int:
        """The host writes ``data`` at ``at_us`` (default now); the link decides when it lands."""
        data = bytes(data)
        t_ns = self.now_ns if at_us is None else int(round(at_us * 1000))
        if t_ns < self.now_ns:
            raise LimitError("at_us", at_us, f">= now ({self.now_us} us)")
        for d in self.link.schedule(data, t_ns, self._host_offset):
            self._deliveries.append((d.t_ns, d.data, d.host_offset))
        self._deliveries.sort(key=lambda x: x[0])
        self._host_offset += len(data)
        return len(data)

    def read_tx(self, size: int | None = None) -> bytes:
        """Replies the firmware wrote by now (all, or at most ``size``)."""
        n = len(self._replies) if size is None else min(size, len(self._replies))
        out = bytes(self._replies[:n])
        del self._replies[:n]
        return out

    @property
    def in_waiting(self) -> int:
        return len(self._replies)

    @property
    def in_flight(self) -> int:
        return sum(len(d[1]) for d in self._deliveries)

    @property
    def queue(self) -> _Queue:
        return _Queue(self)

    @property
    def losses(self) -> list[LossReport]:
        return self._losses

    def new_client(self, name: str) -> None:
        """A new host connection: nothing in the firmware changes (it does not know the host)."""

    # --- state --------------------------------------------------------------------------------------------

    def state(self) -> BoardState:
        """The firmware's registers, read from its own variables; refused when the state map does not say
        which firmware table the tree speaks or does not name the registers."""
        snap = self.host.state()
        missing = [r for r in BOARD_STATE_REGISTERS if r not in snap]
        if self.firmware is None or missing:
            raise ConfigurationError(
                f"state map {self.state_map.name if self.state_map else '(none)'}: a board state needs "
                f"firmware = 'v1.2' or 'v2' and the registers {', '.join(missing or BOARD_STATE_REGISTERS)}"
            )
        pattern = tuple(int(v) for v in snap["stim_pattern"])
        return BoardState(
            firmware=self.firmware,
            electrode_num=int(snap["electrode_num"]),
            polarity=int(snap["polarity"]),
            stim_mode=None if "stim_mode" not in snap else int(snap["stim_mode"]),
            pulse_height=None if "pulse_height" not in snap else int(snap["pulse_height"]),
            pulse_width_us=int(snap["pulse_width"]),
            sense_pulse_height=int(snap["sense_pulse_height"]),
            sense_pulse_width_us=int(snap["sense_pulse_width"]),
            discharge_time_us=int(snap["discharge_time"]),
            period_us=float(snap["period_us"]),
            timer_alarm_ticks=int(snap.get("timer_alarm_ticks", 0)),
            hv513_num=int(snap["hv513_num"]),
            stim_pattern=pattern,
            rx_pending=int(snap["rx_pending"]),
            # what the queue dropped is the board's state where the firmware's parser owns the queue (v2)
            rx_dropped=int(snap["rx_dropped"]) if model_entry(self.firmware).parser_owns_queue else None,
        )

    def sense_and_pulse_height(self) -> tuple[int | None, int | None]:
        """The sense pulse's DAC code and v1.2's pulse height as the firmware holds them now (``None``:
        the state map does not name them)."""
        snap = self.host.state()
        sense = snap.get("sense_pulse_height")
        height = snap.get("pulse_height")
        return (None if sense is None else int(sense), None if height is None else int(height))

    @property
    def commands(self) -> list[Any]:
        """The commands the parser completed, as the Python model records them: none here (the firmware's
        parser keeps its progress in function-local statics), so no command is counted out of step."""
        return []

    def parser_status(self) -> str:
        return "not readable (the firmware keeps its parser's progress in function-local statics)"

    # --- power, faults, history ---------------------------------------------------------------------------

    def reset(self, reason: str = "reset") -> None:
        """Power-cycle: a fresh copy of the firmware boots now; bytes on the link still land."""
        self._pulses += self._shifted(self.host.delivered_pulses())
        self.host = self._power_up()
        self.boot_ns = self.now_ns
        self._drops_seen = 0
        self._stopped = False
        self.reboots += 1

    def stop_reading(self) -> None:
        """The main loop hangs: refused, the built firmware's loop cannot be stopped from outside."""
        raise ConfigurationError("stop_reading: a host build runs the firmware's own loop; it cannot hang it")

    def discard_history(self, before_us: float) -> None:
        """Forget recorded events before ``before_us`` (delivered pulses are kept: safety reads them)."""
        self.host.clear_events()

    def attach(self, sink: Any) -> None:
        raise ConfigurationError("attach: a host build records events() and delivered_pulses(), not a sink")

    # --- records ------------------------------------------------------------------------------------------

    def _shifted(self, pulses: list[DeliveredPulse]) -> list[DeliveredPulse]:
        b = self.boot_us
        if b == 0:
            return pulses
        return [DeliveredPulse(p.start_us + b, p.end_us + b, p.code, p.outputs, p.polarity) for p in pulses]

    def delivered_pulses(self) -> list[DeliveredPulse]:
        """Every stretch of current delivered since the model was made, in the model's time."""
        return self._pulses + self._shifted(self.host.delivered_pulses())

    def scans(self) -> list[tuple[float, float]]:
        """The current power-up's interrupt runs still in the history, in the model's time."""
        return [(a + self.boot_us, b + self.boot_us) for a, b in self.host.scans()]

    def scan_rate(self, at_us: float) -> tuple[int, float]:
        """Scans in the history and the rate of the last two (0 when the last is older than a second)."""
        runs = self.scans()
        if len(runs) < 2 or at_us - runs[-1][0] > 1e6:
            return len(runs), 0.0
        gap = runs[-1][0] - runs[-2][0]
        return len(runs), 1e6 / gap if gap > 0 else math.inf

    def current_pulse_starts_us(self, since_us: float, now_us: float) -> list[float]:
        return [p.start_us for p in self.delivered_pulses() if since_us <= p.start_us < now_us]


def host_build_timed(firmware_src: str | os.PathLike[str], *args: Any, **kwargs: Any) -> HostBuildTimedModel:
    """:class:`HostBuildTimedModel` (the same arguments)."""
    return HostBuildTimedModel(firmware_src, *args, **kwargs)


__all__ = ["BOARD_STATE_REGISTERS", "DeliveredReports", "HostBuildTimedModel", "host_build_timed"]
