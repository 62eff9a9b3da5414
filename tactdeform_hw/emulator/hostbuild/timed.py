"""A host-built firmware behind the timed models' outer API, so everything that drives a model drives it.

The real-time server, the pty and TCP servers, the ``etactile://`` URL handler and the driver speak to a
timed model through :class:`~tactdeform_hw.emulator.timed.base.TimedModel`: bytes written at a time, the
clock advanced, replies read, a typed :class:`~tactdeform_hw.protocol.state.BoardState`, hazards and the
records of delivered pulses.  :class:`HostBuildTimedModel` gives a :class:`.emulator.HostBuildEmulator`
that face, so a driver cannot tell a host build from the Python model by the API it sees.

What it keeps from the Python model: the host's link (``link``: the same USB or UART timing decides when
the bytes reach the firmware's receive queue).  What is the firmware's own: everything else, read from
the firmware's variables through the tree's state map.  What it cannot know without a map that reads it:
the parser's progress (a function-local static in both upstream versions; the v2 map reads it through the
symbol table, and ``parser_status`` reports it), so ``parser_status`` says so and ``command_in_progress``
is ``None``; the only hazards it records are the link's (bytes the receive queue dropped), since firmware
defects are the Python model's reading of the code, not something the built code reports.  A trace sink
(:meth:`HostBuildTimedModel.attach`) receives the firmware's own pin and DAC events.

Replies travel back over ``tx_link`` (by default the same kind of link as the host's, as in the Python
models) from the time the firmware writes each byte.  The model's clock and the
firmware's differ only after a reset: each power-up starts a fresh copy of the firmware at its own time 0
(:attr:`boot_us` is when the current one booted, in the model's time).
"""

from __future__ import annotations

import math
import os
from collections import deque
from pathlib import Path
from typing import TYPE_CHECKING, Any, cast

import numpy as np

from tactdeform_hw.emulator.firmware.board import Board
from tactdeform_hw.emulator.firmware.hazards import Hazard, HazardKind
from tactdeform_hw.emulator.firmware.models import model_entry
from tactdeform_hw.emulator.firmware.scan import ChannelKind, Signal, channel_kind, pulse_kind_of
from tactdeform_hw.emulator.hostbuild.delivered import ETACTILEKIT_PINS, DeliveredPulse
from tactdeform_hw.emulator.hostbuild.emulator import HostBuildEmulator, IsrSample
from tactdeform_hw.emulator.hostbuild.statemap import StateMap, detect
from tactdeform_hw.emulator.hostbuild.torn import TornPatternWatch
from tactdeform_hw.emulator.records.reports import EventRun, LossReport, RowPulseTable
from tactdeform_hw.emulator.timed.link import LinkModel, make_link, reply_link
from tactdeform_hw.emulator.timed.timing import DEFAULT_MODEL, TimingModel
from tactdeform_hw.errors import ConfigurationError, LimitError
from tactdeform_hw.protocol.firmware import FirmwareSpec, get_firmware
from tactdeform_hw.protocol.state import STATE_VARIABLES, BoardState

if TYPE_CHECKING:
    from tactdeform_hw.emulator.core import Emulator

#: The registers a state map must name for :meth:`HostBuildTimedModel.state` to give a BoardState: the
#: board state's variables but the stimulation timer's alarm, which is read from the timer itself.
BOARD_STATE_REGISTERS = tuple(name for name in STATE_VARIABLES if name != "timer_alarm_ticks")

#: The build defines of the large board's branch (``board="large"``): the upstream firmware chooses its
#: board at compile time, ``ETACTILEKIT_BOARD`` against the configuration header's
#: ``ETACTILEKIT_COMPACT_BOARD`` (its stack detection tests the large board first).
LARGE_BOARD_DEFINES: dict[str, str] = {"ETACTILEKIT_BOARD": "", "SERIAL_COMMUNICATION": ""}

#: When nothing else is due, a server wakes the firmware this often (µs): its replies are found by running
#: it, not announced in advance.
POLL_US = 1000.0
#: The firmware's raw events (pins, SPI, interrupt runs) a timed model keeps (µs): only the last scans are
#: read (:meth:`HostBuildTimedModel.scan_rate`).  They are about 100 000 Python objects per second of
#: stimulation: kept for a served board's 10 s of history they took hundreds of megabytes, and the garbage
#: collector's full passes walked them all (100 to 300 ms each, measured).
EVENT_HISTORY_US = 100_000.0


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


