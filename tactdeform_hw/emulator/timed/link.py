"""Host ↔ device link models and the device's 256-byte receive queue.

A link model turns "the host wrote these bytes at time t" into :class:`Delivery` chunks: the bytes the
device's receive path moves into its queue together, and when.  Two models matter for the eTactileKit:

* :class:`UartLink` — 921600 baud 8N1: ten bit times per byte (10.85 µs), bytes back to back, each
  delivered on its own as its stop bit ends.
* :class:`UsbFsLink` — USB full-speed CDC bulk: a write is cut into packets of at most 64 bytes; the host
  controller starts them at the next 1 ms frame (SOF) and sends them back to back inside the frame, each
  taking its wire time at 12 Mbit/s plus protocol overhead, at most ``max_packets_per_frame`` per frame.
  A whole packet reaches the device at once.

Both keep state (a link is busy until its last byte is out), so writes must come in time order.

**Fault injection hook.**  Everything between the host's ``write`` and the device's queue goes through
:meth:`LinkModel.schedule`.  :class:`LinkFilter` wraps any model and passes its deliveries through
:meth:`LinkFilter.transform`; a fault layer subclasses it and drops, corrupts, duplicates, delays or
withholds chunks there (``Delivery.host_offset`` keeps each chunk tied to the host's byte stream, so loss
reports still line up).  The same hook exists on the device-to-host side (``tx_link``).

**The receive queue** (:class:`ReceiveQueue`) is the firmware's: 256 bytes; a chunk is moved in byte by
byte and, at the first byte that does not fit, the rest of that chunk is discarded — the host is neither
held back nor told.
"""

from __future__ import annotations

from bisect import bisect_left, bisect_right
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from tactdeform_hw.errors import ConfigurationError, LimitError
from tactdeform_hw.protocol.constants import (
    BAUD_RATE,
    RX_QUEUE_SIZE,
    UART_BITS_PER_BYTE,
    USB_FRAME_US,
    USB_PACKET_SIZE,
)


@dataclass(frozen=True)
class Delivery:
    """Bytes that reach the device's receive path together, at ``t_ns``.

    ``host_offset`` is the offset of ``data[0]`` in the host's byte stream (-1 for bytes that did not
    come from it, e.g. injected noise); ``sent_ns`` is when the host wrote them."""

    t_ns: int
    data: bytes
    host_offset: int
    sent_ns: int


_new_object = object.__new__


def _delivery(t_ns: int, data: bytes, host_offset: int, sent_ns: int) -> Delivery:
    """A :class:`Delivery` made without the frozen dataclass's field-by-field ``__init__`` (half its cost;
    a UART makes one per byte): the same fields, equal and hashed alike."""
    d: Delivery = _new_object(Delivery)
    d.__dict__.update(t_ns=t_ns, data=data, host_offset=host_offset, sent_ns=sent_ns)
    return d


