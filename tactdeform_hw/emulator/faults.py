"""Fault injection for the timed emulator: a link that misbehaves and a board that fails.

Two layers, both seeded (the same seed gives the same faults, byte for byte):

* :class:`FaultyLink` — a :class:`~tactdeform_hw.emulator.timed.link.LinkFilter` between the host's writes and
  the device's receive queue, applying **silent** byte faults: ``drop``, ``corrupt``, ``duplicate`` and
  ``delay``.  Nobody tells the host.  These are the faults of a link without a checksum (a UART) or of a
  host stack that loses data; on USB full speed the bus's CRC and retries make them reported errors
  instead (``crc_error`` below).  Besides the faults that strike at a time, a :class:`ByteFault` strikes
  one chosen byte of the host's stream (lose it, duplicate it, corrupt it, or lose a USB packet's tail
  from it on), so that a campaign can enumerate every byte of a run rather than sample times.
* :class:`TimedPort` — a pyserial-like port over a
:class:`~tactdeform_hw.emulator.timed.model_v1_2.TimedEmulator`
  that the driver uses unchanged, adding the faults the **host notices** or the **board** causes:

  ``cut``
      the link fails in the middle of a command: part of the write arrives, the write raises, and the
      port is gone until it is reopened (an unplugged cable, a hub reset);
  ``crc_error``
      USB: a packet fails its CRC on every retry; the bytes before it arrived, the write raises (the port
      stays usable);
  ``reset``
      the board resets (power glitch, reset button): registers to power-on, and the USB device
      disappears until the port is reopened;
  ``stop_reading``
      the firmware's main loop stops reading (hung) while the stimulation interrupt goes on scanning the
      old pattern: the receive queue fills after 256 bytes and everything later is lost — the host sees
      only that replies stop.  Only the reset line (or unplugging) ends it;
  ``watchdog_reboot``
      the interrupt watchdog reboots the chip to its power-on state without the host being told.

:func:`check_deliveries` compares what the emulated scans delivered with what the host meant (a timeline
of frames and per-electrode limits) and returns every pulse above its limit or on a channel meant off.

The timed emulator's clock is the driver's pacing clock here (:attr:`TimedPort.pacing_clock`): every wait
of the driver runs the emulated device forward, so a whole session — renderer, driver, fail-safe, faults
and scans — runs in simulated time, deterministically and much faster than real time.
"""

from __future__ import annotations

import random
from bisect import bisect_right
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from enum import Enum
from typing import Any

import numpy as np
from serial.serialutil import PortNotOpenError, SerialException

from tactdeform_hw.emulator.timed.base import TimedModel
from tactdeform_hw.emulator.timed.link import (
    ByteBurst,
    Delivery,
    LinkFilter,
    LinkModel,
    Scheduled,
    expanded,
    make_link,
)
from tactdeform_hw.emulator.timed.model_v1_2 import TimedEmulator
from tactdeform_hw.protocol.state import BoardState

from ..clock import SimulatedClock
from ..errors import LimitError
from ..ports import PortBase


class FaultKind(str, Enum):
    DROP = "drop"
    CORRUPT = "corrupt"
    DUPLICATE = "duplicate"
    DELAY = "delay"
    CUT = "cut"
    CRC_ERROR = "crc_error"
    RESET = "reset"
    STOP_READING = "stop_reading"
    WATCHDOG_REBOOT = "watchdog_reboot"


class ByteFaultKind(str, Enum):
    """What a :class:`ByteFault` does to its byte (see :class:`ByteFault`)."""

    LOSE = "lose"
    DUPLICATE = "duplicate"
    CORRUPT = "corrupt"
    TAIL_LOSS = "tail_loss"


#: The value a corrupted byte is XORed with: every bit flipped, so that a value byte of 0 (an electrode
#: off, a height of 0) becomes 0xFF and a command byte (>= 0xF5) becomes a value byte (<= 0x0A).  Fixed, so
#: that an enumeration of corrupted bytes is deterministic and a run replays byte for byte.
CORRUPT_XOR = 0xFF