class DeliveredReports(RowPulseTable):
    """The delivered pulses as the campaigns read them (:meth:`pulse_table`): one row per output per pulse.

    Columns ``channel`` (the output on the HV513 chain), ``start_us``, ``width_us``, ``code`` (the DAC
    code), ``pol`` (the POL pin) and ``kind``, then ``current_ua`` and ``charge_nc``.  ``kind`` is what
    the firmware's interrupt handler chose, read from the registers it chose by as they stood when the scan
    began (:func:`pulse_kind`): a scan cannot see the main loop change them, so the reading at the
    handler's entry is exact for every pulse of the scan."""

    row_columns = ("channel", "start_us", "width_us", "code", "pol", "kind")
    _owner: HostBuildTimedModel

    def _rows(self, t0_us: float | None, t1_us: float | None) -> list[tuple[float, ...]]:
        return [
            (out, p.start_us, p.width_us, p.code, p.polarity, kind)
            for p, kinds in self._owner.classified_pulses()
            if (t0_us is None or p.start_us >= t0_us) and (t1_us is None or p.start_us < t1_us)
            for out, kind in zip(p.outputs, kinds)
        ]


#: The board's control pins as the trace signals name them (:meth:`HostBuildTimedModel.attach`).
_PIN_SIGNALS = {
    ETACTILEKIT_PINS.bl: Signal.BL,
    ETACTILEKIT_PINS.le: Signal.LE,
    ETACTILEKIT_PINS.pol: Signal.POL,
    ETACTILEKIT_PINS.clk: Signal.CLK,
    ETACTILEKIT_PINS.din: Signal.DIN,
}

#: Registers read at every interrupt entry to tell the pulses' kinds (those the state map names).
KIND_REGISTERS = ("stim_mode", "stim_pattern", "sense_pulse_height", "pulse_height")


def pulse_kind(declared: bool, regs: dict[tuple[str, int], int | float], output: int, pulse: Any) -> int:
    """The :class:`PulseKind` of ``pulse`` on ``output``, from the registers ``regs`` (``(name, index)``)
    as the scan that made it began, by the firmware's own choice when the state map declares the
    firmware's table (``declared``):

    - a firmware with a scan mode (v2's ``StimulationMode``): 0 monophasic, 1 biphasic, 2 sense, for the
      whole scan, as the Python model reads it;
    - otherwise (v1.2) the channel's pattern value: 1 monophasic, 2 biphasic, any other a sense pulse at
      the sense height; the firmware selects output ``ch`` for channel ``ch``;
    - a firmware that declares no table: a pulse at the sense height that is not also the pulse height is
      a sense pulse, any other a stimulation pulse.

    A biphasic phase is told by its POL level, as the Python model tells it."""
    kind: int
    if declared and ("stim_mode", 0) in regs:
        kind = int(regs["stim_mode", 0])  # v2's mode: every channel's ChannelKind
    elif declared and ("stim_pattern", output) in regs:
        kind = channel_kind(int(regs["stim_pattern", output]))
    else:
        sense = regs.get(("sense_pulse_height", 0))
        height = regs.get(("pulse_height", 0))
        is_sense = sense is not None and pulse.code == sense and pulse.code != height
        kind = ChannelKind.SENSE if is_sense else ChannelKind.MONO
    return int(pulse_kind_of(kind, pulse.polarity))


def classify(declared: bool, pulses: list[DeliveredPulse], samples: list[IsrSample]) -> list[tuple[int, ...]]:
    """Each pulse's kind per output (:func:`pulse_kind`), from the registers sampled at the interrupt
    entries up to its start (``pulses`` and ``samples`` in the same clock)."""
    order = sorted(range(len(pulses)), key=lambda i: pulses[i].start_us)
    regs: dict[tuple[str, int], int | float] = {}
    out: list[tuple[int, ...]] = [()] * len(pulses)
    j = 0
    for i in order:
        p = pulses[i]
        while j < len(samples) and samples[j].t_us <= p.start_us:
            regs[samples[j].register, samples[j].index] = samples[j].value
            j += 1
        out[i] = tuple(pulse_kind(declared, regs, o, p) for o in p.outputs)
    return out