class ByteBurst:
    """The single-byte deliveries of one write, kept together: byte ``k`` of the write reaches the device
    on its own at ``times[k]``, exactly as the :class:`Delivery` :meth:`UartLink.schedule` makes for it
    (the same time, host offset and send time).  A UART delivers one byte per 10.85 µs; a model that moved
    each through its event queue spent most of a session doing so.  With the times known up front it
    moves, at once, the bytes that arrive before anything else can happen (a scan, a parser call, another
    delivery), and still takes one byte at a time wherever one byte matters (a full queue, a reboot).

    ``pos`` is the first byte not delivered yet; ``t_ns``, ``data`` and ``host_offset`` describe the
    bytes still on their way (from ``pos``), as a :class:`Delivery`'s fields do, so code that only sums
    or inspects what is in flight reads either alike."""

    __slots__ = ("_data", "times", "_host0", "sent_ns", "pos")

    def __init__(self, data: bytes, times: list[int], host_offset: int, sent_ns: int) -> None:
        if len(times) != len(data) or not data:
            raise ConfigurationError(
                f"a byte burst needs one arrival time per byte ({len(data)} bytes, {len(times)} times)"
            )
        self._data = data
        self.times = times
        self._host0 = host_offset
        self.sent_ns = sent_ns
        self.pos = 0

    def __len__(self) -> int:
        """Bytes still on their way."""
        return len(self._data) - self.pos

    @property
    def t_ns(self) -> int:
        """When the next byte arrives."""
        return self.times[self.pos]

    @property
    def data(self) -> bytes:
        """The bytes still on their way."""
        return self._data[self.pos :]

    @property
    def host_offset(self) -> int:
        """The host offset of the next byte (-1: not from the host's stream)."""
        return self._host0 + self.pos if self._host0 >= 0 else -1

    def pop(self) -> Delivery:
        """The next byte, as the single-byte :class:`Delivery` it stands for."""
        k = self.pos
        self.pos = k + 1
        return _delivery(
            self.times[k], self._data[k : k + 1], self._host0 + k if self._host0 >= 0 else -1, self.sent_ns
        )

    def deliveries(self) -> list[Delivery]:
        """Every byte still on its way, as single-byte deliveries (the burst is left as it was)."""
        h0, sent, data = self._host0, self.sent_ns, self._data
        return [
            _delivery(self.times[k], data[k : k + 1], h0 + k if h0 >= 0 else -1, sent)
            for k in range(self.pos, len(data))
        ]

    def end_before(self, t_ns: float, key: tuple[int, int] | None = None, seq: int = 0) -> int:
        """The index past the last byte that comes first: arriving at or before ``t_ns`` and, when another
        entry of the same event queue is keyed ``key`` = (time, sequence), before it (this burst's own
        sequence ``seq`` breaks a tie in time, as it would for each of its bytes)."""
        j = bisect_right(self.times, t_ns, self.pos)
        if key is not None:
            other_t, other_seq = key
            if other_t <= t_ns:
                cut = bisect_right if seq < other_seq else bisect_left
                j = min(j, cut(self.times, other_t, self.pos))
        return j

    def take(self, j: int) -> bytes:
        """The bytes up to index ``j`` (delivered: they leave the burst)."""
        out = self._data[self.pos : j]
        self.pos = j
        return out

    def host_offsets(self, j: int) -> range | None:
        """The host offsets of the bytes from ``pos`` up to index ``j`` (None: not from the host)."""
        return range(self._host0 + self.pos, self._host0 + j) if self._host0 >= 0 else None


#: What a link schedules for one write: deliveries, and runs of single-byte deliveries kept together.
Scheduled = Delivery | ByteBurst


def expanded(item: Scheduled) -> list[Delivery]:
    """What a link scheduled, as the deliveries it stands for (a burst: one per byte still on its way)."""
    return item.deliveries() if isinstance(item, ByteBurst) else [item]


def next_key(heap: list[tuple[int, int, Any]]) -> tuple[int, int] | None:
    """(time, sequence) of the earliest entry of an event heap after its root (the root's two children)."""
    n = len(heap)
    if n < 2:
        return None
    a = heap[1]
    if n > 2 and (heap[2][0], heap[2][1]) < (a[0], a[1]):
        a = heap[2]
    return (a[0], a[1])


