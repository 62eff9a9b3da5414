"""Pacing: the driver writes no faster than the firmware reads.

The firmware moves each arriving USB packet into a 256-byte receive queue and discards the rest of the
packet at the first byte that does not fit — silently: the host is neither held back nor told.  Its
parser handles at most one command with a payload per 1 ms RTOS tick (it sleeps one tick after each).
A host that writes a configuration burst, or frames faster than one command per millisecond, therefore
loses bytes and desynchronises the parser.  :class:`Pacer` prevents both:

* it spaces commands that carry a payload at least ``command_interval_s`` apart (default 1.2 ms: one
  tick plus margin for the tick's phase and the USB frame) — and further apart when the scans leave the
  parser less room (below), and
* it keeps a worst-case model of the device's queue — every byte written is counted as occupying the
  queue until it has crossed the link, a whole scan may have held the parser off right then, and the
  parser has worked through everything before it — and waits until a write fits whole below a margin
  (``queue_margin_bytes``), never to the brim.  The timer in that model holds only while the parser is
  known to read: after a reset, a reconnect, a timeout or a short reply the model freezes
  (:meth:`Pacer.suspect`) and only a reply from the device (:meth:`Pacer.proven`) empties it.

Bytes that are not commands (the zeros of a resync) are written in 64-byte chunks, each counted as taking
as long as the parser needs to skip them in the gaps between scans; 0xF5 counts its millisecond of board
detection, which at a short gap spreads over many periods.

**The scans decide the parser's pace.**  The stimulation interrupt pre-empts the main loop, so the parser
runs only in the gap between the end of one scan and the next alarm.  A command with a payload ends with
a one-tick sleep; when the gap is shorter than a tick (the TactDeform setting: 32 channels × 245 µs =
7.85 ms of an 8 ms period) the next call comes only after the next scan — **one payload command per scan
period**, not per millisecond.  Unknown bytes cost one call each (a few µs) and no sleep.  The device layer
tells the pacer the period and its estimate of the scan (:func:`estimate_scan_us`, the firmware's own
sequence of SPI exchanges and busy-waits) through :meth:`Pacer.set_timing`, and the guard refuses frames
whose scan would leave no gap at all (back-to-back scans starve the parser: the host could not even
switch them off).  The same pre-emption can tear a pattern: a scan that starts
while the firmware applies one (v2: its copy loop; v1.2: the pattern's transfer) uses part new, part old
heights.  Pacing keeps a v2 pattern from waiting behind other commands (:meth:`Pacer.spaced`) but cannot
place its copy in a gap: the parser's tick and the scan's alarm run on clocks the host does not see.

Time comes from a :class:`Clock`.  :class:`MonotonicClock` sleeps for real (serial ports, the pty
emulator); :class:`InstantClock` reads wall time but never waits, for the untimed in-process emulator whose
parser consumes every byte the moment it is written; a timed emulator exposes its own simulated clock
(:class:`SimulatedClock`), so pacing advances emulated time rather than wall time.

**Robust encoding** (``robust_encoding=True``, for links that can lose bytes — a UART, or a test that
injects faults): each command is followed by padding bytes chosen so that a lost byte can only make a
value smaller or leave the old value, never larger, and never lock the parser:

* after a u16 (pulse height, width, frequency): two 0x00 — losing the low byte leaves ``high`` (≤ the
  value), losing the high byte leaves ``low | 0 << 8`` (≤ the value), losing both gives 0;
* after a u8 value ``v`` (electrode count, polarity, v2's stimulation mode): ``v`` itself — if the
  payload is lost the padding becomes the payload and means the same; otherwise it is an unknown byte and
  ignored;
* after other u8 values (sense height, sense width, discharge): one 0x00;
* after a pattern: two 0x00 — a lost level byte makes the padding the last channel's level (off);
* except after a pattern of two-byte heights (v2) that another command follows in the same write
  (:func:`paddings`): nothing.  A byte lost inside such a pattern shifts every later height by one byte,
  so the low byte of one channel becomes the high byte of the one before — a height far above the
  value, whatever the padding.  Unpadded, the shifted pattern takes the next command's first byte as its
  last and that command does not apply (its payload bytes are unknown ones).  The only such write is v2's
  cover (:func:`~tactdeform_hw.device.driver.v2.covered_pattern`): ``FB 02``, the pattern, ``FB mode``;
  the mode then stays 2 at sense height 0, where no pattern height is delivered, until the pattern is
  written again.

and no payload byte may be ≥ 0xF5 (a command byte), so a lost command byte turns its payload into
ignored unknown bytes rather than into a command.  The device layer lowers pulse heights whose low byte
would be ≥ 0xF5 by up to 110 µA and refuses other such values.  The padding costs a few unknown bytes
per command, which the firmware skips without sleeping.
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

from tactdeform_hw.clock import Clock, InstantClock, MonotonicClock
from tactdeform_hw.protocol.constants import RX_QUEUE_SIZE, USB_PACKET_SIZE, Opcode
from tactdeform_hw.protocol.firmware import DEFAULT_FIRMWARE, FirmwareSpec
from tactdeform_hw.protocol.firmware_math import estimate_scan_us as estimate_scan_us
from tactdeform_hw.protocol.firmware_math import firmware_period_us as firmware_period_us

COMMAND_BYTE_MIN = DEFAULT_FIRMWARE.command_byte_min

# The scan's timing constants are the firmware table's (protocol.firmware); the parser's cost per unknown
# byte is this layer's own assumption, one parser call plus one byte read, rounded up.
SPI_EXCHANGE_US = DEFAULT_FIRMWARE.timing.spi_exchange_us
GPIO_WRITE_US = DEFAULT_FIRMWARE.timing.gpio_write_us
ISR_ENTRY_US = DEFAULT_FIRMWARE.timing.isr_entry_us
PARSER_BYTE_US = 4.0
HV513_COUNT_BYTE = int(Opcode.HV513_COUNT)
#: 0xF5 re-detects the stacked boards before it answers: 50 analog readings, about 1 ms of main-loop time
#: (the reference's own estimate), rounded up.
HV513_DETECT_US = 1200.0
#: Frames whose estimated scan leaves less than this before the next alarm are refused by the guard.
SCAN_GAP_MIN_US = 50.0


@dataclass(frozen=True)
class PacingPolicy:
    """``queue_margin_bytes`` of the 256-byte queue are never planned for (a probe of a few bytes always
    fits, even behind a queue the model only bounds); ``byte_s`` is the slowest a byte crosses the link
    (a USB full-speed frame carries 64 bytes per ms, a 921600-baud UART one byte per 10.85 µs).
    ``firmware`` is the table of the parser being paced: which bytes carry a payload, and whether it
    sleeps a tick after each (v1.2) or reads complete commands back to back (v2)."""

    firmware: FirmwareSpec = DEFAULT_FIRMWARE
    queue_bytes: int = RX_QUEUE_SIZE
    command_interval_s: float = 0.0012
    tick_s: float = 0.001
    link_latency_s: float = 0.001
    chunk_bytes: int = USB_PACKET_SIZE
    robust_encoding: bool = False
    queue_margin_bytes: int = 32
    byte_s: float = 16e-6


@dataclass
class PacingStats:
    commands: int = 0
    payload_commands: int = 0
    bytes_written: int = 0
    padding_bytes: int = 0
    waits: int = 0
    waited_s: float = 0.0
    max_queue_estimate: int = 0

    def to_dict(self) -> dict[str, Any]:
        return dict(self.__dict__)


def has_payload(data: bytes, firmware: FirmwareSpec = DEFAULT_FIRMWARE) -> bool:
    """Whether the command starting ``data`` carries a payload (on v1.2: the parser sleeps a tick after
    it)."""
    if not data:
        return False
    c = firmware.by_opcode.get(data[0])
    return c is not None and c.kind is not None


def padding_for(data: bytes, firmware: FirmwareSpec = DEFAULT_FIRMWARE) -> bytes:
    """The robust-encoding padding that follows one whole command (see the module docstring)."""
    if not data:
        return b""
    c = firmware.by_opcode.get(data[0])
    if c is None or c.kind is None:
        return b""
    if c.kind in ("u16", "pattern"):
        return b"\x00\x00"
    if (
        c.register in ("electrode_num", "polarity", "stim_mode")
        and len(data) >= 2
        and data[1] < firmware.command_byte_min
    ):
        return bytes([data[1]])
    return b"\x00"


def paddings(commands: Sequence[bytes], firmware: FirmwareSpec = DEFAULT_FIRMWARE) -> list[bytes]:
    """The robust-encoding padding after each of ``commands`` written as one write: :func:`padding_for`,
    except none after a pattern of two-byte heights that another command follows (see the module
    docstring: a byte lost inside it then leaves the next command unapplied rather than applying it
    after a shifted pattern)."""
    last = len(commands) - 1
    wide = firmware.pattern_bytes_per_electrode > 1
    out: list[bytes] = []
    for i, c in enumerate(commands):
        if wide and i < last and c[:1] and c[0] == firmware.pattern_command.opcode:
            out.append(b"")
        else:
            out.append(padding_for(c, firmware))
    return out


def command_like_payload(data: bytes, firmware: FirmwareSpec = DEFAULT_FIRMWARE) -> int | None:
    """Index of the first payload byte of a command that looks like a command byte (None if none)."""
    cmin = firmware.command_byte_min
    for i, b in enumerate(data[1:], start=1):
        if b >= cmin:
            return i
    return None


@dataclass
class Pacer:
    """Spaces and sizes writes to what the firmware can take (see the module docstring).

    The queue model is an upper bound on the device's receive queue, kept in written-byte offsets: every
    write stays *in flight* until its worst-case consumption time — the bytes' arrival, plus a whole scan
    that may block the parser just then (biphasic channels included: the caller gives the worst scan), plus
    one parser call per payload command or the skip time of unknown bytes, plus a tick.  That timer is
    valid only while the parser is known to read: :meth:`suspect` (a reset, a reconnect, a timeout, a short
    reply, a failed write) freezes the model — nothing in flight is assumed consumed by the passing of time
    until :meth:`proven` records a reply from the device, which proves every byte written before the
    request consumed.  Writes fill the queue to ``queue_bytes - queue_margin_bytes``, not to the brim; a
    larger single write waits until the model is empty.
    """

    clock: Clock = field(default_factory=MonotonicClock)
    policy: PacingPolicy = field(default_factory=PacingPolicy)
    stats: PacingStats = field(default_factory=PacingStats)

    def __post_init__(self) -> None:
        # (time the bytes are surely consumed, count, written offset just past them)
        self._inflight: deque[tuple[float, int, int]] = deque()
        self._inflight_bytes = 0  # the sizes in ``_inflight``, summed (asked before every write)
        self._last_done = -1e18
        self._last_payload_write = -1e18
        self._arrived_by = -1e18  # when every byte written so far has surely crossed the link
        self.offset = 0  # bytes written so far (the queue model's clock of positions)
        self.frozen = False  # True while the parser is not known to read (see :meth:`suspect`)
        self.period_s: float | None = None
        self.scan_s: float | None = None

    def set_timing(self, period_s: float | None, scan_s: float | None) -> None:
        """The firmware's alarm period and the worst scan that may be in force; None: unknown (1 ms pace)."""
        self.period_s = period_s
        self.scan_s = scan_s

    @property
    def yields_per_command(self) -> bool:
        """Whether the parser sleeps a tick after every command with a payload (v1.2); v2 sleeps only
        when a call made no progress, so complete commands are read back to back in one gap."""
        return self.policy.firmware.yield_rule == "after_payload"

    def spaced(self, data: bytes) -> bool:
        """Whether the command starting ``data`` waits :meth:`payload_interval_s` after the previous
        command with a payload.  v1.2: every such command (its parser sleeps a tick after each).  v2 reads
        complete commands back to back, so only a pattern waits: written alone, nothing queued before it
        delays its copy into the pattern buffer.

        What the spacing cannot do is keep that copy clear of the next scan.  The parser copies the pattern
        at its first wake-up after the pattern arrived: the end of a scan, or its own 1 ms tick wherever a
        tick falls between two scans.  Unless the period is a whole number of ticks and no tick falls in
        the gap, some wake-ups come just before an alarm, and a pattern read there is torn by the scan (the
        first channels new, the rest old) whatever was written before it.  No reply tells the host when the
        scans run, so the moment of a write cannot choose the wake-up; tests/test_safety_pacing.py shows one
        such pattern, written alone."""
        fw = self.policy.firmware
        if not has_payload(data, fw):
            return False
        return self.yields_per_command or fw.by_opcode[data[0]].kind == "pattern"

    def payload_interval_s(self) -> float:
        """How far apart commands with a payload must be for the parser to keep up (see :meth:`spaced`)."""
        base = self.policy.command_interval_s
        if self.period_s is None or self.scan_s is None:
            return base
        gap = self.period_s - self.scan_s
        tick = self.policy.tick_s
        if tick <= 0:
            return base
        if gap <= 0:
            return max(base, self.period_s * 1.05 + 0.0002)  # starved: the guard refuses such frames
        per_period = max(1, int(gap / tick)) if gap >= tick else 1
        return max(base, self.period_s / per_period * 1.05 + 0.0002)

    def skip_s(self, nbytes: int) -> float:
        """How long the parser needs, at worst, to skip ``nbytes`` unknown bytes: it reads only in the gaps
        between scans, so they take whole periods."""
        if self.period_s is None or self.scan_s is None:
            return self.policy.tick_s * max(1, nbytes / 64)
        gap_us = max(1.0, (self.period_s - self.scan_s) * 1e6)
        per_period = max(1.0, gap_us / PARSER_BYTE_US)
        # the first gap's worth is read right after the scan the queue model already waits for
        whole = math.ceil(nbytes / per_period) - 1
        return self.period_s * whole * 1.1 + min(gap_us, nbytes * PARSER_BYTE_US) / 1e6 + self.policy.tick_s

    def busy_s(self, cpu_us: float) -> float:
        """How long ``cpu_us`` of main-loop work takes at worst when it runs only in the gaps between scans
        (0xF5's board detection: one gap when the gaps are long, several periods when they are short)."""
        if self.period_s is None or self.scan_s is None:
            return cpu_us / 1e6 + self.policy.tick_s
        gap_us = max(1.0, (self.period_s - self.scan_s) * 1e6)
        if gap_us >= cpu_us:
            return cpu_us / 1e6
        return self.period_s * math.ceil(cpu_us / gap_us) * 1.1

    @property
    def robust(self) -> bool:
        return self.policy.robust_encoding

    @property
    def limit_bytes(self) -> int:
        """What the model fills the queue to."""
        return max(1, self.policy.queue_bytes - max(0, self.policy.queue_margin_bytes))

    def suspect(self) -> None:
        """The parser may not be reading (a reset, a reconnect, a timeout, a short reply, a failed write):
        from now on nothing in flight is assumed consumed until :meth:`proven`."""
        self.frozen = True

    def reset(self) -> None:
        """Kept for callers of the open-loop model: the queue is *not* assumed empty; see :meth:`suspect`."""
        self.suspect()

    def proven(self, offset: int) -> None:
        """The device answered a request written just before ``offset``: every byte before it has been
        read.  Unfreezes the model (the parser reads, and was at a command boundary there)."""
        while self._inflight and self._inflight[0][2] <= offset:
            self._inflight_bytes -= self._inflight.popleft()[1]
        self.frozen = False
        if not self._inflight:
            self._last_done = min(self._last_done, self.clock.now())

    def queue_estimate(self, now: float | None = None) -> int:
        """Bytes the device's queue may hold (an upper bound)."""
        if not self.frozen:
            t = self.clock.now() if now is None else now
            while self._inflight and self._inflight[0][0] <= t:
                self._inflight_bytes -= self._inflight.popleft()[1]
        return self._inflight_bytes

    def drained_by(self) -> float:
        """When everything written so far is surely consumed, if the parser reads."""
        return max([self.clock.now()] + [d for d, _, _ in self._inflight])

    def arrived_by(self) -> float:
        """When everything written so far has surely crossed the link (and reached the queue)."""
        return max(self.clock.now(), self._arrived_by)

    def _wait_until(self, t: float) -> None:
        now = self.clock.now()
        if t > now:
            self.stats.waits += 1
            self.stats.waited_s += t - now
            self.clock.sleep(t - now)

    def wait_until(self, t: float) -> None:
        """Let time pass until ``t`` (the pacer's clock: simulated, instant or wall)."""
        self._wait_until(t)

    def _fit(self, size: int) -> None:
        """Wait until ``size`` bytes fit in the modelled queue below its margin (or the model is empty).
        While frozen the same waits apply — they decide when to write, the bytes stay counted."""
        limit = self.limit_bytes
        while True:
            now = self.clock.now()
            occupied = self.queue_estimate(now)
            if self.frozen:
                pending: Sequence[tuple[float, int, int]] = [e for e in self._inflight if e[0] > now]
                expected = sum(n for _, n, _ in pending)
            else:  # (queue_estimate dropped what is done: the rest is pending)
                pending, expected = self._inflight, occupied
            if not pending or (expected + size <= limit and (self.frozen or occupied + size <= limit)):
                return
            need = expected + size - limit
            freed = 0
            target = pending[-1][0]
            if size <= limit:
                for done, n, _ in pending:
                    freed += n
                    if freed >= need:
                        target = done
                        break
            self._wait_until(target)

    def _account(self, size: int, duration_s: float) -> None:
        now = self.clock.now()
        arrival = now + self.policy.link_latency_s + size * self.policy.byte_s
        self._arrived_by = max(self._arrived_by, arrival)
        start = max(arrival + (self.scan_s or 0.0), self._last_done)
        done = start + duration_s
        self._last_done = done
        self.offset += size
        self._inflight.append((done + self.policy.tick_s, size, self.offset))
        self._inflight_bytes += size
        self.stats.max_queue_estimate = max(self.stats.max_queue_estimate, self.queue_estimate(now))

    def write(self, write: Callable[[bytes], None], data: bytes, *, pad: bool | None = None) -> None:
        """Write one command (or a run of non-command bytes) through ``write``, paced.  ``pad``: None pads
        under robust encoding, True always (the recovery's own commands), False never."""
        if not data:
            return
        if data[0] < COMMAND_BYTE_MIN:
            step = max(1, self.policy.chunk_bytes)
            for i in range(0, len(data), step):
                chunk = data[i : i + step]
                self._fit(len(chunk))
                write(chunk)
                detect = chunk.count(HV513_COUNT_BYTE) * self.busy_s(HV513_DETECT_US)  # a probe's 0xF5
                self._account(len(chunk), self.skip_s(len(chunk)) + detect)
                self.stats.bytes_written += len(chunk)
            return
        fw = self.policy.firmware
        payload = has_payload(data, fw)
        padded = self.policy.robust_encoding if pad is None else pad
        out = data + padding_for(data, fw) if padded else data
        self._fit(len(out))
        spaced = self.spaced(data)
        interval = self.payload_interval_s() if spaced else 0.0  # (only a spaced write uses it)
        if spaced:
            self._wait_until(self._last_payload_write + interval)
        write(out)
        if payload:
            self._last_payload_write = self.clock.now()
            self.stats.payload_commands += 1
        parts = max(1, math.ceil(len(out) / max(1, self.policy.chunk_bytes)))  # a long pattern: several reads
        if spaced:
            duration = interval * parts
        elif payload:
            # read whole once complete, in the gaps between scans; a payload still crossing the link costs
            # a one-tick sleep per waiting call, which the in-flight entry's tick covers once per part
            duration = self.skip_s(len(out)) + self.policy.tick_s * (parts - 1)
        else:
            duration = self.skip_s(len(out)) + (
                self.busy_s(HV513_DETECT_US) if out[0] == HV513_COUNT_BYTE else 0.0
            )
        self._account(len(out), duration)
        self.stats.commands += 1
        self.stats.bytes_written += len(out)
        self.stats.padding_bytes += len(out) - len(data)

    def write_commands(
        self, write: Callable[[bytes], None], commands: Sequence[bytes], *, pad: bool | None = None
    ) -> None:
        """Several whole commands in **one** write through ``write``, paced as one unit: each padded as
        :meth:`write` pads it, the group spaced (:meth:`spaced`) when any of its commands is, and counted in
        the queue model as one write whose parsing takes every command's time.

        Why one write: the bytes then cross the link back to back and reach the queue together, and v2's
        parser reads complete commands without sleeping between them — so a command written in front of a
        pattern and one written behind it take effect around the pattern's copy and nowhere else (the cover
        of :meth:`~tactdeform_hw.device.driver.v2.V2Dialect.frame`).  Written one by one, the pacer would
        space the
        pattern a period or more behind the command before it."""
        cmds = [bytes(c) for c in commands if c]
        if not cmds:
            return
        if any(c[0] < COMMAND_BYTE_MIN for c in cmds):
            raise ValueError("write_commands: every element must start with a command byte")
        fw = self.policy.firmware
        padded = self.policy.robust_encoding if pad is None else pad
        out = (
            b"".join(c + pad_ for c, pad_ in zip(cmds, paddings(cmds, fw), strict=True))
            if padded
            else b"".join(cmds)
        )
        self._fit(len(out))
        interval = self.payload_interval_s()
        spaced = any(self.spaced(c) for c in cmds)
        if spaced:
            self._wait_until(self._last_payload_write + interval)
        write(out)
        payloads = sum(1 for c in cmds if has_payload(c, fw))
        if payloads:
            self._last_payload_write = self.clock.now()
            self.stats.payload_commands += payloads
        parts = max(1, math.ceil(len(out) / max(1, self.policy.chunk_bytes)))
        if self.yields_per_command:
            # v1.2 sleeps a tick after every payload command: each costs a spaced interval
            duration = interval * (max(1, payloads) + parts - 1)
        elif spaced:
            duration = interval * parts
        else:
            duration = self.skip_s(len(out)) + self.policy.tick_s * (parts - 1)
        self._account(len(out), duration)
        self.stats.commands += len(cmds)
        self.stats.bytes_written += len(out)
        self.stats.padding_bytes += len(out) - sum(len(c) for c in cmds)


def default_pacer(port: Any, robust_encoding: bool | None = None) -> Pacer:
    """The pacer a port needs.

    * A port that declares ``pacing_clock`` (a timed emulator) is paced in that clock.
    * ``robust_encoding`` chooses the loss-tolerant encoding (True) or the plain one (False); None (the
      default) takes the port's own ``robust_encoding`` (plain when it declares none: every real port).
    * A port that declares itself ``instant`` (every byte consumed as it is written) needs no waiting:
      its pacer only keeps the books.
    * Anything else — a real board, a pty — is paced in wall time.
    """
    if robust_encoding is None:
        robust_encoding = bool(getattr(port, "robust_encoding", False))
    policy = PacingPolicy(robust_encoding=robust_encoding)
    clock = getattr(port, "pacing_clock", None)
    if clock is not None:
        return Pacer(clock=clock, policy=policy)
    if getattr(port, "instant", False) is True:
        return Pacer(clock=InstantClock(), policy=policy)
    return Pacer(clock=MonotonicClock(), policy=policy)