class HostBuildTimedModel:
    """A host-built firmware tree as a timed model (see the module documentation).

    ``firmware_src``: the PlatformIO tree.  ``board`` / ``switching_boards``: the board around it (the
    compact board: 4 HV513 chips per switching board, sensed by the firmware's own stack detection).
    ``state_map``: which variables hold the registers and which firmware table the tree speaks (default:
    the shipped map whose unit the tree holds).  ``link``: how the host's bytes travel (``usb``, ``uart``
    or a :class:`LinkModel`).  ``event_history_us``: how much of the firmware's raw event record is kept
    (:data:`EVENT_HISTORY_US`).  Other keywords go to :class:`HostBuildEmulator` (``defines``, ``cache``,
    ``compiler``, ``rx_buffer_bytes``, ``chain_outputs``)."""

    def __init__(
        self,
        firmware_src: str | os.PathLike[str],
        board: str | Board = "compact",
        switching_boards: int = 1,
        *,
        state_map: StateMap | None = None,
        link: str | LinkModel = "usb",
        tx_link: str | LinkModel | None = None,
        model: TimingModel | None = None,
        stack_reading: float | None = None,
        event_history_us: float = EVENT_HISTORY_US,
        **host_options: Any,
    ) -> None:
        self.board = board if isinstance(board, Board) else Board(board, switching_boards, stack_reading)
        if self.board.kind == "large":
            # the large board's stack detection: the firmware's #if defined(ETACTILEKIT_BOARD) branch, which
            # wins over the configuration header's own ETACTILEKIT_COMPACT_BOARD (a build of its own key)
            host_options = {"defines": LARGE_BOARD_DEFINES, **host_options}
            if stack_reading is None:
                stack_reading = self.board.reading()
        self.firmware_src = firmware_src
        self.state_map = state_map if state_map is not None else detect(Path(firmware_src))
        self.firmware: FirmwareSpec | None = (
            get_firmware(self.state_map.firmware, "state map firmware")
            if self.state_map is not None and self.state_map.firmware
            else None
        )
        self.model = model if model is not None else DEFAULT_MODEL
        self.link = make_link(link)
        self.tx_link = make_link(tx_link) if tx_link is not None else reply_link(self.link)
        self._stack_reading = None if stack_reading is None else int(stack_reading)
        self._options = host_options
        self.hazards: list[Hazard] = []
        self._losses: list[LossReport] = []
        self.reboots = 0
        self.event_history_us = event_history_us
        self._trimmed_us = 0.0
        self.received_bytes = 0
        self._host_offset = 0
        self._deliveries: list[tuple[int, bytes, int]] = []  # (arrival ns, data, host offset), time order
        self._replies = bytearray()  # reply bytes that have reached the host
        self._tx_flight: deque[tuple[int, int]] = deque()  # (arrival ns, byte) still on the reply link
        self._tx_cursor = (0, 0)  # the firmware's reply writes handed to the link: (write, byte in it)
        self._drops_seen = 0
        self._stopped = False
        self._sinks: list[Any] = []  # trace sinks (:meth:`attach`)
        self._torn: TornPatternWatch | None = None  # this power-up's torn-scan finder (:mod:`.torn`)
        self._landed: list[tuple[int, bytes]] = []  # (host offset, bytes) written, not yet read for it
        self._samples_seen = 0  # interrupt-entry samples already handed to it
        self._scan_regs: dict[tuple[str, int], int | float] = {}  # the registers at the last entry
        self._traced_to_ns = 0  # the sinks hold every event before this (model clock)
        self.boot_ns = 0
        self.now_ns = 0
        self.host = self._power_up()
        self._pulses: list[DeliveredPulse] = []  # the previous power-ups' pulses, in model time
        self._kinds: list[tuple[int, ...]] = []  # their kinds per output

    def _power_up(self) -> HostBuildEmulator:
        host = HostBuildEmulator(
            self.firmware_src,
            hv513_count=self.board.detect_hv513(),
            timing=self.model,
            state_map=self.state_map,
            stack_reading=self._stack_reading,
            **self._options,
        )
        mapped = {r.name for r in host.built.registers}
        for name in KIND_REGISTERS:
            if name in mapped:
                host.watch_at_isr(name)
        self._torn = None
        self._tx_cursor = (0, 0)  # a fresh copy's reply log (bytes on the link still arrive)
        self._drops_read = 0  # the fresh copy's queue drops handed to the torn-scan finder
        self._landed.clear()
        self._samples_seen = 0
        self._scan_regs.clear()
        if self.firmware is not None and {"stim_pattern", "electrode_num"} <= mapped:
            host.watch_at_isr("electrode_num")
            snap = host.state()
            pattern = [int(v) for v in snap["stim_pattern"]]
            self._torn = TornPatternWatch(self.firmware, pattern, int(snap["electrode_num"]))
        return host

    @property
    def reports(self) -> DeliveredReports:
        """The delivered pulses as the campaigns read them.  Made on each use, not kept: a model that holds
        no reference to itself is freed, with its firmware's records, the moment it is dropped, not at the
        next full garbage collection."""
        return DeliveredReports(self)

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
        self._feed_sinks()
        host_us = (target - self.boot_ns) / 1000.0
        if host_us - self._trimmed_us > self.event_history_us:
            self.host.clear_events(host_us - self.event_history_us)
            self._trimmed_us = host_us

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
        if self._torn is not None:
            self._landed.append((offset, data))
        self.received_bytes += len(data)
        self._collect()

    def _collect(self) -> None:
        """Replies the firmware wrote and the queue's drops, into the host's view and the hazard list."""
        self.host.read()  # (the bytes travel as the firmware's reply log has them, below)
        self._send_replies()
        drops = self.host.rx_drops
        for d in drops[self._drops_seen :]:
            t_us = d.t_us + self.boot_us
            self._losses.append(
                LossReport(t_us, d.host_offset, d.count, b"", "queue_full", d.queued, self.parser_status())
            )
            detail = {"bytes": d.count, "host_offset": d.host_offset, "reason": "queue_full"}
            self._mark(int(round(t_us * 1000)), "loss", detail)
            self.hazards.append(
                Hazard(
                    HazardKind.QUEUE_OVERFLOW,
                    d.host_offset,
                    {"bytes_lost": d.count, "host_offset": d.host_offset, "parser": self.parser_status()},
                    t_us,
                )
            )
        self._drops_seen = len(drops)
        if self._torn is not None:
            self._find_torn()

    def _find_torn(self) -> None:
        """Hand the torn-scan finder the bytes the queue kept and the scans' registers, and record what it
        finds as ``torn_pattern`` hazards (see :mod:`.torn`)."""
        watch = self._torn
        assert watch is not None
        if self._landed:
            arrived = sum(len(d) for _o, d in self._landed) - self.host.rx_in_flight
            drops = self.host.rx_drops
            while self._landed and len(self._landed[0][1]) <= arrived:
                offset, data = self._landed.pop(0)
                arrived -= len(data)
                end = offset + len(data)
                # the queue drops bytes as they land, in the host's order: one pass over the drops in all
                cut = []
                while self._drops_read < len(drops) and drops[self._drops_read].host_offset < end:
                    d = drops[self._drops_read]
                    cut.append((d.host_offset, d.host_offset + d.count))
                    self._drops_read += 1
                kept = (
                    data
                    if not cut
                    else bytes(
                        b for i, b in enumerate(data, offset) if not any(lo <= i < hi for lo, hi in cut)
                    )
                )
                if kept:
                    watch.read(kept, offset)
        samples = self.host.isr_samples()
        regs = self._scan_regs
        i = self._samples_seen
        while i < len(samples):
            t_us = samples[i].t_us
            while i < len(samples) and samples[i].t_us == t_us:
                regs[samples[i].register, samples[i].index] = samples[i].value
                i += 1
            n = int(regs.get(("electrode_num", 0), 0))
            pattern = [int(regs.get(("stim_pattern", ch), 0)) for ch in range(n)]
            reads = int(regs.get(("stim_mode", 0), 0)) < 2  # v2's mode 2 uses no height
            watch.scan(t_us, pattern, n, reads)
        self._samples_seen = i
        for torn in watch.torn:
            detail = {
                "scan_start_us": torn.t_us + self.boot_us,
                "command_host_offset": torn.command_host_offset,
                "new_channels": torn.new_channels,
                "new_channels_up_to": torn.new_channels_up_to,
                "channels": torn.channels,
                "changed": [list(c) for c in torn.changed],
            }
            self.hazards.append(
                Hazard(HazardKind.TORN_PATTERN, torn.command_host_offset, detail, torn.t_us + self.boot_us)
            )
        watch.torn.clear()

    def next_event_us(self, scans: bool = True) -> float:
        """When the model next needs running: a delivery landing, the stimulation timer's alarm (with
        ``scans``), and at the latest :data:`POLL_US` from now (replies are found by running the code)."""
        t = self.now_us + POLL_US
        if self._deliveries:
            t = min(t, self._deliveries[0][0] / 1000.0)
        if self._tx_flight:
            t = min(t, self._tx_flight[0][0] / 1000.0)
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
                while self._tx_flight and self.now_ns < end:  # and its way back
                    self.advance_to(min(end, self._tx_flight[-1][0]) / 1000.0)
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

    def _send_replies(self) -> None:
        """Put the firmware's new reply writes on the reply link, each byte at the time of its write, and
        hand the host the bytes that have arrived by now, as the Python models' replies travel."""
        log = self.host.tx_log
        i, k = self._tx_cursor
        while i < len(log):
            t_us, data = log[i]
            if k < len(data):  # (a write at the same time as the last one extends its entry)
                part = data[k:]
                times = self.tx_link.arrival_times(part, round(t_us * 1000) + self.boot_ns)
                self._tx_flight.extend(zip(times.tolist(), part))
            if i == len(log) - 1:
                k = len(data)
                break
            i, k = i + 1, 0
        self._tx_cursor = (i, k)
        flight = self._tx_flight
        while flight and flight[0][0] <= self.now_ns:
            self._replies.append(flight.popleft()[1])

    def read_tx(self, size: int | None = None) -> bytes:
        """Reply bytes that have reached the host by now, over the reply link (all, or at most ``size``)."""
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
        # the firmware's variables as its own types: the shim reads every one as a double
        variables: dict[str, Any] = {
            name: [int(v) for v in value] if isinstance(value, list) else int(value)
            for name, value in snap.items()
        }
        variables["period_us"] = float(snap["period_us"])
        variables.setdefault("timer_alarm_ticks", 0)  # no interrupt attached yet
        return BoardState.from_variables(
            self.firmware,
            variables,
            rx_pending=int(snap["rx_pending"]),
            # what the queue dropped is the board's state where the firmware's parser owns the queue (v2)
            rx_dropped=int(snap["rx_dropped"]) if model_entry(self.firmware).parser_owns_queue else None,
        )

    @property
    def commands(self) -> list[Any]:
        """The commands the parser completed, as the Python model records them: none here (the firmware's
        parser keeps its progress in function-local statics), so no command is counted out of step."""
        return []

    def parser_status(self) -> str:
        snap = self.host.state()
        if "command_in_progress" in snap:  # the map reads the parser's function-local static
            return "reading a command's payload" if snap["command_in_progress"] else "between commands"
        return "not readable (the firmware keeps its parser's progress in function-local statics)"

    # --- power, faults, history ---------------------------------------------------------------------------

    def reset(self, reason: str = "reset") -> None:
        """Power-cycle: a fresh copy of the firmware boots now; bytes on the link still land."""
        self._feed_sinks()
        self._mark(self.now_ns, "reset", {"reason": reason})
        for p, kinds in self._current_classified():
            self._pulses.append(p)
            self._kinds.append(kinds)
        if self._torn is not None:
            self._torn.close()
        self.host = self._power_up()
        self._trimmed_us = 0.0
        self.boot_ns = self.now_ns
        self._drops_seen = 0
        self._stopped = False
        self.reboots += 1

    def stop_reading(self) -> None:
        """The main loop stops reading until a reset, as the Python model's does: the firmware's reads find
        nothing from now on (it keeps polling, its interrupt keeps scanning), the host's bytes still fill
        the receive queue and are dropped when it is full."""
        self.host.set_reading(False)

    def discard_history(self, before_us: float) -> None:
        """Forget recorded events before ``before_us`` (delivered pulses are kept: safety reads them)."""
        self._feed_sinks()
        self.host.clear_events()

    def attach(self, sink: Any) -> None:
        """Send the firmware's pin and DAC events and the link's markers (bytes lost, resets) from now on to
        ``sink`` (see :mod:`~tactdeform_hw.emulator.records.trace`), as the Python models send their scans.

        The events are the firmware's own writes in the golden traces' conventions
        (:meth:`.emulator.HostBuildEmulator.events`): BL, LE, POL, CLK and DIN on the board's pins, and the
        DAC code.  SEL and ADC are the Python models' readings of the HV513 chain and the ADC; a host build
        has no such reading, so they keep their power-on levels.  Events reach the sink as the model's clock
        passes them, in time order, before the history they come from is trimmed."""
        if not self.host.pin_events:
            raise ConfigurationError("attach: this host build keeps no pin events (pin_events=False)")
        self._sinks.append(sink)
        if len(self._sinks) == 1:
            self._traced_to_ns = self.now_ns
        if hasattr(sink, "begin"):
            sink.begin(self.now_ns)

    def detach(self, sink: Any) -> None:
        """Stop sending to ``sink``, after handing it every event up to now."""
        if sink in self._sinks:
            self._feed_sinks()
            self._sinks.remove(sink)

    def _mark(self, t_ns: int, kind: str, detail: dict[str, Any]) -> None:
        for s in self._sinks:
            s.marker(t_ns, kind, detail)

    def _feed_sinks(self) -> None:
        """Every event of the running firmware from where the sinks stand to now, as one
        :class:`~..records.reports.EventRun` (events in the model's clock)."""
        if not self._sinks or self.now_ns <= self._traced_to_ns:
            return
        since_us = max(0.0, (self._traced_to_ns - self.boot_ns) / 1000.0)
        until_ns = self.now_ns - self.boot_ns
        rows = [e for e in self.host.events(since_us) if e[0] * 1000.0 < until_ns]
        self._traced_to_ns = self.now_ns
        t_ns: list[int] = []
        sig: list[int] = []
        val: list[int] = []
        for t_us, kind, pin, value in rows:
            s = Signal.DAC if kind == "DAC" else _PIN_SIGNALS.get(pin)
            if s is not None:
                t_ns.append(int(round(t_us * 1000.0)) + self.boot_ns)
                sig.append(int(s))
                val.append(int(value))
        if not t_ns:
            return
        start = t_ns[0]
        run = EventRun(
            start,
            t_ns[-1] - start,
            (np.asarray(t_ns, np.int64) - start, np.asarray(sig, np.int64), np.asarray(val, np.int64)),
        )
        for s in self._sinks:
            s.scan_run(run)

    # --- records ------------------------------------------------------------------------------------------

    def _shifted(self, pulses: list[DeliveredPulse]) -> list[DeliveredPulse]:
        b = self.boot_us
        if b == 0:
            return pulses
        return [DeliveredPulse(p.start_us + b, p.end_us + b, p.code, p.outputs, p.polarity) for p in pulses]

    def _current_classified(self) -> list[tuple[DeliveredPulse, tuple[int, ...]]]:
        own = self.host.delivered_pulses()
        kinds = classify(self.firmware is not None, own, self.host.isr_samples())
        return list(zip(self._shifted(own), kinds))

    def classified_pulses(self) -> list[tuple[DeliveredPulse, tuple[int, ...]]]:
        """Every delivered pulse (model time) with its :class:`PulseKind` per output (:func:`classify`)."""
        return list(zip(self._pulses, self._kinds)) + self._current_classified()

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


