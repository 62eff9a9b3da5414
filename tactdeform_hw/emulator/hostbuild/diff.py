"""The firmware differential: one firmware tree, built on the host, against another tree or the Python model.

Both sides are fed the same :class:`~.streams.Stream` (writes at virtual times) and observed at
checkpoints (before each write and at the stream's end): the firmware's registers under the golden
vectors' names, the reply bytes, and the pulses the board delivered (those ended a margin before the
checkpoint, so a pulse crossing it is compared at the next one).  The first difference is a
:class:`Divergence`; :func:`shrink` then drops writes, runs of bytes and single bytes while the same
difference persists, leaving a minimal reproduction.

Against another tree everything is compared exactly (the same shim, the same costs).  Against the Python
model (``v1.2``: :class:`~..timed.model_v1_2.TimedEmulator`, ``v2``: :class:`~..timed.model_v2.
TimedEmulatorV2`) the comparison is made modulo the named, documented equivalences of :data:`EQUIVALENCES`
and nothing else; each report lists the ones it applied.
"""

from __future__ import annotations

import bisect
import dataclasses
import itertools
import math
import multiprocessing
import time
from collections import deque
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import Executor, Future, ProcessPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, ClassVar, Protocol

import numpy as np

from tactdeform_hw.emulator.hostbuild.build import build
from tactdeform_hw.emulator.hostbuild.emulator import USB_PACKET_BYTES, HostBuildEmulator
from tactdeform_hw.emulator.hostbuild.statemap import StateMap, detect
from tactdeform_hw.emulator.hostbuild.streams import SETUP_US, Stream, edge_streams, random_stream
from tactdeform_hw.emulator.timed.link import Delivery, LinkModel
from tactdeform_hw.emulator.timed.timing import DEFAULT_MODEL, TimingModel
from tactdeform_hw.errors import ConfigurationError, FirmwareBuildError, LimitError
from tactdeform_hw.protocol.commands import STIM_MODE_BIPHASIC
from tactdeform_hw.protocol.firmware import FIRMWARES, V1_2, V2, FirmwareSpec

MODELS = tuple(FIRMWARES)

EQUIVALENCES: dict[str, str] = {
    "timer-origin": "the firmware starts its stimulation timer after setup() (1010.25 us: the stack "
    "detection); the model's timer_start_us is set to the time the host build measured (both versions)",
    "setup-before-bytes": "the host's first byte arrives at 2000 us, after the firmware's setup(); the "
    "model's parser runs from 0",
    "readings": "the model runs under the host build's readings of what the firmware's code leaves open "
    "(TimingModel.cs_writes_costed, v2's firmware_scan.HOST_BUILD): each chip-select write around an SPI "
    "exchange costs one GPIO write on top of the 6.6 us exchange (0.1 us each), as the shim's digitalWrite "
    "does; the package's default reading puts them inside the exchange (a pulse 0.2 us shorter). Pulse "
    "widths and starts are then compared exactly (pulse_tolerance_us 0)",
    "pulse-numbering": "when scans overrun (the next alarm is due before a scan returns), the firmware runs "
    "them back to back: on the host build a pulse is numbered within its run of back-to-back scans, in the "
    "models by its slot within its run (every pulse the scans make counts, those of channels past the "
    "chain's outputs included; on v2 a channel has a slot per phase, those of zero height included), so a "
    "run's n-th pulse is compared with the other side's n-th, and a pulse_tolerance_us given on the command "
    "line allows the n-th a start (n + 1) times that late",
    "adc-reads-skin": "the host build's ADC reads the DAC code, the model's the skin's voltage: the "
    "voltage registers are not compared, and a stream holding the readback opcode has its replies "
    "compared by byte count",
    "rx-unread": "the receive queue is compared as the bytes that arrived and were not read yet "
    "(rx_unread): the host build moves arrived bytes into its queue at the firmware's next call "
    "(rx_pending + rx_in_flight), v2's model hands them to its parser only when it calls it",
    "tick-ties": "no write arrives exactly on an RTOS tick: at a tie the host build delivers the bytes "
    "before the main loop wakes, the model wakes the loop first (a convention of each)",
    "watchdog": "the host build does not model the interrupt watchdog: a stream is compared up to the "
    "last checkpoint before the model's watchdog resets the board (the report counts these streams)",
    "call-resolution": "the model applies a parser call's effects (registers, the receive queue, v1.2's "
    "logged reply) at the call's start, the firmware as its code reads and stores: a state or reply "
    "difference seen at a checkpoint that is gone by CALL_WINDOW_US (the longest parser call) later, with "
    "no difference in between outlasting it, is this resolution (the report counts these streams); one "
    "still there then is reported as it was first seen (gone: that register, or that element of an "
    "array, or the replies, the same on both sides, or the firmware's register at the value the model "
    "showed: the call is over on the firmware too; another difference then is a later call's, held "
    "with a window of its own; the model also lands arrived bytes, and counts those the full queue "
    "drops, at its next call; the window is the firmware's main-loop time: a scan that pre-empts the call "
    "stretches it by the scan's length, unless scans then run back to back)",
    "registers-in-common": "only registers both sides hold are compared (the host build's receive-queue "
    "counters have no counterpart; command_in_progress, which only v2's map reads, is the parser's progress "
    "flag, which the model sets at a call's start: call-resolution)",
}
"""What a comparison against the Python model is made modulo (none apply between two trees)."""

CALL_WINDOW_US = (
    DEFAULT_MODEL.parser_call_us
    + DEFAULT_MODEL.rx_queue_bytes * DEFAULT_MODEL.parser_byte_us
    + DEFAULT_MODEL.hv513_detect_us
)
"""Against the model: the longest a parser call can take (its overhead, a full receive queue read a byte at
a time, and 0xF5's stack detection): a state or reply difference that is gone by this long after it was
seen is the model showing the call's effects from its start (see EQUIVALENCES["call-resolution"])."""