#: Faults applied to bytes in flight, silently (by :class:`FaultyLink`).
LINK_FAULTS = frozenset({FaultKind.DROP, FaultKind.CORRUPT, FaultKind.DUPLICATE, FaultKind.DELAY})
#: Faults of the port or the board (by :class:`TimedPort`).
PORT_FAULTS = frozenset(set(FaultKind) - LINK_FAULTS)
#: Faults the host is told about by its port (an exception from ``write``).
REPORTED_BY_PORT = frozenset({FaultKind.CUT, FaultKind.CRC_ERROR, FaultKind.RESET})


@dataclass(frozen=True)
class Fault:
    """One fault: it strikes the first write (or delivery) at or after ``at_s`` of simulated time.
    ``count`` bytes are dropped, corrupted or duplicated; ``delay_s`` delays a delivery (and, the link
    being first-in first-out, everything behind it)."""

    kind: FaultKind
    at_s: float
    count: int = 1
    delay_s: float = 0.003

    def __post_init__(self) -> None:
        object.__setattr__(self, "kind", FaultKind(self.kind))
        if not (isinstance(self.at_s, (int, float)) and self.at_s >= 0):
            raise LimitError("at_s", self.at_s, "a time >= 0 s")
        if isinstance(self.count, bool) or not isinstance(self.count, int) or self.count < 1:
            raise LimitError("count", self.count, "an integer >= 1")
        if not (isinstance(self.delay_s, (int, float)) and 0 <= self.delay_s <= 10):
            raise LimitError("delay_s", self.delay_s, "0 to 10 s")


@dataclass(frozen=True)
class ByteFault:
    """A silent fault at one byte of the host's stream, the one at offset ``host_index`` (counted from
    the first byte the host ever wrote to the emulator, as ``host_offset``), rather than at a time:

    ``lose``
        the byte never reaches the receive queue (a UART byte with a framing error the firmware drops);
    ``duplicate``
        the byte arrives twice;
    ``corrupt``
        the byte arrives XORed with :data:`CORRUPT_XOR`;
    ``tail_loss``
        the byte and every later byte of the same delivery (a USB bulk packet) are lost: the packet's
        tail after its first ``host_index - packet start`` bytes (on a UART, a delivery is one byte: the
        same as ``lose``).

    It strikes once, when the delivery that carries that byte is scheduled, and is recorded like the
    timed faults (:attr:`FaultyLink.injected`)."""

    kind: ByteFaultKind
    host_index: int

    def __post_init__(self) -> None:
        object.__setattr__(self, "kind", ByteFaultKind(self.kind))
        if isinstance(self.host_index, bool) or not isinstance(self.host_index, int) or self.host_index < 0:
            raise LimitError("host_index", self.host_index, "an integer >= 0")


@dataclass
class InjectedFault:
    """A fault as it happened: when, where in the host's byte stream, and what it did."""

    kind: FaultKind | ByteFaultKind
    t_s: float
    host_offset: int
    detail: dict[str, Any] = field(default_factory=dict)

    def to_dict(self) -> dict[str, Any]:
        return {"kind": self.kind.value, "t_s": self.t_s, "host_offset": self.host_offset, **self.detail}


def random_plan(
    seed: int, kinds: Sequence[FaultKind | str], count: int, start_s: float, end_s: float
) -> list[Fault]:
    """``count`` faults of the given kinds at seeded random times in ``[start_s, end_s)``."""
    rng = random.Random(seed)
    ks = [FaultKind(k) for k in kinds]
    out = [
        Fault(rng.choice(ks), rng.uniform(start_s, end_s), count=rng.choice((1, 1, 1, 2)))
        for _ in range(count)
    ]
    return sorted(out, key=lambda f: f.at_s)