class LinkModel:
    """Base class: ``schedule`` turns one host write into deliveries (and advances the link's state)."""

    name = "link"
    #: Whether a byte can be lost, corrupted or duplicated on this link without either end being told
    #: (a UART has no checksum; USB's CRC turns such faults into reported transfer errors).
    loses_bytes = False

    def schedule(self, data: bytes, t_ns: int, host_offset: int = -1) -> list[Delivery]:
        raise NotImplementedError

    def schedule_bursts(self, data: bytes, t_ns: int, host_offset: int = -1) -> list[Scheduled]:
        """:meth:`schedule`, where a run of single-byte deliveries may come as one :class:`ByteBurst`
        standing for exactly those deliveries (by default, never)."""
        return list(self.schedule(data, t_ns, host_offset))

    def arrival_times(self, data: bytes, t_ns: int) -> np.ndarray:
        """Per-byte delivery times of one write (advances the link's state like :meth:`schedule`)."""
        out = np.zeros(len(data), dtype=np.int64)
        i = 0
        for d in self.schedule(data, t_ns, 0):
            out[i : i + len(d.data)] = d.t_ns
            i += len(d.data)
        return out[:i]

    def reset(self) -> None:
        """Forget the link's state (idle, nothing in flight)."""

    def wire_ns(self, nbytes: int) -> int:
        """Nominal time for ``nbytes`` on an idle link, from the write to the last byte's delivery,
        excluding any wait for a frame boundary."""
        raise NotImplementedError

    def describe(self) -> dict[str, Any]:
        return {"name": self.name}