STATE_MAP_FILE = "hostbuild_state.toml"
"""A tree's own state map, by convention at its root (``tests/data/firmware_tiny`` has one)."""

PULSE_TOLERANCE_US = 0.0
"""Against the model: pulse widths and starts agree exactly (the model runs under the host build's readings,
EQUIVALENCES["readings"]); ``--pulse-tolerance-us`` loosens it, to compare a tree whose shim costs differ."""

PULSE_MARGIN_US = 500.0
"""A pulse is compared once it ended this long before a checkpoint (on either side): its counterpart may
start later by the drift :data:`PULSE_TOLERANCE_US` allows, and must have ended by the checkpoint."""

STALL_CALLS = 2_000_000
"""Shim calls without time passing after which a side is declared stuck (the outcome is compared)."""


Pulse = tuple[float, float, int, tuple[int, ...], int, int]
"""A delivered pulse: start µs, end µs, DAC code, outputs, polarity (1 anodic), its index within its scan
(on the host build: within its run of back-to-back scans, see :meth:`HostSide._pulses`)."""


def _number_in_scans(pulses: list[tuple[float, float, int, tuple[int, ...], int, int]]) -> list[Pulse]:
    """Replace the scan number (last field) by the pulse's index within that scan."""
    out: list[Pulse] = []
    last, k = None, 0
    for p in sorted(pulses):
        k = k + 1 if p[5] == last else 0
        last = p[5]
        out.append((*p[:5], k))
    return out


@dataclass
class Observation:
    """What a side shows at a checkpoint."""

    state: dict[str, Any]
    replies: bytes
    pulses: list[Pulse]
    stuck: str | None = None
    reset: bool = False  # the model's interrupt watchdog has reset the board


class Side(Protocol):
    name: str

    def write(self, data: bytes, at_us: float) -> None: ...

    def advance_to(self, t_us: float) -> None: ...

    def observe(self, upto_us: float) -> Observation: ...

    def close(self) -> None: ...


class HostSide:
    """A firmware tree built on the host (keeping no pin events: its delivered pulses are decoded in the
    shim)."""

    def __init__(self, tree: Path, *, name: str, state_map: StateMap | None, **kw: Any) -> None:
        self.name = name
        self.emu = HostBuildEmulator(
            tree, state_map=state_map, stall_calls=STALL_CALLS, pin_events=False, **kw
        )
        self.stuck: str | None = None

    @property
    def timer_origin_us(self) -> float | None:
        """When the firmware first enabled a timer alarm (its stimulation timer's start)."""
        return self.emu.first_event_us("ALARM_ENABLE")

    def close(self) -> None:
        self.emu.close()

    def write(self, data: bytes, at_us: float) -> None:
        if self.stuck is None:
            self.advance_to(at_us)
        if self.stuck is None:
            self.emu.write(data, at_us=at_us)

    def advance_to(self, t_us: float) -> None:
        if self.stuck is not None or t_us <= self.emu.now_us:
            return
        try:
            self.emu.advance_to(t_us)
        except FirmwareBuildError as exc:
            if "without time passing" not in str(exc):
                raise
            self.stuck = f"stuck at {self.emu.firmware_now_us:.3f} us (a loop on calls that cost no time)"

    def observe(self, upto_us: float) -> Observation:
        st = self.emu.state()
        st["rx_unread"] = st["rx_pending"] + st["rx_in_flight"]
        replies = b"".join(b for _, b in self.emu.tx_log)
        return Observation(st, replies, _number_in_scans(self._pulses(upto_us)), self.stuck)

    def scanning_us(self, since_us: float, upto_us: float) -> tuple[float, int]:
        """How long the firmware spent in its interrupt handlers between ``since_us`` and ``upto_us`` (a
        handler still running counts up to ``upto_us``), time a pre-empted parser call does not advance in
        (see EQUIVALENCES["call-resolution"]), and how many handlers it entered meanwhile."""
        total, entered, entry = 0.0, 0, None
        for e in self.emu.shim_events():
            if e.kind == "ISR_ENTER":
                entry = e.t_us
                entered += since_us <= e.t_us < upto_us
            elif e.kind == "ISR_RETURN" and entry is not None:
                total += max(0.0, min(e.t_us, upto_us) - max(entry, since_us))
                entry = None
        if entry is not None:
            total += max(0.0, upto_us - max(entry, since_us))
        return total, entered

    def _pulses(self, upto_us: float) -> list[tuple[float, float, int, tuple[int, ...], int, int]]:
        """The delivered pulses ended by ``upto_us``, each with the number of its run of scans, read from the
        shim's columns.  A run is a scan its alarm started and the scans that followed it back to back (an
        overrun: the next alarm was due before the scan returned, so the next scan starts at its return):
        a cost one side counts and the other does not (a tree's own shim costs, compared with
        ``--pulse-tolerance-us``) accumulates along such a run as along one scan
        (see EQUIVALENCES["pulse-numbering"])."""
        arr = self.emu.delivered_arrays()
        start_us, end_us = arr.start_ns / 1000.0, arr.end_ns / 1000.0
        keep = np.flatnonzero(end_us <= upto_us)
        scans = self.emu.scans()
        entries = np.array(
            [a for i, (a, _) in enumerate(scans) if i == 0 or a != scans[i - 1][1]], dtype=np.float64
        )
        scan = np.searchsorted(entries, start_us[keep], side="right")
        offsets, outputs = arr.offsets.tolist(), arr.outputs.tolist()
        return [
            (s, e, code, tuple(outputs[offsets[i] : offsets[i + 1]]), pol, n)
            for i, s, e, code, pol, n in zip(
                keep.tolist(),
                start_us[keep].tolist(),
                end_us[keep].tolist(),
                arr.code[keep].tolist(),
                arr.polarity[keep].tolist(),
                scan.tolist(),
            )
        ]