class FaultyLink(LinkFilter):
    """Silent byte faults between the host and the receive queue (see the module documentation)."""

    def __init__(self, inner: LinkModel, faults: Sequence[Fault] = (), *, seed: int = 0) -> None:
        super().__init__(inner)
        self.pending = sorted((f for f in faults if f.kind in LINK_FAULTS), key=lambda f: f.at_s)
        self.rng = random.Random(seed)
        self.injected: list[InjectedFault] = []
        self.byte_faults: list[ByteFault] = []
        self._floor_ns = 0

    def add(self, fault: Fault) -> None:
        if fault.kind not in LINK_FAULTS:
            raise LimitError(
                "kind", fault.kind.value, f"a link fault ({', '.join(sorted(k.value for k in LINK_FAULTS))})"
            )
        self.pending.append(fault)
        self.pending.sort(key=lambda f: f.at_s)

    def add_byte_fault(self, fault: ByteFault) -> None:
        """Strike the host's byte ``fault.host_index`` when it is scheduled (it must not have been yet)."""
        self.byte_faults.append(fault)

    def schedule_bursts(self, data: bytes, t_ns: int, host_offset: int = -1) -> list[Scheduled]:
        """The inner link's bursts unchanged when :meth:`transform` would change none of their bytes: no
        fault due by the write's time and nothing delayed still ahead of them; else every byte through
        :meth:`transform`, as :meth:`schedule` does (so does a byte fault still to strike)."""
        if self.byte_faults or (self.pending and self.pending[0].at_s * 1e9 <= t_ns):
            return list(self.schedule(data, t_ns, host_offset))
        out = self.inner.schedule_bursts(data, t_ns, host_offset)
        floor = self._floor_ns
        for d in out:
            if not isinstance(d, ByteBurst) or d.t_ns < floor:
                # a delivery of another shape, or a delayed chunk still ahead (each byte waits behind it)
                return list(self.transform([x for d in out for x in expanded(d)]))
            floor = d.times[-1]
        self._floor_ns = floor
        return out

    def transform(self, deliveries: list[Delivery]) -> list[Delivery]:
        out: list[Delivery] = []
        for d in deliveries:
            if self.byte_faults and d.host_offset >= 0:
                d = self._strike_byte(d)
            while self.pending and self.pending[0].at_s * 1e9 <= d.sent_ns and d.data:
                d = self._apply(self.pending.pop(0), d)
            if d.t_ns < self._floor_ns:  # first in, first out: nothing overtakes a delayed chunk
                d = Delivery(self._floor_ns, d.data, d.host_offset, d.sent_ns)
            self._floor_ns = max(self._floor_ns, d.t_ns)
            if d.data:
                out.append(d)
        return out

    def _strike_byte(self, d: Delivery) -> Delivery:
        """Apply the byte faults whose byte ``d`` carries (each once; after a fault that shifts the bytes
        past it, their offsets are unknown and no further fault strikes this delivery)."""
        while True:
            hit = [
                f
                for f in self.byte_faults
                if 0 <= d.host_offset <= f.host_index < d.host_offset + len(d.data)
            ]
            if not hit:
                return d
            f = hit[0]
            self.byte_faults.remove(f)
            pos = f.host_index - d.host_offset
            data = bytearray(d.data)
            offset = d.host_offset
            detail: dict[str, Any]
            if f.kind is ByteFaultKind.LOSE:
                detail = {"bytes": 1, "data": data[pos : pos + 1].hex()}
                del data[pos]
                offset = offset if pos == len(data) else -1  # the bytes past it no longer line up
            elif f.kind is ByteFaultKind.DUPLICATE:
                detail = {"bytes": 1, "data": data[pos : pos + 1].hex()}
                data.insert(pos, data[pos])
                offset = -1
            elif f.kind is ByteFaultKind.CORRUPT:
                detail = {"bytes": 1, "before": data[pos : pos + 1].hex()}
                data[pos] ^= CORRUPT_XOR
                detail["after"] = data[pos : pos + 1].hex()
            else:  # tail loss: the prefix still lines up with the host's stream
                detail = {"bytes": len(data) - pos, "kept": pos, "data": data[pos:].hex()}
                del data[pos:]
            self.injected.append(InjectedFault(f.kind, d.t_ns / 1e9, f.host_index, detail))
            d = Delivery(d.t_ns, bytes(data), offset, d.sent_ns)

    def _apply(self, f: Fault, d: Delivery) -> Delivery:
        data = bytearray(d.data)
        pos = self.rng.randrange(len(data))
        host = d.host_offset + pos if d.host_offset >= 0 else -1
        detail: dict[str, Any]
        if f.kind is FaultKind.DROP:
            n = min(f.count, len(data) - pos)
            detail = {"bytes": n, "data": bytes(data[pos : pos + n]).hex()}
            del data[pos : pos + n]
        elif f.kind is FaultKind.CORRUPT:
            n = min(f.count, len(data) - pos)
            before = bytes(data[pos : pos + n])
            for i in range(pos, pos + n):
                data[i] ^= self.rng.randrange(1, 256)
            detail = {"bytes": n, "before": before.hex(), "after": bytes(data[pos : pos + n]).hex()}
        elif f.kind is FaultKind.DUPLICATE:
            n = min(f.count, len(data) - pos)
            data[pos + n : pos + n] = data[pos : pos + n]
            detail = {"bytes": n, "data": bytes(data[pos : pos + n]).hex()}
        else:  # delay
            detail = {"delay_s": f.delay_s, "bytes": len(data)}
            host = d.host_offset
            self.injected.append(InjectedFault(f.kind, d.t_ns / 1e9, host, detail))
            return Delivery(d.t_ns + int(f.delay_s * 1e9), bytes(data), d.host_offset, d.sent_ns)
        self.injected.append(InjectedFault(f.kind, d.t_ns / 1e9, host, detail))
        # the host offsets of a chunk whose length changed no longer line up past the fault
        return Delivery(d.t_ns, bytes(data), d.host_offset if f.kind is FaultKind.CORRUPT else -1, d.sent_ns)