def realtime_host_build(
    firmware_src: str | os.PathLike[str],
    board: str = "compact",
    switching_boards: int = 1,
    *,
    rules: Any = None,
    state_map: StateMap | None = None,
    stack_reading: float | None = None,
    cls: Any = None,
) -> Any:
    """The tree built on this machine as a board on the wall clock: a :class:`HostBuildTimedModel` on the
    serving rules' link and timing (``rules``: a :class:`~..serving.realtime.BuildRules`, default the USB
    build's) inside a :class:`~..serving.realtime.RealtimeEmulator` (or ``cls``, a subclass of it)."""
    from tactdeform_hw.emulator.serving.realtime import SERIAL_USB, RealtimeEmulator

    rules = SERIAL_USB if rules is None else rules
    model = HostBuildTimedModel(
        firmware_src,
        board,
        switching_boards,
        state_map=state_map,
        stack_reading=stack_reading,
        link=rules.make_link(),
        model=rules.timing(None),
    )
    return (cls or RealtimeEmulator)(rules=rules, timed=model)  # type: ignore[arg-type]


def host_build_timed(firmware_src: str | os.PathLike[str], *args: Any, **kwargs: Any) -> HostBuildTimedModel:
    """:class:`HostBuildTimedModel` (the same arguments)."""
    return HostBuildTimedModel(firmware_src, *args, **kwargs)


__all__ = [
    "BOARD_STATE_REGISTERS",
    "KIND_REGISTERS",
    "LARGE_BOARD_DEFINES",
    "DeliveredReports",
    "HostBuildTimedModel",
    "classify",
    "host_build_timed",
    "pulse_kind",
    "realtime_host_build",
]