class DirectLink(LinkModel):
    """The host build's receive path: a write reaches the queue at its own time, in 64-byte packets (no USB
    frames).  The model is given the same, so both sides see the same arrivals."""

    name = "direct"

    def schedule(self, data: bytes, t_ns: int, host_offset: int = -1) -> list[Delivery]:
        return [
            Delivery(
                t_ns, bytes(data[i : i + USB_PACKET_BYTES]), host_offset + i if host_offset >= 0 else -1, t_ns
            )
            for i in range(0, len(data), USB_PACKET_BYTES)
        ]

    def wire_ns(self, nbytes: int) -> int:
        return 0


class ModelSide:
    """The package's Python timed model of one firmware version (a subclass per version)."""

    version = ""
    readings: ClassVar[dict[str, Any]] = {"cs_writes_costed": True}
    """The model's readings of what the firmware's code leaves open (``TimingModel``'s ``cs_writes_costed``,
    ``dac_load``), taken as the host build's shim takes them, so both sides time the same statements alike
    and a difference is the code's, not a reading's."""

    def __init__(self, *, timer_origin_us: float, hv513_count: int) -> None:
        self.name = f"model {self.version}"
        model = dataclasses.replace(DEFAULT_MODEL, timer_start_us=timer_origin_us, **self.readings)
        self.emu: Any = self._make(max(1, hv513_count // 4), model)
        self.timer_origin_us = timer_origin_us

    def _make(self, boards: int, model: TimingModel) -> Any:
        raise NotImplementedError

    def write(self, data: bytes, at_us: float) -> None:
        if at_us > self.emu.now_us:
            self.emu.advance_to(at_us)
        self.emu.write(data, at_us=at_us)

    def advance_to(self, t_us: float) -> None:
        if t_us > self.emu.now_us:
            self.emu.advance_to(t_us)

    def close(self) -> None:
        """Nothing to release: the model is plain Python."""

    def observe(self, upto_us: float) -> Observation:
        st = self.emu.state().as_dict()
        st["rx_unread"] = st["rx_pending"] + self.emu.in_flight
        return Observation(st, self._replies(upto_us), self._numbered(upto_us), None, self.emu.reboots > 0)

    def _numbered(self, upto_us: float) -> list[Pulse]:
        """The delivered pulses ended by ``upto_us``, each numbered within its scan."""
        return _number_in_scans(self._pulses(upto_us))

    def _replies(self, upto_us: float) -> bytes:
        raise NotImplementedError

    def _pulses(self, limit_us: float) -> list[tuple[float, float, int, tuple[int, ...], int, int]]:
        raise NotImplementedError


class ModelSideV1_2(ModelSide):
    """:class:`~..timed.model_v1_2.TimedEmulator`: its timer starts at ``timer_start_us``."""

    version = "v1.2"

    def _make(self, boards: int, model: TimingModel) -> Any:
        from tactdeform_hw.emulator.timed.model_v1_2 import TimedEmulator

        return TimedEmulator("compact", boards, link=DirectLink(), tx_link=DirectLink(), model=model)

    def _replies(self, upto_us: float) -> bytes:
        """The replies written by ``upto_us`` (a parser call's reply is logged at its start, stamped with
        the time the call writes it)."""
        return b"".join(b for t, b in self.emu.tx_log if t <= upto_us)

    def _numbered(self, upto_us: float) -> list[Pulse]:
        """The delivered pulses numbered by their pulse slot within their run of back-to-back scans: every
        pulse the scans make counts, those of channels past the chain's outputs included (they go nowhere,
        but their SPI exchanges cost the same: see EQUIVALENCES["pulse-numbering"])."""
        return sorted(self._pulses(upto_us))

    def _run_offsets(self) -> dict[int, tuple[int, int, int]]:
        """Per stretch of scans (by its first scan's index): the slots of its run's scans before it, the
        slots of each of its scans, and whether its own scans run back to back."""
        out: dict[int, tuple[int, int, int]] = {}
        prev_end, carried = -1, 0
        for run in self.emu.runs:
            slots = int(run.template.pulses.channel.size)
            before = carried if run.start_ns == prev_end else 0
            chained = int(run.stride_ns == run.duration_ns)
            out[run.first_index] = (before, slots, chained)
            carried = before + run.count * slots if chained else (before if run.count == 1 else 0) + slots
            prev_end = run.end_ns
        return out

    def _pulses(self, limit_us: float) -> list[tuple[float, float, int, tuple[int, ...], int, int]]:
        """The pulses of a non-zero code through at least one output, ended by ``limit_us`` (read from the
        reports' columns: no report object per pulse), each numbered by :meth:`_numbered`'s slots."""
        reports = self.emu.reports
        t = reports.pulse_table(t1_us=limit_us)
        end_us = t["start_us"] + t["width_us"]
        keep = (t["code"] > 0) & (end_us <= limit_us)
        slot = self._slots(t["cycle"], t["start_us"])
        outputs_of = reports.outputs_lookup()
        out: list[tuple[float, float, int, tuple[int, ...], int, int]] = []
        col = {k: t[k][keep].tolist() for k in ("start_us", "code", "pol", "cycle", "channel", "output")}
        for start, end, code, pol, cycle, channel, output, n_out, n in zip(
            col["start_us"],
            end_us[keep].tolist(),
            col["code"],
            col["pol"],
            col["cycle"],
            col["channel"],
            col["output"],
            t["n_outputs"][keep].tolist(),
            slot[keep].tolist(),
        ):
            outputs = outputs_of(int(cycle), int(channel), int(output), int(n_out))
            if outputs:
                out.append((float(start), float(end), int(code), tuple(outputs), int(bool(pol)), int(n)))
        return out

    def _slots(self, cycle: np.ndarray, start_us: np.ndarray) -> np.ndarray:
        """Each pulse's slot within its run of back-to-back scans: its rank among all its scan's pulses
        plus the slots of the run's earlier scans."""
        if cycle.size == 0:
            return np.zeros(0, dtype=np.int64)
        order = np.lexsort((start_us, cycle))
        cyc = cycle[order].astype(np.int64)
        first = np.r_[True, cyc[1:] != cyc[:-1]]
        group_start = np.maximum.accumulate(np.where(first, np.arange(cyc.size), 0))
        rank = np.arange(cyc.size) - group_start
        runs = self._run_offsets()
        firsts = np.array(sorted(runs), dtype=np.int64)
        table = np.array([runs[f] for f in firsts.tolist()], dtype=np.int64).reshape(-1, 3)
        i = np.searchsorted(firsts, cyc, side="right") - 1
        known = i >= 0
        i = np.maximum(i, 0)
        f, (before, slots, chained) = firsts[i], table[i].T
        later = cyc - f
        base = np.where(chained == 1, before + later * slots, np.where(later == 0, before, 0))
        base = np.where(known, base, 0)
        out = np.empty(cyc.size, dtype=np.int64)
        out[order] = base + rank
        return out


class ModelSideV2(ModelSide):
    """:class:`~..timed.model_v2.TimedEmulatorV2`: it starts its timer at boot whatever
    ``timer_start_us`` says, so its pulses are moved by the timer origin instead; it keeps no reply log,
    so the replies are those that reached the host (no reply link: at once)."""

    version = "v2"

    def _make(self, boards: int, model: TimingModel) -> Any:
        from tactdeform_hw.emulator.timed.model_v2 import TimedEmulatorV2

        self._got = bytearray()
        from tactdeform_hw.emulator.firmware.firmware_scan import HOST_BUILD

        return TimedEmulatorV2(
            "compact", boards, link=DirectLink(), tx_link=DirectLink(), model=model, conventions=HOST_BUILD
        )

    def _replies(self, upto_us: float) -> bytes:
        self._got += self.emu.read_tx()
        return bytes(self._got)

    def _numbered(self, upto_us: float) -> list[Pulse]:
        """The delivered pulses numbered by their slot within their run of back-to-back scans (see
        :meth:`_pulses`)."""
        return sorted(self._pulses(upto_us))

    def _pulses(self, limit_us: float) -> list[tuple[float, float, int, tuple[int, ...], int, int]]:
        """The pulses of a non-zero code ended by ``limit_us``, each numbered by its slot within its run of
        back-to-back scans (a scan that starts at the previous one's end continues the run).  Every pulse
        the scans make has a slot, those of zero height and of channels past the chain's outputs included:
        they deliver nothing, but the firmware's ``DAAD`` calls for them cost the same (two exchanges a
        slot: see EQUIVALENCES["pulse-numbering"]).  A channel
        has one slot per phase: two in mode 1 (``biPhasicPulse``), one otherwise."""
        out: list[tuple[float, float, int, tuple[int, ...], int, int]] = []
        base, prev_end, prev_slots = 0, -1, 0
        for scan in self.emu.scans:  # the model starts its timer at timer_start_us itself, as v1.2's
            base = base + prev_slots if scan.start_ns == prev_end else 0
            phases = 2 if scan.stim_mode == STIM_MODE_BIPHASIC else 1
            prev_end, prev_slots = scan.end_ns, scan.electrode_num * phases
            seen: dict[int, int] = {}
            for channel, onset_ns, code, width_ns, pol in scan.pulses:  # as delivered() reads them
                phase = seen.get(channel, 0)
                seen[channel] = phase + 1
                t = (scan.start_ns + onset_ns) / 1000
                end = t + width_ns / 1000
                if code > 0 and end <= limit_us:
                    slot = base + channel * phases + min(phase, phases - 1)
                    out.append((t, end, code, (channel,), int(bool(pol)), slot))
        return out


MODEL_SIDES: dict[str, type[ModelSide]] = {"v1.2": ModelSideV1_2, "v2": ModelSideV2}
"""The Python model of each firmware version, by the name ``--against`` takes."""


@dataclass(frozen=True)
class Divergence:
    """The first difference between the two sides on one stream."""

    kind: str  # "state", "replies", "pulses", "stuck"
    field: str  # the register, "replies", "pulse N" or "stuck"
    at_us: float  # the checkpoint where it shows (the pulse's start for pulses, the reply's time if known)
    since_us: float  # the previous checkpoint: it arose in (since_us, at_us]
    left: Any
    right: Any
    delivered: bytes  # the host's bytes written by at_us

    @property
    def signature(self) -> tuple[str, str]:
        if self.kind == "state":
            return (self.kind, self.field.split("[")[0])
        if self.kind == "pulses":  # what differs: outputs, code, polarity, start, width or count
            return (self.kind, self.field.split("(")[-1].rstrip(")"))
        return (self.kind, self.kind)

    def to_dict(self) -> dict[str, Any]:
        return {
            "kind": self.kind,
            "field": self.field,
            "at_us": self.at_us,
            "since_us": self.since_us,
            "left": _jsonable(self.left),
            "right": _jsonable(self.right),
            "delivered_hex": self.delivered.hex(),
        }


def _jsonable(v: Any) -> Any:
    if isinstance(v, bytes):
        return v.hex()
    if isinstance(v, tuple):
        return [_jsonable(x) for x in v]
    if isinstance(v, list):
        return [_jsonable(x) for x in v]
    return v


@dataclass(frozen=True)
class Comparison:
    """How the two sides are compared."""

    exact: bool
    spec: FirmwareSpec | None
    pulse_tolerance_us: float = 0.0

    @property
    def equivalences(self) -> tuple[str, ...]:
        return () if self.exact else tuple(EQUIVALENCES)


def _same_number(key: str, a: Any, b: Any, exact: bool) -> bool:
    if not exact and key == "period_us" and isinstance(a, (int, float)) and isinstance(b, (int, float)):
        import numpy as np

        return bool(np.float32(a) == np.float32(b))
    return bool(a == b)


_NOT_COMPARED_MODEL = {
    "voltage",
    "voltage_bytes",
    "command_in_progress",
    "rx_pending",
    "rx_in_flight",
    "rx_capacity",
}


def compare(
    left: Observation,
    right: Observation,
    cmp: Comparison,
    stream_has_readback: bool,
    upto_us: float = math.inf,
) -> tuple[str, str, Any, Any, float | None] | None:
    """The first difference between two observations made at ``upto_us``: (kind, field, left, right, time
    if known).  The pulses compared are those either side ended :data:`PULSE_MARGIN_US` (or the drift their
    start is allowed, if more) before ``upto_us``; their counterparts on the other side may have ended any
    time before ``upto_us``."""
    if left.stuck != right.stuck:
        return ("stuck", "stuck", left.stuck, right.stuck, None)
    keys = [k for k in left.state if k in right.state or cmp.exact]
    if not cmp.exact:
        keys = [k for k in keys if k not in _NOT_COMPARED_MODEL]
    for k in keys:
        a, b = left.state.get(k), right.state.get(k)
        if isinstance(a, list) and isinstance(b, list) and len(a) == len(b):
            for i, (x, y) in enumerate(zip(a, b)):
                if x != y:
                    return ("state", f"{k}[{i}]", x, y, None)
        elif not _same_number(k, a, b, cmp.exact):
            return ("state", k, a, b, None)
    if cmp.exact or not stream_has_readback:
        if left.replies != right.replies:
            shorter = min(len(left.replies), len(right.replies))
            i = next((j for j, (x, y) in enumerate(zip(left.replies, right.replies)) if x != y), shorter)
            return ("replies", f"replies[{i}]", left.replies[i : i + 16], right.replies[i : i + 16], None)
    elif len(left.replies) != len(right.replies):
        return ("replies", "replies (count)", len(left.replies), len(right.replies), None)
    tol = cmp.pulse_tolerance_us
    # a pulse's counterpart must exist once the checkpoint is past the pulse's end by the margin, or by the
    # drift its start may have (a long run of back-to-back scans, see EQUIVALENCES["pulse-numbering"])
    n = max(
        sum(1 for p in side.pulses if p[1] + max(PULSE_MARGIN_US, tol * (2 + p[5])) <= upto_us)
        for side in (left, right)
    )
    for i, (p, q) in enumerate(zip(left.pulses[:n], right.pulses[:n])):
        if (
            p[2:5] != q[2:5]
            or abs(p[0] - q[0]) > tol * (1 + max(p[5], q[5])) + 1e-9
            or abs((p[1] - p[0]) - (q[1] - q[0])) > tol + 1e-9
        ):
            return (
                "pulses",
                f"pulse {i} ({_pulse_reason(p, q, tol)})",
                _pulse(p),
                _pulse(q),
                min(p[0], q[0]),
            )
    if min(len(left.pulses), len(right.pulses)) < n:
        i = min(len(left.pulses), len(right.pulses))
        more = left.pulses if len(left.pulses) > i else right.pulses
        lp = _pulse(left.pulses[i]) if len(left.pulses) > i else None
        rp = _pulse(right.pulses[i]) if len(right.pulses) > i else None
        return ("pulses", f"pulse {i} (count)", lp, rp, more[i][0])
    return None


def _pulse_reason(p: Pulse, q: Pulse, tol: float) -> str:
    for name, i in (("outputs", 3), ("code", 2), ("polarity", 4)):
        if p[i] != q[i]:
            return name
    return "start" if abs(p[0] - q[0]) > tol * (1 + max(p[5], q[5])) + 1e-9 else "width"


def _pulse(p: Pulse) -> dict[str, Any]:
    return {
        "start_us": round(p[0], 3),
        "width_us": round(p[1] - p[0], 3),
        "code": p[2],
        "outputs": list(p[3]),
        "polarity": p[4],
        "index_in_scan": p[5],
    }


@dataclass
class Differ:
    """Makes the two sides for each run: ``left`` is always a host-built tree, ``right`` another tree or a
    model version."""

    tree: Path
    against: str  # "v1.2", "v2" or a tree path
    hv513_count: int = 4
    state_map: StateMap | None = None
    pulse_tolerance_us: float = PULSE_TOLERANCE_US
    cache: Path | None = None
    runs: int = 0
    watchdog_cut: int = 0  # runs compared only up to the model's watchdog reset
    call_resolved: int = 0  # state or reply differences gone once the model's parser call was over
    _origin: float | None = None

    def __post_init__(self) -> None:
        self.tree = Path(self.tree)
        if self.against in MODELS:
            self.cmp = Comparison(False, FIRMWARES[self.against], self.pulse_tolerance_us)
        else:
            other = Path(self.against)
            if not other.is_dir():
                raise ConfigurationError(
                    f"--against={self.against!r} is neither v1.2, v2 nor a firmware tree folder"
                )
            self.cmp = Comparison(True, _spec_of(self.tree), 0.0)

    def sides(self) -> tuple[Side, Side]:
        kw: dict[str, Any] = {"hv513_count": self.hv513_count, "cache": self.cache}
        left = HostSide(self.tree, name=str(self.tree), state_map=self.state_map, **kw)
        right: Side
        if self.against in MODELS:
            if self._origin is None:  # measured once, on a probe run past setup()
                probe = HostSide(self.tree, name="probe", state_map=self.state_map, **kw)
                probe.advance_to(SETUP_US)
                self._origin = probe.timer_origin_us or 0.0
                probe.close()
            side = MODEL_SIDES[self.against]
            right = side(timer_origin_us=self._origin, hv513_count=self.hv513_count)
        else:
            right = HostSide(Path(self.against), name=self.against, state_map=self.state_map, **kw)
        return left, right

    def has_readback(self, stream: Stream) -> bool:
        spec = self.cmp.spec
        if spec is None:
            return False
        ops = {op for op, c in spec.by_opcode.items() if c.reply == "measure"}
        return any(b in ops for _, data in stream.writes for b in data)

    def first_divergence(self, stream: Stream, at_us: float | None = None) -> Divergence | None:
        """Run ``stream`` on fresh sides; the first checkpoint at which they differ.  With ``at_us``, a
        single checkpoint there (the writes before it written)."""
        self.runs += 1
        left, right = self.sides()
        try:
            return self._first_divergence(left, right, stream, at_us)
        finally:
            left.close()
            right.close()

    def _first_divergence(
        self, left: Side, right: Side, stream: Stream, at_us: float | None
    ) -> Divergence | None:
        readback = self.has_readback(stream)
        if at_us is None:
            checkpoints = sorted({t for t, _ in stream.writes} | {stream.end_us})
        else:
            checkpoints = [at_us]
        pending = list(stream.writes)
        prev = 0.0
        held: Divergence | None = None  # a state or reply difference waiting for the parser call to end
        held_until = math.inf
        i = 0
        while i < len(checkpoints):
            cp = checkpoints[i]
            i += 1
            while pending and pending[0][0] < cp:
                t_w, data = pending.pop(0)
                left.write(data, t_w)
                right.write(data, t_w)
            left.advance_to(cp)
            right.advance_to(cp)
            seen_left, seen_right = left.observe(cp), right.observe(cp)
            if seen_left.reset or seen_right.reset:  # see EQUIVALENCES["watchdog"]
                self.watchdog_cut += 1
                return None
            found = compare(seen_left, seen_right, self.cmp, readback, cp)
            in_call = found is not None and found[0] in ("state", "replies")
            d: Divergence | None = None
            if found is not None:
                kind, fld, a, b, t = found
                at = t if t is not None else cp
                d = Divergence(kind, fld, at, prev, a, b, _written_by(stream, at))
            if held is not None and (not in_call or cp >= held_until):
                if in_call and _still_differs(held, seen_left, seen_right, self.cmp, readback):
                    later = _call_window_end(left, held, cp, prev)
                    if later is not None:  # scans pre-empted the firmware's call: it is not over yet
                        held_until = later
                        bisect.insort(checkpoints, later)
                        prev = cp
                        continue
                    return held  # still different once the longest parser call is over: a divergence
                # gone (another register or element differing now is a difference of its own: a later call's
                # effects, with a window of its own)
                self.call_resolved += 1  # see EQUIVALENCES["call-resolution"]
                held = None
            if d is not None:
                if not in_call or self.cmp.exact or at_us is not None:
                    return d
                if held is None:
                    held, held_until = d, cp + CALL_WINDOW_US
                    if held_until not in checkpoints:
                        bisect.insort(checkpoints, held_until)
            prev = cp
        return held

    def locate(self, stream: Stream, found: Divergence, resolution_us: float = 1.0) -> Divergence:
        """Narrow a state or reply divergence seen at a checkpoint to within ``resolution_us`` of when it
        arose (by bisection between the checkpoint and the one before, each probe a fresh run)."""
        if found.kind not in ("state", "replies"):
            return found
        lo, hi, best = found.since_us, found.at_us, found
        while hi - lo > resolution_us:
            mid = round((lo + hi) / 2, 3)
            d = self.first_divergence(stream, at_us=mid)
            if d is not None and d.signature == found.signature:
                hi, best = mid, d
            else:
                lo = mid
        return dataclasses.replace(best, at_us=hi, since_us=lo)


def _call_window_end(left: Side, held: Divergence, cp: float, prev: float) -> float | None:
    """When the firmware's longest parser call begun by ``held.at_us`` is over, if later than ``cp``: the
    call advances only while no scan runs, so the CALL_WINDOW_US of main-loop time end later by the time the
    firmware spent in scans since (a scan of 255 channels takes 3.5 ms, a call 1 ms at most).  ``None``:
    the window is over, or since the checkpoint before (``prev``) the loop had no time while a scan began
    (scans back to back: the call never ends)."""
    if not isinstance(left, HostSide):
        return None
    end = held.at_us + CALL_WINDOW_US + left.scanning_us(held.at_us, cp)[0]
    busy_us, entered = left.scanning_us(prev, cp)
    if end <= cp or (busy_us >= cp - prev and entered > 0):
        return None
    return end


def _still_differs(
    held: Divergence, left: Observation, right: Observation, cmp: Comparison, readback: bool
) -> bool:
    """Whether the state or reply difference ``held`` (its register, or its element of an array register;
    the replies) is still there in these observations: a register is no longer different once both sides
    agree or once the firmware (``left``) holds the value the model showed when it was held -- the call
    is over on the firmware too, and what differs now is a later call's (the model at its start)."""
    if held.kind == "replies":
        if cmp.exact or not readback:
            return left.replies != right.replies
        return len(left.replies) != len(right.replies)
    key, _, index = held.field.partition("[")
    a, b = left.state.get(key), right.state.get(key)
    if index:
        i = int(index.rstrip("]"))
        if not (isinstance(a, list) and isinstance(b, list) and i < min(len(a), len(b))):
            return True
        a, b = a[i], b[i]
    return not (_same_number(key, a, b, cmp.exact) or _same_number(key, a, held.right, cmp.exact))


def _written_by(stream: Stream, t_us: float) -> bytes:
    """The host's bytes written before ``t_us`` (a checkpoint is taken before that time's write)."""
    return b"".join(d for t, d in stream.writes if t < t_us)


def _spec_of(tree: Path) -> FirmwareSpec | None:
    from tactdeform_hw.emulator.hostbuild.statemap import UPSTREAM_V1_2, UPSTREAM_V2

    if (tree / UPSTREAM_V1_2.unit).is_file():
        return V1_2
    if (tree / UPSTREAM_V2.unit).is_file():
        return V2
    return None


def shrink(
    differ: Differ, stream: Stream, found: Divergence, max_runs: int = 400
) -> tuple[Stream, Divergence]:
    """Drop writes, then runs of bytes, then single bytes while a divergence of the same signature
    persists; then cut the run's end to just after it.  At most ``max_runs`` comparisons."""
    best, best_div = stream, found
    budget = [max_runs]

    def still(candidate: Stream) -> Divergence | None:
        if budget[0] <= 0:
            return None
        budget[0] -= 1
        d = differ.first_divergence(candidate)
        return d if d is not None and d.signature == found.signature else None

    i = len(best.writes) - 1
    while i >= 0 and len(best.writes) > 1:  # whole writes
        cand = Stream(best.writes[:i] + best.writes[i + 1 :], best.end_us, best.label)
        d = still(cand)
        if d is not None:
            best, best_div = cand, d
        i -= 1
    chunk = max(1, max(len(b) for _, b in best.writes) // 2)
    while chunk >= 1 and budget[0] > 0:  # runs of bytes, halving
        progress = False
        for w in range(len(best.writes)):
            pos = 0
            while pos < len(best.writes[w][1]) and budget[0] > 0:
                t, data = best.writes[w]
                cut = data[:pos] + data[pos + chunk :]
                if not cut:
                    pos += chunk
                    continue
                writes = best.writes[:w] + ((t, cut),) + best.writes[w + 1 :]
                d = still(Stream(writes, best.end_us, best.label))
                if d is not None:
                    best, best_div, progress = Stream(writes, best.end_us, best.label), d, True
                else:
                    pos += chunk
        if not progress:
            chunk //= 2
    best_div = differ.locate(best, best_div)
    end = math.ceil(best_div.at_us + 2 * PULSE_MARGIN_US + 1000.0)
    if end < best.end_us:
        cand = Stream(best.writes, end, best.label)
        if still(cand) is not None:  # the run can stop soon after (the located divergence stands)
            best = cand
    return Stream(best.writes, best.end_us, f"minimal reproduction of {stream.label}"), best_div


@dataclass
class DiffReport:
    """The outcome of a differential run."""

    tree: str
    against: str
    streams_run: int = 0
    seconds: float = 0.0
    equivalences: tuple[str, ...] = ()
    stream: Stream | None = None
    divergence: Divergence | None = None
    minimal: Stream | None = None
    minimal_divergence: Divergence | None = None
    stopped_by_time: bool = False
    watchdog_cut: int = 0  # streams compared only up to the model's watchdog reset
    call_resolved: int = 0  # streams with a difference that was the model's call resolution
    diverged: int = 0  # streams that diverged (more than 1 only with keep_going)
    kinds: dict[str, dict[str, Any]] = field(default_factory=dict)  # keep_going: per signature

    def to_dict(self) -> dict[str, Any]:
        return {
            "tree": self.tree,
            "against": self.against,
            "streams_run": self.streams_run,
            "seconds": round(self.seconds, 3),
            "streams_per_s": round(self.streams_run / self.seconds, 2) if self.seconds else None,
            "equivalences": {k: EQUIVALENCES[k] for k in self.equivalences},
            "stopped_by_time": self.stopped_by_time,
            "watchdog_cut": self.watchdog_cut,
            "call_resolved": self.call_resolved,
            "divergences": self.diverged,
            "by_kind": self.kinds,
            "stream": self.stream.to_dict() if self.stream else None,
            "divergence": self.divergence.to_dict() if self.divergence else None,
            "minimal": self.minimal.to_dict() if self.minimal else None,
            "minimal_divergence": self.minimal_divergence.to_dict() if self.minimal_divergence else None,
        }


def streams_for(spec: FirmwareSpec | None, count: int, seed: int, edges: bool = True) -> Iterator[Stream]:
    """``count`` streams: the edge streams first (when ``edges``), then seeded random ones."""
    made = 0
    if edges:
        for s in edge_streams(spec):
            if made >= count:
                return
            yield s
            made += 1
    k = 0
    while made < count:
        yield random_stream(spec, seed * 1_000_003 + k)
        k += 1
        made += 1


class _Runner:
    """Runs the streams of one differential, in this process (``jobs=1``) or in ``jobs`` worker processes
    (each with its own :class:`Differ`), and hands back each stream's outcome in the streams' order: any
    ``jobs`` gives the same outcomes, so the same report."""

    BATCH = 8
    """Streams per task sent to a worker (a stream takes tens of ms; a task's round trip far less)."""

    def __init__(self, differ: Differ, jobs: int) -> None:
        self.differ = differ
        self.jobs = jobs
        self._pool: Executor | None = None
        if jobs > 1:
            self._prebuild()
            self._pool = ProcessPoolExecutor(
                max_workers=jobs,
                mp_context=multiprocessing.get_context("spawn"),
                initializer=_start_worker,
                initargs=(_DifferArgs.of(differ),),
            )

    def _prebuild(self) -> None:
        """Build the trees here first, so a build error is raised here and the workers find them cached."""
        d = self.differ
        trees = [d.tree] + ([] if d.against in MODELS else [Path(d.against)])
        for tree in trees:
            build(tree, state_map=d.state_map if d.state_map is not None else detect(tree), cache=d.cache)

    def __enter__(self) -> _Runner:
        return self

    def __exit__(self, *exc: object) -> None:
        if self._pool is not None:
            self._pool.shutdown(wait=True, cancel_futures=True)

    def outcomes(self, streams: Iterable[Stream]) -> Iterator[tuple[Stream, Divergence | None, int, int]]:
        """(stream, then :func:`_outcome`'s three), in the streams' order."""
        if self._pool is None:
            for stream in streams:
                yield (stream, *_outcome(self.differ, stream))
            return
        pool = self._pool
        it = iter(streams)
        window: deque[tuple[list[Stream], Future[list[tuple[Divergence | None, int, int]]]]] = deque()

        def submit() -> bool:
            batch = list(itertools.islice(it, self.BATCH))
            if batch:
                window.append((batch, pool.submit(_worker_batch, batch)))
            return bool(batch)

        while len(window) < 4 * self.jobs and submit():
            pass
        while window:
            batch, fut = window.popleft()
            results = fut.result()
            submit()
            for stream, (d, cut, resolved) in zip(batch, results):
                yield stream, d, cut, resolved

    def shrink(
        self, stream: Stream, found: Divergence, max_runs: int
    ) -> Callable[[], tuple[Stream, Divergence]]:
        """Start shrinking ``found``; the returned call gives the minimal reproduction (at once with
        ``jobs=1``, as the sequential run always did; in a worker otherwise, beside the streams)."""
        if self._pool is None:
            done = shrink(self.differ, stream, found, max_runs)
            return lambda: done
        fut = self._pool.submit(_worker_shrink, stream, found, max_runs)
        return fut.result


def _outcome(differ: Differ, stream: Stream) -> tuple[Divergence | None, int, int]:
    """A stream's first divergence, whether it was compared only up to the model's watchdog reset (1 or 0),
    and whether a difference in it was the model's call resolution (1 or 0)."""
    cut_before, resolved_before = differ.watchdog_cut, differ.call_resolved
    d = differ.first_divergence(stream)
    return d, differ.watchdog_cut - cut_before, int(differ.call_resolved > resolved_before)


@dataclass(frozen=True)
class _DifferArgs:
    """What a worker process needs to make the same :class:`Differ` (its fields, without its state)."""

    tree: Path
    against: str
    hv513_count: int
    state_map: StateMap | None
    pulse_tolerance_us: float
    cache: Path | None

    @classmethod
    def of(cls, d: Differ) -> _DifferArgs:
        return cls(d.tree, d.against, d.hv513_count, d.state_map, d.pulse_tolerance_us, d.cache)

    def make(self) -> Differ:
        return Differ(
            self.tree, self.against, self.hv513_count, self.state_map, self.pulse_tolerance_us, self.cache
        )


_WORKER: list[Differ] = []  # the worker process's own Differ (set once, by its initializer)


def _start_worker(args: _DifferArgs) -> None:
    _WORKER[:] = [args.make()]


def _worker_batch(streams: list[Stream]) -> list[tuple[Divergence | None, int, int]]:
    return [_outcome(_WORKER[0], s) for s in streams]


def _worker_shrink(stream: Stream, found: Divergence, max_runs: int) -> tuple[Stream, Divergence]:
    return shrink(_WORKER[0], stream, found, max_runs)


def diff_firmware(
    tree: str | Path,
    against: str,
    *,
    streams: int = 100,
    seed: int = 0,
    extra_streams: Iterable[Stream] = (),
    hv513_count: int = 4,
    state_map: StateMap | None = None,
    pulse_tolerance_us: float = PULSE_TOLERANCE_US,
    shrink_runs: int = 400,
    edges: bool = True,
    cache: Path | None = None,
    progress: Callable[[str], None] | None = None,
    keep_going: bool = False,
    time_limit_s: float | None = None,
    jobs: int = 1,
) -> DiffReport:
    """Compare ``tree`` with ``against`` (``"v1.2"``, ``"v2"`` or another tree) on ``extra_streams`` then
    ``streams`` generated ones; stop at the first divergence and shrink it.  With ``keep_going`` run every
    stream, count the divergences per signature (kind and field) and shrink the first of each.
    ``time_limit_s`` stops starting new streams after that much wall time (the report says how many ran).
    ``jobs`` worker processes share the streams; the report is the same for any ``jobs`` (but for its
    times, and for where a ``time_limit_s`` cuts the run)."""
    tree = Path(tree)
    if not (tree / "src").is_dir():
        raise ConfigurationError(
            f"--firmware-src={str(tree)!r} is not a PlatformIO tree: it has no src/ folder"
        )
    if against not in MODELS and not (Path(against) / "src").is_dir():
        raise ConfigurationError(
            f"--against={against!r} is neither v1.2, v2 nor a PlatformIO tree (a folder with src/)"
        )
    if jobs < 1:
        raise LimitError("jobs", jobs, "an integer >= 1 (worker processes)")
    differ = Differ(tree, against, hv513_count, state_map, pulse_tolerance_us, cache)
    spec = differ.cmp.spec
    report = DiffReport(str(tree), against, equivalences=differ.cmp.equivalences)
    shrinks: dict[str, Callable[[], tuple[Stream, Divergence]]] = {}
    t0 = time.perf_counter()
    told = t0
    with _Runner(differ, jobs) as runner:
        outcomes = runner.outcomes(_chain(extra_streams, streams_for(spec, streams, seed, edges)))
        for n, (stream, d, cut, resolved) in enumerate(outcomes, 1):
            report.streams_run = n
            report.watchdog_cut += cut
            report.call_resolved += resolved
            now = time.perf_counter()
            if progress is not None and now - told >= 2.0:  # at most one line every 2 s
                progress(f"{n}/{streams} streams, {now - t0:.1f} s, {n / (now - t0):.1f}/s")
                told = now
            if time_limit_s is not None and now - t0 >= time_limit_s:
                report.stopped_by_time = True
                if d is None:
                    break
            if d is None:
                continue
            report.diverged += 1
            key = " ".join(d.signature)
            if key in report.kinds:
                report.kinds[key]["streams"] += 1
                continue
            if progress is not None:
                progress(
                    f"{d.kind} {d.field} differs on {stream.label}: shrinking it (at most {shrink_runs} runs)"
                )
            report.kinds[key] = {"streams": 1, "first": stream.label}
            shrinks[key] = runner.shrink(stream, d, shrink_runs)
            if report.divergence is None:
                report.stream, report.divergence = stream, d
            if not keep_going or report.stopped_by_time:
                break
        for i, (key, result) in enumerate(shrinks.items()):
            minimal, md = result()
            report.kinds[key]["minimal"] = minimal.to_dict()
            report.kinds[key]["minimal_divergence"] = md.to_dict()
            if i == 0:
                report.minimal, report.minimal_divergence = minimal, md
    report.seconds = time.perf_counter() - t0
    return report


def _chain(*its: Iterable[Stream]) -> Iterator[Stream]:
    for it in its:
        yield from it
