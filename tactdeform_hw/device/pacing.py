"""Pacing: the driver writes no faster than the firmware reads.

The firmware moves each arriving USB packet into a 256-byte receive queue and discards the rest of the
packet at the first byte that does not fit — silently: the host is neither held back nor told.  Its
parser handles at most one command with a payload per 1 ms RTOS tick (it sleeps one tick after each).
A host that writes a configuration burst, or frames faster than one command per millisecond, therefore
loses bytes and desynchronises the parser.  :class:`Pacer` prevents both:

* it spaces commands that carry a payload at least ``command_interval_s`` apart (default 1.2 ms: one
  tick plus margin for the tick's phase and the USB frame) — and further apart when the scans leave the
  parser less room (below), and
* it keeps a conservative model of the device's queue — every byte written is counted as occupying the
  queue until ``link_latency_s`` plus one tick after the parser could have started on it — and waits
  until a write fits whole.

Bytes that are not commands (the 256 zeros of a resync) are written in 64-byte chunks, each counted as
taking as long as the parser needs to skip them, so even a queue holding a half-read command never
overflows.

**The scans decide the parser's pace.**  The stimulation interrupt pre-empts the main loop, so the parser
runs only in the gap between the end of one scan and the next alarm.  A command with a payload ends with
a one-tick sleep; when the gap is shorter than a tick (the TactDeform setting: 32 channels × 245 µs =
7.85 ms of an 8 ms period) the next call comes only after the next scan — **one payload command per scan
period**, not per millisecond.  Unknown bytes cost one call each (a few µs) and no sleep.  The device layer
tells the pacer the period and its estimate of the scan (:func:`estimate_scan_us`, the firmware's own
sequence of SPI exchanges and busy-waits) through :meth:`Pacer.set_timing`, and the guard refuses frames
whose scan would leave no gap at all (back-to-back scans starve the parser: the host could not even
switch them off).

Time comes from a :class:`Clock`.  :class:`MonotonicClock` sleeps for real (serial ports, the pty
emulator); :class:`InstantClock` reads wall time but never waits, for the untimed in-process emulator whose
parser consumes every byte the moment it is written; a timed emulator exposes its own simulated clock
(:class:`SimulatedClock`), so pacing advances emulated time rather than wall time.

**Robust encoding** (``robust_encoding=True``, for links that can lose bytes — a UART, or a test that
injects faults): each command is followed by padding bytes chosen so that a lost byte can only make a
value smaller or leave the old value, never larger, and never lock the parser:

* after a u16 (pulse height, width, frequency): two 0x00 — losing the low byte leaves ``high`` (≤ the
  value), losing the high byte leaves ``low | 0 << 8`` (≤ the value), losing both gives 0;
* after a u8 value ``v`` (electrode count, polarity): ``v`` itself — if the payload is lost the padding
  becomes the payload and means the same; otherwise it is an unknown byte and ignored;
* after other u8 values (sense height, sense width, discharge): one 0x00;
* after a pattern: two 0x00 — a lost level byte makes the padding the last channel's level (off).

and no payload byte may be ≥ 0xF5 (a command byte), so a lost command byte turns its payload into
ignored unknown bytes rather than into a command.  The device layer lowers pulse heights whose low byte
would be ≥ 0xF5 by up to 110 µA and refuses other such values.  The padding costs a few unknown bytes
per command, which the firmware skips without sleeping.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from ..clock import Clock, InstantClock, MonotonicClock
from ..protocol.constants import RX_QUEUE_SIZE, USB_PACKET_SIZE
from ..protocol.firmware import DEFAULT_FIRMWARE, FirmwareSpec
from ..protocol.firmware_math import estimate_scan_us as estimate_scan_us
from ..protocol.firmware_math import firmware_period_us as firmware_period_us

COMMAND_BYTE_MIN = DEFAULT_FIRMWARE.command_byte_min

# The scan's timing constants are the firmware table's (protocol.firmware); the parser's cost per unknown
# byte is this layer's own assumption, one parser call plus one byte read, rounded up.
SPI_EXCHANGE_US = DEFAULT_FIRMWARE.timing.spi_exchange_us
GPIO_WRITE_US = DEFAULT_FIRMWARE.timing.gpio_write_us
ISR_ENTRY_US = DEFAULT_FIRMWARE.timing.isr_entry_us
PARSER_BYTE_US = 4.0
#: Frames whose estimated scan leaves less than this before the next alarm are refused by the guard.
SCAN_GAP_MIN_US = 50.0


@dataclass(frozen=True)
class PacingPolicy:
    queue_bytes: int = RX_QUEUE_SIZE
    command_interval_s: float = 0.0012
    tick_s: float = 0.001
    link_latency_s: float = 0.001
    chunk_bytes: int = USB_PACKET_SIZE
    robust_encoding: bool = False


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
    """Whether the command starting ``data`` carries a payload (on v1.2: the parser sleeps a tick after it)."""
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
    if c.register in ("electrode_num", "polarity") and len(data) >= 2 and data[1] < firmware.command_byte_min:
        return bytes([data[1]])
    return b"\x00"


def command_like_payload(data: bytes, firmware: FirmwareSpec = DEFAULT_FIRMWARE) -> int | None:
    """Index of the first payload byte of a command that looks like a command byte (None if none)."""
    cmin = firmware.command_byte_min
    for i, b in enumerate(data[1:], start=1):
        if b >= cmin:
            return i
    return None


@dataclass
class Pacer:
    """Spaces and sizes writes to what the firmware can take (see the module docstring)."""

    clock: Clock = field(default_factory=MonotonicClock)
    policy: PacingPolicy = field(default_factory=PacingPolicy)
    stats: PacingStats = field(default_factory=PacingStats)

    def __post_init__(self) -> None:
        self._inflight: deque[tuple[float, int]] = deque()  # (time the bytes are surely consumed, count)
        self._last_done = -1e18
        self._last_payload_write = -1e18
        self.period_s: float | None = None
        self.scan_s: float | None = None

    def set_timing(self, period_s: float | None, scan_s: float | None) -> None:
        """The firmware's alarm period and the (estimated) scan in force; None: unknown (1 ms pace)."""
        self.period_s = period_s
        self.scan_s = scan_s

    def payload_interval_s(self) -> float:
        """How far apart commands with a payload must be for the parser to keep up."""
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
        """How long the parser needs to skip ``nbytes`` unknown bytes."""
        if self.period_s is None or self.scan_s is None:
            return self.policy.tick_s * max(1, nbytes / 64)
        gap_us = max(1.0, (self.period_s - self.scan_s) * 1e6)
        per_period = max(1.0, gap_us / PARSER_BYTE_US)
        return self.period_s * (nbytes / per_period) * 1.1 + self.policy.tick_s

    @property
    def robust(self) -> bool:
        return self.policy.robust_encoding

    def reset(self) -> None:
        """Forget the queue model (after a reconnect or a device reset the queue is empty)."""
        self._inflight.clear()
        self._last_done = -1e18

    def queue_estimate(self, now: float | None = None) -> int:
        t = self.clock.now() if now is None else now
        while self._inflight and self._inflight[0][0] <= t:
            self._inflight.popleft()
        return sum(n for _, n in self._inflight)

    def _wait_until(self, t: float) -> None:
        now = self.clock.now()
        if t > now:
            self.stats.waits += 1
            self.stats.waited_s += t - now
            self.clock.sleep(t - now)

    def _fit(self, size: int) -> None:
        """Wait until ``size`` bytes fit in the modelled queue."""
        limit = self.policy.queue_bytes
        while True:
            now = self.clock.now()
            occupied = self.queue_estimate(now)
            if occupied + size <= limit or not self._inflight:
                return
            # the queue frees in order: wait for the first entry that makes room
            need = occupied + size - limit
            freed = 0
            for done, n in self._inflight:
                freed += n
                if freed >= need:
                    self._wait_until(done)
                    break

    def _account(self, size: int, duration_s: float) -> None:
        now = self.clock.now()
        arrival = now + self.policy.link_latency_s
        start = max(arrival, self._last_done)
        done = start + duration_s
        self._last_done = done
        self._inflight.append((done + self.policy.tick_s, size))
        self.stats.max_queue_estimate = max(self.stats.max_queue_estimate, self.queue_estimate(now))

    def write(self, write: Callable[[bytes], None], data: bytes) -> None:
        """Write one command (or a run of non-command bytes) through ``write``, paced."""
        if not data:
            return
        if data[0] < COMMAND_BYTE_MIN:
            step = max(1, self.policy.chunk_bytes)
            for i in range(0, len(data), step):
                chunk = data[i : i + step]
                self._fit(len(chunk))
                write(chunk)
                self._account(len(chunk), self.skip_s(len(chunk)))
                self.stats.bytes_written += len(chunk)
            return
        payload = has_payload(data)
        out = data + padding_for(data) if self.policy.robust_encoding else data
        self._fit(len(out))
        interval = self.payload_interval_s()
        if payload:
            self._wait_until(self._last_payload_write + interval)
        write(out)
        if payload:
            self._last_payload_write = self.clock.now()
            self.stats.payload_commands += 1
        self._account(len(out), interval if payload else self.skip_s(len(out) - 1))
        self.stats.commands += 1
        self.stats.bytes_written += len(out)
        self.stats.padding_bytes += len(out) - len(data)


def default_pacer(port: Any) -> Pacer:
    """The pacer a port needs.

    * A port that declares ``pacing_clock`` (a timed emulator) is paced in that clock.
    * A port whose ``robust_encoding`` is true gets the loss-tolerant encoding.
    * A port that declares itself ``instant`` (every byte consumed as it is written) needs no waiting:
      its pacer only keeps the books.
    * Anything else — a real board, a pty — is paced in wall time.
    """
    policy = PacingPolicy(robust_encoding=bool(getattr(port, "robust_encoding", False)))
    clock = getattr(port, "pacing_clock", None)
    if clock is not None:
        return Pacer(clock=clock, policy=policy)
    if getattr(port, "instant", False) is True:
        return Pacer(clock=InstantClock())
    return Pacer(clock=MonotonicClock())