@dataclass
class UartLink(LinkModel):
    """A UART: ``bits_per_byte`` bit times per byte (8N1 → 10), bytes delivered one by one."""

    baud: int = BAUD_RATE
    bits_per_byte: int = UART_BITS_PER_BYTE
    _busy_until_ns: int = field(default=0, repr=False)
    name = "uart"
    loses_bytes = True

    def __post_init__(self) -> None:
        if not isinstance(self.baud, int) or self.baud <= 0:
            raise LimitError("baud", self.baud, "a positive integer")
        if not isinstance(self.bits_per_byte, int) or self.bits_per_byte <= 0:
            raise LimitError("bits_per_byte", self.bits_per_byte, "a positive integer")

    def _offset_ns(self, nbytes: int) -> int:
        # exact integer arithmetic from the start of the write: no drift over long bursts
        return (nbytes * self.bits_per_byte * 1_000_000_000) // self.baud

    def schedule(self, data: bytes, t_ns: int, host_offset: int = -1) -> list[Delivery]:
        start = max(t_ns, self._busy_until_ns)
        step = self.bits_per_byte * 1_000_000_000
        baud = self.baud
        out = [
            _delivery(
                start + ((i + 1) * step) // baud,  # = _offset_ns(i + 1), inlined: one per byte
                data[i : i + 1],
                host_offset + i if host_offset >= 0 else -1,
                t_ns,
            )
            for i in range(len(data))
        ]
        if data:
            self._busy_until_ns = start + self._offset_ns(len(data))
        return out

    def schedule_bursts(self, data: bytes, t_ns: int, host_offset: int = -1) -> list[Scheduled]:
        """The write as one :class:`ByteBurst`: the bytes and times of :meth:`schedule`."""
        if not data:
            return []
        start = max(t_ns, self._busy_until_ns)
        step = self.bits_per_byte * 1_000_000_000
        baud = self.baud
        n = len(data)
        if n >= 16 and type(start) is int and type(step) is int and type(baud) is int:
            # the same integer arithmetic, one array operation per step (a pattern is a long write)
            times = (np.arange(1, n + 1, dtype=np.int64) * step // baud + start).tolist()
        else:
            times = [start + (i * step) // baud for i in range(1, n + 1)]
        self._busy_until_ns = start + self._offset_ns(n)
        return [ByteBurst(bytes(data), times, host_offset, t_ns)]

    def arrival_times(self, data: bytes, t_ns: int) -> np.ndarray:
        start = max(t_ns, self._busy_until_ns)
        n = len(data)
        if n:
            self._busy_until_ns = start + self._offset_ns(n)
        return (
            start + (np.arange(1, n + 1, dtype=np.int64) * (self.bits_per_byte * 1_000_000_000)) // self.baud
        )

    def reset(self) -> None:
        self._busy_until_ns = 0

    def wire_ns(self, nbytes: int) -> int:
        return self._offset_ns(nbytes)

    def describe(self) -> dict[str, Any]:
        return {
            "name": self.name,
            "baud": self.baud,
            "bits_per_byte": self.bits_per_byte,
            "byte_us": self._offset_ns(1000) / 1e6,
        }


@dataclass
class UsbFsLink(LinkModel):
    """USB full-speed CDC bulk OUT: 64-byte packets scheduled from the next 1 ms frame.

    ``packet_overhead_bytes`` (token, sync, PID, CRC, handshake, gaps; an assumption) and the 12 Mbit/s
    bus give a 64-byte packet about 51 µs; ``max_packets_per_frame`` (19, the full-speed bulk ceiling) caps
    one frame.  SOFs fall on multiples of ``frame_us`` from time 0 (assumption)."""

    packet_size: int = USB_PACKET_SIZE
    frame_us: int = USB_FRAME_US
    max_packets_per_frame: int = 19
    bit_rate_hz: int = 12_000_000
    packet_overhead_bytes: int = 13
    _frame: int = field(default=-1, repr=False)
    _count: int = field(default=0, repr=False)
    _used_ns: int = field(default=0, repr=False)
    name = "usb"

    def __post_init__(self) -> None:
        for name in ("packet_size", "frame_us", "max_packets_per_frame", "bit_rate_hz"):
            v = getattr(self, name)
            if not isinstance(v, int) or v <= 0:
                raise LimitError(name, v, "a positive integer")
        if not isinstance(self.packet_overhead_bytes, int) or self.packet_overhead_bytes < 0:
            raise LimitError("packet_overhead_bytes", self.packet_overhead_bytes, "an integer >= 0")
        if self.max_packets_per_frame * self._packet_ns(self.packet_size) > self.frame_us * 1000:
            raise ConfigurationError(
                f"max_packets_per_frame={self.max_packets_per_frame} packets of {self.packet_size} bytes do "
                f"not fit a {self.frame_us} µs frame at {self.bit_rate_hz} bit/s"
            )

    def _packet_ns(self, nbytes: int) -> int:
        bits = (nbytes + self.packet_overhead_bytes) * 8
        return -(-bits * 1_000_000_000 // self.bit_rate_hz)

    def schedule(self, data: bytes, t_ns: int, host_offset: int = -1) -> list[Delivery]:
        frame_ns = self.frame_us * 1000
        first = t_ns // frame_ns + 1
        if first > self._frame:
            self._frame, self._count, self._used_ns = first, 0, 0
        out: list[Delivery] = []
        for i in range(0, len(data), self.packet_size):
            chunk = data[i : i + self.packet_size]
            if self._count >= self.max_packets_per_frame:
                self._frame, self._count, self._used_ns = self._frame + 1, 0, 0
            self._used_ns += self._packet_ns(len(chunk))
            self._count += 1
            out.append(
                Delivery(
                    self._frame * frame_ns + self._used_ns,
                    bytes(chunk),
                    host_offset + i if host_offset >= 0 else -1,
                    t_ns,
                )
            )
        return out

    def reset(self) -> None:
        self._frame, self._count, self._used_ns = -1, 0, 0

    def wire_ns(self, nbytes: int) -> int:
        full, rest = divmod(nbytes, self.packet_size)
        return full * self._packet_ns(self.packet_size) + (self._packet_ns(rest) if rest else 0)

    def describe(self) -> dict[str, Any]:
        return {
            "name": self.name,
            "packet_size": self.packet_size,
            "frame_us": self.frame_us,
            "max_packets_per_frame": self.max_packets_per_frame,
            "bit_rate_hz": self.bit_rate_hz,
            "packet_overhead_bytes": self.packet_overhead_bytes,
            "packet_us": self._packet_ns(self.packet_size) / 1000,
        }


class LinkFilter(LinkModel):
    """Wraps a link model; override :meth:`transform` to alter what reaches the device.

    This is the hook point for fault injection: ``transform`` sees every :class:`Delivery` the wrapped
    link produced for one write and returns the deliveries that really happen (fewer, altered, more,
    later).  Deliveries may come back in any order; the emulator sorts them by time."""

    def __init__(self, inner: LinkModel) -> None:
        self.inner = inner
        self.name = f"{type(self).__name__}({inner.name})"
        self.loses_bytes = inner.loses_bytes

    def schedule(self, data: bytes, t_ns: int, host_offset: int = -1) -> list[Delivery]:
        return self.transform(self.inner.schedule(data, t_ns, host_offset))

    def schedule_bursts(self, data: bytes, t_ns: int, host_offset: int = -1) -> list[Scheduled]:
        """Every delivery through :meth:`transform` (a filter that lets a burst through unchanged
        overrides this)."""
        return list(self.schedule(data, t_ns, host_offset))

    def transform(self, deliveries: list[Delivery]) -> list[Delivery]:
        return deliveries

    def reset(self) -> None:
        self.inner.reset()

    def wire_ns(self, nbytes: int) -> int:
        return self.inner.wire_ns(nbytes)

    def describe(self) -> dict[str, Any]:
        return {"name": self.name, "inner": self.inner.describe()}


LINK_NAMES = ("usb", "uart")


def make_link(link: str | LinkModel) -> LinkModel:
    """A link model by name (``usb`` / ``uart``) or the model itself."""
    if isinstance(link, LinkModel):
        return link
    if link == "usb":
        return UsbFsLink()
    if link == "uart":
        return UartLink()
    raise LimitError("link", link, " or ".join(LINK_NAMES))


def reply_link(link: str | LinkModel) -> LinkModel:
    """The link replies travel back over when none is named: the same kind as the host's (a UART at the
    same baud rate and frame, else full-speed USB), looking through fault filters to the link itself."""
    inner: LinkModel = make_link(link)
    while hasattr(inner, "inner"):
        inner = inner.inner
    return UartLink(inner.baud, inner.bits_per_byte) if isinstance(inner, UartLink) else UsbFsLink()


def unread_after(read_starts_ns: list[int], t_ns: int) -> int:
    """How many of a parser call's reads (``read_starts_ns``, ascending: when the firmware begins each byte's
    read) start at ``t_ns`` or later: bytes the call took from the model's queue that the firmware has not
    read yet at ``t_ns``, which still take room in its queue (``ReceiveQueue.offer``'s ``unread``).  Both
    timed models ask it for an arrival: runEtactileKit() reads a payload a byte (a u16's two) at a time."""
    if not read_starts_ns or read_starts_ns[-1] < t_ns:
        return 0
    return len(read_starts_ns) - bisect_left(read_starts_ns, t_ns)


class ReceiveQueue:
    """The firmware's receive queue: bytes delivered and not yet read by the parser."""

    def __init__(self, capacity: int = RX_QUEUE_SIZE) -> None:
        if not isinstance(capacity, int) or capacity < 1:
            raise LimitError("capacity", capacity, "an integer >= 1")
        self.capacity = capacity
        self.buf = bytearray()
        self.high_water = 0

    def __len__(self) -> int:
        return len(self.buf)

    @property
    def free(self) -> int:
        return self.capacity - len(self.buf)

    def offer(self, data: bytes, unread: int = 0) -> int:
        """Move a chunk in byte by byte; return how many bytes fitted (the rest is discarded).  ``unread``:
        bytes a parser call has taken out of ``buf`` that the firmware has not read yet -- they still
        take room in its queue."""
        take = min(len(data), self.capacity - len(self.buf) - unread)
        if take > 0:
            self.buf += data[:take]
            if len(self.buf) > self.high_water:
                self.high_water = len(self.buf)
        return max(take, 0)

    def join(self, data: bytes, peak: int) -> None:
        """Bytes that arrived one by one while the parser read (all fitted); ``peak`` is the most bytes
        that waited at one of their arrivals."""
        self.buf += data
        self.high_water = max(self.high_water, peak)

    def take(self, n: int) -> bytes:
        out = bytes(self.buf[:n])
        del self.buf[:n]
        return out

    def clear(self) -> bytes:
        out = bytes(self.buf)
        self.buf.clear()
        return out