#: Simulated seconds: time passes when the driver sleeps or a test advances it; ``on_advance`` runs the
#: emulator up to the new time.
SimClock = SimulatedClock


class TimedPort(PortBase):
    """A pyserial-like port over a :class:`TimedEmulator` (or the v2 model,
    :class:`~.timed_v2.TimedEmulatorV2`), in simulated time, with injectable faults.

    ``pacing_clock`` is the simulated clock (seconds) the driver's pacer must use (the driver picks it up
    by itself through :func:`~tactdeform_hw.device.driver.pacing.default_pacer`); every wait advances the
    emulator, and ``hooks`` (e.g. a fail-safe's ``poll``) run after each advance.  ``robust_encoding``
    asks the driver for the loss-tolerant command encoding (see :mod:`tactdeform_hw.device.driver.pacing`).
    ``loses_bytes`` (the port capability, :mod:`tactdeform_hw.ports`) is the link's: true on a UART.
    """

    @property
    def loses_bytes(self) -> bool:
        """Whether the emulated link can lose a byte without telling (a UART), as a real port declares."""
        return bool(self.faulty_link.loses_bytes)

    def __init__(
        self,
        emulator: TimedModel | None = None,
        *,
        link: str | LinkModel = "usb",
        faults: Sequence[Fault] = (),
        seed: int = 0,
        timeout: float = 0.02,
        robust_encoding: bool = True,
        read_step_s: float = 0.0002,
    ) -> None:
        self.faulty_link = FaultyLink(make_link(link), faults, seed=seed)
        self.emulator = emulator if emulator is not None else TimedEmulator(link=self.faulty_link)
        if emulator is not None:
            self.emulator.link = self.faulty_link
        self.pacing_clock = SimClock(self.emulator.now_us / 1e6, on_advance=self._advanced)
        self.robust_encoding = robust_encoding
        self.rng = random.Random(seed + 1)
        self.port_faults = sorted((f for f in faults if f.kind in PORT_FAULTS), key=lambda f: f.at_s)
        self.injected: list[InjectedFault] = []
        self.hooks: list[Callable[[float], None]] = []
        self.timeout = timeout
        self.write_timeout: float | None = None
        self.read_step_s = read_step_s
        self.is_open = False
        self.dtr = False
        self.rts = False
        self.port = "timed-emulator"
        self.gone = False  # the USB device vanished (cut, reset): the port must be reopened
        self.frozen = False  # the main loop stopped reading
        self.writes = 0
        self.write_errors = 0
        self.line_resets = 0

    @property
    def board_untouched(self) -> bool:
        """No byte has reached the board since its power-on (see :mod:`tactdeform_hw.ports`)."""
        return self.emulator.received_bytes == 0 and not self.gone

    # --- the clock ------------------------------------------------------------------------------------------

    @property
    def now_s(self) -> float:
        return self.pacing_clock.now()

    def _advanced(self, t_s: float) -> None:
        self.emulator.advance_to(max(self.emulator.now_us, t_s * 1e6))
        self._strike_board_faults()
        for hook in list(self.hooks):
            hook(t_s)

    def advance(self, seconds: float) -> None:
        """Let simulated time pass (the host doing something else)."""
        self.pacing_clock.advance(seconds)

    def advance_to(self, t_s: float) -> None:
        if t_s > self.now_s:
            self.pacing_clock.advance(t_s - self.now_s)

    def _strike_board_faults(self) -> None:
        if not self.port_faults:  # (asked at every step of the clock: most sessions have none)
            return
        now = self.now_s
        keep = []
        for f in self.port_faults:
            if f.at_s > now or f.kind not in (
                FaultKind.RESET,
                FaultKind.STOP_READING,
                FaultKind.WATCHDOG_REBOOT,
            ):
                keep.append(f)
                continue
            self._record(f.kind, {"state": self._state_brief()})
            if f.kind is FaultKind.RESET:
                self.emulator.reset("reset")
                self.gone = True
                self.frozen = False
            elif f.kind is FaultKind.WATCHDOG_REBOOT:
                self.emulator.reset("watchdog")
                self.frozen = False
            else:
                self._freeze()
        self.port_faults = keep

    def _freeze(self) -> None:
        """The main loop stops reading: the timed model's main loop waits forever (as on a locked parser)
        while deliveries keep filling the queue and the interrupt keeps scanning."""
        emu = self.emulator
        emu.stop_reading()
        self.frozen = True

    def _state_brief(self) -> dict[str, Any]:
        s = self.emulator.state()
        if s.stim_mode is not None:  # v2: a height per channel, the waveform by the mode
            return {"stim_mode": s.stim_mode, "active": sum(1 for v in s.scanned_pattern if v)}
        return {"pulse_height": s.pulse_height, "active": sum(1 for v in s.scanned_pattern if v in (1, 2))}

    def _record(self, kind: FaultKind, detail: dict[str, Any], host_offset: int = -1) -> None:
        self.injected.append(InjectedFault(kind, self.now_s, host_offset, detail))

    @property
    def all_injected(self) -> list[InjectedFault]:
        return sorted(self.injected + self.faulty_link.injected, key=lambda f: f.t_s)

    # --- pyserial face --------------------------------------------------------------------------------------

    def open(self) -> None:
        if self.is_open:
            raise SerialException("Port is already open.")
        self.is_open = True
        if self.gone:  # the board enumerates again: a fresh USB connection, nothing in flight
            self.gone = False

    def close(self) -> None:
        self.is_open = False

    def _check(self) -> None:
        if not self.is_open:
            raise PortNotOpenError()
        if self.gone:
            raise SerialException("device disconnected (the port must be reopened)")

    def _check_open(self) -> None:
        self._check()  # a vanished device fails like a closed port: the port must be reopened

    def board_state(self) -> BoardState:
        """The registers the emulated firmware holds (see :mod:`tactdeform_hw.ports`)."""
        return self.emulator.state()

    @property
    def board_hazards(self) -> list[Any]:
        return self.emulator.hazards

    def write(self, data: bytes) -> int:
        self._check()
        data = bytes(data)
        self.writes += 1
        now = self.now_s
        for f in list(self.port_faults):
            if f.at_s > now or f.kind not in (FaultKind.CUT, FaultKind.CRC_ERROR):
                continue
            self.port_faults.remove(f)
            if len(data) < 2 and f.kind is FaultKind.CUT:
                cut = 0
            elif f.kind is FaultKind.CUT:
                cut = self.rng.randrange(1, len(data))
            else:  # a failing packet: the whole packets before it arrived
                packet = self.rng.randrange(0, (len(data) + 63) // 64)
                cut = packet * 64
            host = self.emulator.host_offset
            if cut:
                self.emulator.write(data[:cut])
            self._record(f.kind, {"written": cut, "of": len(data), "lost": data[cut:].hex()}, host + cut)
            self.write_errors += 1
            if f.kind is FaultKind.CUT:
                self.gone = True
                raise SerialException(f"write failed after {cut} of {len(data)} byte(s): link cut")
            raise SerialException(f"USB transfer error (CRC) after {cut} of {len(data)} byte(s)")
        self.emulator.write(data)
        return len(data)

    def read(self, size: int = 1) -> bytes:
        self._check()
        out = bytearray(self.emulator.read_tx(size))
        deadline = self.now_s + (self.timeout or 0.0)
        while len(out) < size and self.now_s < deadline:
            self.pacing_clock.advance(min(self.read_step_s, deadline - self.now_s))
            if self.gone:
                break
            out += self.emulator.read_tx(size - len(out))
        return bytes(out)

    @property
    def in_waiting(self) -> int:
        self._check()
        return self.emulator.in_waiting

    def reset_input_buffer(self) -> None:
        self._check()
        self.emulator.read_tx()

    def pulse_reset(self) -> None:
        """The board's reset line: the chip restarts at its power-on state (a hung main loop too)."""
        self.emulator.reset("reset line")
        self.frozen = False
        self.line_resets += 1


# --- what the scans delivered, against what the host meant --------------------------------------------------


@dataclass(frozen=True)
class Intent:
    """From ``t_s`` on, the host means electrodes ``levels`` (application order) to be as given."""

    t_s: float
    levels: tuple[int, ...]


@dataclass
class DeliveryCheck:
    """Pulses that broke the host's intent, with the worst cases."""

    pulses: int = 0
    above_limit: list[dict[str, Any]] = field(default_factory=list)
    meant_off: list[dict[str, Any]] = field(default_factory=list)
    max_current_ua: float = 0.0
    max_charge_nc: float = 0.0

    @property
    def violations(self) -> list[dict[str, Any]]:
        return sorted(self.above_limit + self.meant_off, key=lambda v: v["t_s"])


def check_deliveries(
    emulator: TimedEmulator,
    intents: Sequence[Intent],
    limits_ua: Sequence[int],
    hw_to_app: dict[int, int],
    *,
    settle_s: float = 0.012,
    t0_s: float = 0.0,
    t1_s: float | None = None,
) -> DeliveryCheck:
    """Every stimulation pulse (mono or biphasic) between ``t0_s`` and ``t1_s`` against the intent.

    A pulse breaks the intent when its current exceeds its electrode's limit, or when it lands on an
    electrode the host had switched off more than ``settle_s`` earlier (the normal latency of a frame:
    pacing, the USB frame, the parser's tick and the scan in progress).  Sense pulses count too when they
    carry current.  A pulse on a hardware channel no electrode maps to is always a violation.
    """
    table = emulator.reports.pulse_table(t0_s * 1e6, None if t1_s is None else t1_s * 1e6)
    out = DeliveryCheck()
    cur = table["current_ua"]
    live = np.nonzero(cur > 0)[0]
    out.pulses = int(live.size)
    if live.size == 0:
        return out
    out.max_current_ua = float(cur[live].max())
    out.max_charge_nc = float(table["charge_nc"][live].max())
    times = [i.t_s for i in intents]
    # for each intent and electrode: since when the electrode has been off (None while on)
    n_el = len(limits_ua)
    off_since: list[list[float | None]] = []
    prev: list[float | None] = [None] * n_el
    for it in intents:
        row: list[float | None] = []
        for e in range(n_el):
            if it.levels[e] in (1, 2):
                row.append(None)
            else:
                row.append(prev[e] if prev[e] is not None else it.t_s)
        off_since.append(row)
        prev = row
    for k in live:
        t = float(table["start_us"][k]) / 1e6
        ch = int(table["channel"][k])
        ua = float(cur[k])
        app = hw_to_app.get(ch)
        rec = {"t_s": round(t, 6), "channel": ch, "electrode": app, "current_ua": round(ua, 1)}
        if app is None:
            out.meant_off.append({**rec, "why": "channel no electrode maps to"})
            continue
        if ua > limits_ua[app] + 1e-6:
            out.above_limit.append({**rec, "limit_ua": limits_ua[app]})
        # what did the host mean at t, and since when?
        i = bisect_right(times, t) - 1
        since = off_since[i][app] if i >= 0 else None
        if since is not None and t - since > settle_s:
            out.meant_off.append({**rec, "off_since_s": round(since, 6)})
    return out
