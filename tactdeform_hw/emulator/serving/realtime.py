"""The timed emulator locked to the wall clock, for a board served behind a real port.

A :class:`RealtimeEmulator` holds one :class:`~.timed.TimedEmulator` and keeps its clock on wall time:
host bytes are stamped on arrival and enter the link and receive-queue model at that moment; replies
reach the host when the model delivers them; scans run, so 0xFF answers with the skin model's voltages.
The model itself is event-exact and causal, so simulating a stretch in one step gives the same result
as simulating it as it happens — what the wall clock decides is *when input enters* and *when output
leaves*.  Two ways to drive it:

* lazily (the ``etactile://`` URL handler): every host call first brings the model up to now; nothing
  can observe it in between, so nothing runs in between;
* from a server loop (:mod:`.pty_server`, :mod:`.tcp_server`): the loop sleeps until
  :meth:`RealtimeEmulator.wait_s` says the next event is due (a delivery, a parser call, a reply, an
  alarm), then calls :meth:`~RealtimeEmulator.catch_up`.  How late each wake-up comes is the *lag*,
  recorded in :attr:`RealtimeEmulator.lag`; every wake-up later than ``behind_limit_us`` is a
  :class:`FallBehind` record.

:class:`BuildRules` says how the firmware build gets its bytes: the serial build's USB link and 256-byte
queue that discards what does not fit, or the Wi-Fi build's TCP stream, where flow control holds the
host back (the server takes bytes from the socket only while the receive path has room) and one client
is served at a time.

A reset (:meth:`RealtimeEmulator.reset`: DTR/RTS, SIGUSR1, a new client) power-cycles the model at the
current wall time and returns a :class:`ResetRecord` naming the state it discarded.

``firmware="v2"`` serves :class:`~.timed_v2.TimedEmulatorV2` the same way (its 1024-byte queue, whole
payloads, the 2 s command timeout); a new client is told to it (:meth:`RealtimeEmulator.client_opened`),
because on v2 a command the previous client cut takes the new client's first bytes within 2 s.
"""

from __future__ import annotations

import socket
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from tactdeform_hw.emulator.core import Emulator
from tactdeform_hw.emulator.firmware.board import Board
from tactdeform_hw.emulator.firmware.hazards import Hazard, HazardKind
from tactdeform_hw.emulator.firmware.models import model_entry
from tactdeform_hw.emulator.firmware.skin import SkinModel
from tactdeform_hw.emulator.timed.base import TimedModel
from tactdeform_hw.emulator.timed.link import Delivery, LinkModel
from tactdeform_hw.emulator.timed.timing import DEFAULT_MODEL, TimingModel
from tactdeform_hw.errors import ConfigurationError
from tactdeform_hw.protocol.firmware import V1_2, FirmwareSpec, get_firmware
from tactdeform_hw.protocol.state import BoardState

#: how late a wake-up may come before it counts as falling behind the wall clock
BEHIND_LIMIT_US = 1000.0
#: records older than this are dropped from the model's books while serving (memory stays bounded)
HISTORY_US = 10e6
#: lwIP's default TCP receive window on the ESP32 Arduino core (4 × 1436-byte segments): what the Wi-Fi
#: build holds before TCP flow control stops the host
TCP_WINDOW_BYTES = 5744


class TcpLink(LinkModel):
    """A TCP stream as the Wi-Fi build sees it: bytes the server took from the socket are in the
    firmware's receive buffer at once (network latency is the real network's; over loopback, none)."""

    name = "tcp"

    def schedule(self, data: bytes, t_ns: int, host_offset: int = -1) -> list[Delivery]:
        return [Delivery(t_ns, bytes(data), host_offset, t_ns)] if data else []

    def wire_ns(self, nbytes: int) -> int:
        return 0


@dataclass(frozen=True)
class BuildRules:
    """How a firmware build receives bytes and writes replies.

    ``link``: the host→device link model (``usb``, ``uart`` or ``tcp``).  ``flow_control``: the
    transport holds the host back (TCP) — the server takes bytes only while the receive path has room,
    so nothing is lost; without it (serial) every byte is taken and the queue discards what does not
    fit.  ``receive_bytes``: the receive path's capacity (``None``: the timing model's 256-byte queue).
    ``one_client``: a new client is served only after the current one has gone."""

    name: str
    link: str
    flow_control: bool
    receive_bytes: int | None = None
    one_client: bool = True

    def make_link(self) -> str | LinkModel:
        return TcpLink() if self.link == "tcp" else self.link

    def timing(self, model: TimingModel | None) -> TimingModel:
        m = model if model is not None else DEFAULT_MODEL
        return m if self.receive_bytes is None else m.with_(rx_queue_bytes=self.receive_bytes)


SERIAL_USB = BuildRules("serial", "usb", flow_control=False)
SERIAL_UART = BuildRules("serial-uart", "uart", flow_control=False)
WIFI_TCP = BuildRules("wifi", "tcp", flow_control=True, receive_bytes=TCP_WINDOW_BYTES)
BUILD_RULES = {r.name: r for r in (SERIAL_USB, SERIAL_UART, WIFI_TCP)}


@dataclass(frozen=True)
class FallBehind:
    """A wake-up that came ``lag_us`` after the event it was for (device time ``due_us``)."""

    due_us: float
    lag_us: float

    def __str__(self) -> str:
        return f"fell behind the wall clock by {self.lag_us / 1000:.2f} ms at t={self.due_us:.1f}us"


class LagRecorder:
    """Lag of every wake-up (µs): a bounded window of samples for the distribution, the maximum and
    every fall-behind beyond ``limit_us`` (all of them counted; the latest ``keep`` kept)."""

    def __init__(self, limit_us: float = BEHIND_LIMIT_US, window: int = 200_000, keep: int = 10_000) -> None:
        self.limit_us = limit_us
        self.samples: deque[float] = deque(maxlen=window)
        self.count = 0
        self.max_us = 0.0
        self.behind_count = 0
        self.behind: deque[FallBehind] = deque(maxlen=keep)

    def record(self, due_us: float, lag_us: float) -> FallBehind | None:
        lag_us = max(0.0, lag_us)
        self.samples.append(lag_us)
        self.count += 1
        if lag_us > self.max_us:
            self.max_us = lag_us
        if lag_us > self.limit_us:
            fb = FallBehind(due_us, lag_us)
            self.behind_count += 1
            self.behind.append(fb)
            return fb
        return None

    def stats(self) -> dict[str, float | int]:
        """``median_us``, ``p99_us``, ``max_us`` (over the window; max over the whole run), ``wakeups``,
        ``behind``."""
        xs = sorted(self.samples)
        if not xs:
            return {"median_us": 0.0, "p99_us": 0.0, "max_us": 0.0, "wakeups": 0, "behind": 0}
        return {
            "median_us": xs[len(xs) // 2],
            "p99_us": xs[min(len(xs) - 1, int(len(xs) * 0.99))],
            "max_us": self.max_us,
            "wakeups": self.count,
            "behind": self.behind_count,
        }


@dataclass(frozen=True)
class ResetRecord:
    """A power-on reset and the state it discarded."""

    reason: str
    time_us: float
    discarded: dict[str, Any]

    def __str__(self) -> str:
        d = self.discarded
        regs = ", ".join(f"{k}={d[k]}" for k in _SHOWN if k in d)
        on = d.get("channels_on", [])
        return (
            f"reset ({self.reason}) at t={self.time_us:.1f}us, discarded: {regs}; "
            f"{len(on)} channel(s) on {_ranges(on)}; {d.get('queue_bytes', 0)} byte(s) in the queue; "
            f"parser {d.get('parser', '?')}"
        )


#: The registers a reset record and the live view show, by the firmware's names (``BoardState.as_dict``).
_SHOWN = (
    "electrode_num",
    "polarity",
    "stim_mode",
    "pulse_height",
    "pulse_width",
    "sense_pulse_height",
    "sense_pulse_width",
    "discharge_time",
    "period_us",
)


def _shown(state: BoardState) -> dict[str, Any]:
    """The registers of :data:`_SHOWN` the version has."""
    regs = state.as_dict()
    return {k: regs[k] for k in _SHOWN if k in regs}


def _channels_on(state: BoardState) -> list[int]:
    """Channels the scans give current: v1.2 pattern values 1 and 2; v2 a non-zero height (mode 0/1) or,
    in mode 2, every channel (the sense pulse) when the sense height is not 0."""
    n = state.electrode_num
    pattern = state.scanned_pattern
    if state.stim_mode is None:  # v1.2: the pattern byte picks the waveform
        return [i for i, v in enumerate(pattern) if v in (1, 2)]
    if state.stim_mode == 2:
        return list(range(n)) if state.sense_pulse_height else []
    return [i for i, v in enumerate(pattern) if v]


def _ranges(chs: list[int]) -> str:
    if not chs:
        return ""
    out: list[str] = []
    start = prev = chs[0]
    for c in [*chs[1:], None]:
        if c is not None and c == prev + 1:
            prev = c
            continue
        out.append(f"{start}" if start == prev else f"{start}-{prev}")
        if c is not None:
            start = prev = c
    return "[" + ",".join(out) + "]"


@dataclass
class LiveStatus:
    """What the firmware developer's live view shows: registers in force, queue depth, scan rate,
    overruns, hazards, losses, lag."""

    time_us: float
    registers: dict[str, Any]
    queue_depth: int
    scans: int
    scans_per_s: float
    overrun_cycles: int
    hazards: int
    lost_bytes: int
    resets: int
    behind: int
    new_hazards: list[Hazard] = field(default_factory=list)

    def key(self) -> tuple[Any, ...]:
        """What must change for the view to be printed again (not the clock, not the scan count)."""
        return (
            tuple(sorted(self.registers.items())),
            self.queue_depth,
            round(self.scans_per_s, 1),
            self.overrun_cycles,
            self.hazards,
            self.lost_bytes,
            self.resets,
            self.behind,
        )

    def lines(self) -> list[str]:
        r = self.registers
        on = list(r.get("on", ()))
        drive = (
            f"mode={r['stim_mode']} max height={max(r.get('pattern', ()), default=0)}"
            if "stim_mode" in r
            else f"height={r.get('pulse_height')}"
        )
        head = (
            f"t={self.time_us:.0f}us electrodes={r.get('electrode_num')} polarity={r.get('polarity')} "
            f"{drive} width={r.get('pulse_width')}µs "
            f"sense={r.get('sense_pulse_height')}/{r.get('sense_pulse_width')}µs "
            f"discharge={r.get('discharge_time')}µs period={r.get('period_us'):.2f}µs "
            f"on={len(on)}{_ranges(on)}"
        )
        body = (
            f"  queue={self.queue_depth}B scans/s={self.scans_per_s:.1f} overruns={self.overrun_cycles} "
            f"hazards={self.hazards} lost={self.lost_bytes}B resets={self.resets} behind={self.behind}"
        )
        out = [head, body]
        shown = self.new_hazards[:5]
        out += [f"  hazard: {h}" for h in shown]
        if len(self.new_hazards) > len(shown):
            out.append(f"  ... and {len(self.new_hazards) - len(shown)} more hazard(s)")
        return out


class LiveView:
    """The firmware developer's live view: at most once per ``interval_s``, and only when something
    changed (registers in force, queue depth, scan rate, overruns, hazards, losses, resets, fall-behinds).
    ``hazards=False`` leaves out the hazard lines, for a caller that prints each hazard at once."""

    def __init__(self, interval_s: float = 1.0, hazards: bool = True) -> None:
        self.interval_s = interval_s
        self.hazards = hazards
        self._key: tuple[Any, ...] | None = None
        self._last = -float("inf")

    def poll(self, board: RealtimeEmulator, now: float) -> list[str]:
        """Lines to print now (none if it is too soon or nothing changed)."""
        if now - self._last < self.interval_s:
            return []
        status = board.status()
        if not self.hazards:
            status.new_hazards = []
        key = status.key()
        if key == self._key and not status.new_hazards:
            return []
        self._key = key
        self._last = now
        return status.lines()


class RealtimeEmulator:
    """One timed emulator on the wall clock.  Thread-safe: a server thread drives it, the main thread
    reads its status and resets it.  See the module documentation."""

    def __init__(
        self,
        board: str = "compact",
        switching_boards: int = 1,
        *,
        rules: BuildRules = SERIAL_USB,
        model: TimingModel | None = None,
        skin: SkinModel | None = None,
        stack_reading: float | None = None,
        clock: Callable[[], float] = time.monotonic,
        behind_limit_us: float = BEHIND_LIMIT_US,
        follow_scans: bool = True,
        history_us: float = HISTORY_US,
        firmware: str | FirmwareSpec = "v1.2",
        timed: TimedModel | None = None,
    ) -> None:
        """``timed``: a model already made (a host-built firmware,
        :class:`~tactdeform_hw.emulator.hostbuild.timed.HostBuildTimedModel`) served in place of the
        Python model of ``firmware``; its own ``firmware`` is the one served (``None``: a firmware that is
        no eTactileKit)."""
        self.rules = rules
        self.firmware: FirmwareSpec | None
        if timed is not None:
            self.firmware = timed.firmware
            self.timed: TimedModel = timed
        else:
            entry = model_entry(firmware)
            self.firmware = entry.spec
            self.timed = entry.timed_class().served(
                board,
                switching_boards,
                link=rules.make_link(),
                tx_link=TcpLink() if rules.link == "tcp" else None,
                model=rules.timing(model),
                skin=skin,
                stack_reading=stack_reading,
            )
        self.lock = threading.RLock()
        self._clock = clock
        self._t0 = clock()  # wall-clock time of device time 0
        self.lag = LagRecorder(behind_limit_us)
        self.follow_scans = follow_scans
        self.history_us = history_us
        self._trimmed_at = 0.0
        self.resets: list[ResetRecord] = []
        self.bytes_in = 0
        self.bytes_out = 0
        self._status_seen = 0
        self.on_behind: Callable[[FallBehind], None] | None = None

    # --- what the board looks like from outside ----------------------------------------------------

    @property
    def emulator(self) -> Emulator:
        """The firmware's parser and registers (the untimed face: ``state()``, ``hazards``)."""
        return self.timed.emulator

    @property
    def hazards(self) -> list[Hazard]:
        return self.timed.hazards

    @property
    def board(self) -> Board:
        return self.timed.board

    def state(self) -> BoardState:
        """The registers as of now (the model is brought up to the wall clock first)."""
        with self.lock:
            self.advance_now()
            return self.timed.state()

    # --- the clock -----------------------------------------------------------------------------------

    def start_clock(self) -> None:
        """Make now device time 0, if the model has not run yet (a server starting up after the board was
        made: the boot's first events are not counted as late)."""
        with self.lock:
            if self.timed.now_us == 0 and self.bytes_in == 0:
                self._t0 = self._clock()

    @property
    def t0(self) -> float:
        """The wall-clock time (``clock()``) of device time 0: device µs = (wall − t0) × 1e6."""
        return self._t0

    def device_us(self, t: float | None = None) -> float:
        """Device time for wall-clock time ``t`` (default now): µs since power-up, never behind the model."""
        now = self._clock() if t is None else t
        return max(self.timed.now_us, (now - self._t0) * 1e6)

    def advance_now(self, t: float | None = None) -> float:
        """Run the model to the wall clock's now (or ``t``) and return that device time; old history is
        trimmed on the way (a board served for hours keeps a bounded memory)."""
        at = self.device_us(t)
        self.timed.advance_to(at)
        if at - self._trimmed_at > self.history_us:
            self._trimmed_at = at
            self.timed.discard_history(at - self.history_us)
        return at

    def catch_up(self, record_lag: bool = True) -> bytes:
        """Run the model to now and return the replies that reached the host.  With ``record_lag`` (a
        server loop that slept until :meth:`wait_s`), how late this wake-up came is recorded."""
        with self.lock:
            due = self.timed.next_event_us(self.follow_scans)
            at = self.advance_now()
            out = self.timed.read_tx()
            self.bytes_out += len(out)
        if record_lag and due <= at + 0.001:  # a wake-up for an event now due (1 ns of float rounding)
            fb = self.lag.record(due, at - due)
            if fb is not None and self.on_behind is not None:
                self.on_behind(fb)
        return out

    def wait_s(self, cap_s: float = 0.1) -> float:
        """Seconds until the model's next event (at most ``cap_s``; 0 if it is due)."""
        with self.lock:
            nxt = self.timed.next_event_us(self.follow_scans)
            now = self.device_us()
        return max(0.0, min(cap_s, (nxt - now) / 1e6))

    # --- host traffic ----------------------------------------------------------------------------------

    @property
    def received_bytes(self) -> int:
        """Bytes that reached the board since power-on (see :attr:`TimedEmulator.received_bytes`)."""
        with self.lock:
            return int(self.timed.received_bytes)

    def write(self, data: bytes, t: float | None = None) -> int:
        """Host bytes arriving at wall-clock time ``t`` (default now) enter the link model then."""
        with self.lock:
            at = self.advance_now(t)
            self.bytes_in += len(data)
            return self.timed.write(bytes(data), at)

    def read(self, size: int | None = None) -> bytes:
        """Replies that have reached the host by now."""
        with self.lock:
            self.advance_now()
            out = self.timed.read_tx(size)
            self.bytes_out += len(out)
            return out

    @property
    def in_waiting(self) -> int:
        with self.lock:
            self.advance_now()
            return self.timed.in_waiting

    def room(self) -> int:
        """Bytes the receive path can take now without losing any (flow-controlled builds)."""
        with self.lock:
            self.advance_now()
            return max(0, self.timed.queue.free - self.timed.in_flight)

    def client_opened(self, name: str) -> bytes:
        """A new host connection.  Returns the replies written before it (no host read them: they are
        not the new host's).  On v2 a command the previous host cut can take this host's first bytes as
        its payload (see :meth:`~.timed_v2.TimedEmulatorV2.new_client`)."""
        with self.lock:
            self.advance_now()
            stale = self.timed.read_tx()
            self.timed.new_client(name)
            return stale

    # --- reset ---------------------------------------------------------------------------------------

    def reset(self, reason: str) -> ResetRecord:
        """Power-cycle the board now; the record names the state that was discarded."""
        with self.lock:
            at = self.advance_now()
            discarded: dict[str, Any] = {}
            if self.firmware is not None:  # a host build's firmware may declare no board state
                regs = self.timed.state()
                discarded = _shown(regs)
                discarded["channels_on"] = _channels_on(regs)
            discarded["queue_bytes"] = len(self.timed.queue)
            discarded["parser"] = self.timed.parser_status()
            discarded["replies_unread"] = len(self.timed.read_tx())
            self.timed.reset(reason)
            rec = ResetRecord(reason, at, discarded)
            self.resets.append(rec)
            return rec

    # --- live view ----------------------------------------------------------------------------------

    def status(self) -> LiveStatus:
        with self.lock:
            at = self.advance_now()
            t = self.timed
            regs = t.state()
            shown = _shown(regs)
            shown["pattern"] = regs.scanned_pattern
            shown["on"] = tuple(_channels_on(regs))
            scans, rate = _scan_rate(t, at)
            hz = t.hazards
            new = hz[self._status_seen :]
            self._status_seen = len(hz)
            overruns = sum(int(h.detail.get("cycles", 1)) for h in hz if h.kind is HazardKind.OVERRUN)
            lost = sum(int(h.detail.get("bytes_lost", 0)) for h in hz if h.kind is HazardKind.QUEUE_OVERFLOW)
            return LiveStatus(
                at,
                shown,
                len(t.queue),
                scans,
                rate,
                overruns,
                len(hz),
                lost,
                len(self.resets),
                self.lag.behind_count,
                list(new),
            )


def _scan_rate(t: TimedModel, at_us: float) -> tuple[int, float]:
    """Scans since power-up and the current scan rate (0 when the scans stopped)."""
    return t.scan_rate(at_us)


# --- serving a board on a byte stream ------------------------------------------------------------------

ByteHook = Callable[[str, bytes, float], None]


def reset_untimed(emulator: Emulator, reason: str) -> ResetRecord:
    """Power-cycle an untimed :class:`~.core.Emulator` and say what it discarded (no clock: time 0)."""
    regs = emulator.state()
    discarded = _shown(regs)
    discarded["channels_on"] = _channels_on(regs)
    discarded["queue_bytes"] = regs.rx_pending
    pending = emulator.parser.processing
    discarded["parser"] = "locked" if emulator.locked else "mid-command" if pending else "between commands"
    emulator.reset()
    return ResetRecord(reason, 0.0, discarded)


def check_served_firmware(board: Any, firmware: str | FirmwareSpec | None) -> None:
    """Refuse a server's ``firmware`` that contradicts the board it was given: a server never claims a
    version it does not serve (None: whatever the board runs)."""
    if firmware is None:
        return
    served: FirmwareSpec = getattr(board, "firmware", V1_2)
    if get_firmware(firmware) is not served:
        raise ConfigurationError(f"firmware={firmware!r}, but the board given runs {served.name!r}")


class BoardServer:
    """What the pty and TCP servers share: the board (a :class:`RealtimeEmulator`, or an untimed
    :class:`~.core.Emulator` that answers at once), a loop thread, resets from any thread, the bytes a
    client has not read yet.

    ``hook(direction, data, t)`` sees every byte both ways (``host->dev``/``dev->host``) with a
    ``time.monotonic`` stamp; ``on_reset(record)`` is told of every reset; ``reset_on_open`` power-cycles
    the board whenever a client connects (a board plugged in fresh for each session)."""

    thread_name = "etactile-server"

    def __init__(
        self,
        board: Any = None,
        *,
        hook: ByteHook | None = None,
        reset_on_open: bool = False,
        on_reset: Callable[[ResetRecord], None] | None = None,
        poll_s: float = 0.05,
    ) -> None:
        self.board: Any = board if board is not None else RealtimeEmulator()
        self.timed = isinstance(self.board, RealtimeEmulator)
        self.hook = hook
        self.reset_on_open = reset_on_open
        self.on_reset = on_reset
        self.poll_s = poll_s
        self.resets: list[ResetRecord] = []
        self.connected = False
        self.clients = 0
        self.bytes_in = 0
        self.bytes_out = 0
        self.bytes_dropped = 0  # replies written while no client was connected
        self.cpu_s = 0.0  # CPU time of the serving thread
        self._out = bytearray()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._wake_r, self._wake_w = socket.socketpair()  # select() takes sockets on every platform
        self._wake_r.setblocking(False)
        self._wake_w.setblocking(False)

    @property
    def emulator(self) -> Any:
        """The firmware's parser and registers (``state()``, ``hazards``) whichever board is served."""
        return self.board.emulator if self.timed else self.board

    def state(self) -> BoardState:
        state: BoardState = self.board.state()
        return state

    # --- control from any thread --------------------------------------------------------------------

    def reset(self, reason: str) -> ResetRecord:
        """Power-on reset now (SIGUSR1, a new client, a test); bytes not yet sent to the client go too."""
        rec: ResetRecord = self.board.reset(reason) if self.timed else reset_untimed(self.board, reason)
        self._out.clear()
        self.resets.append(rec)
        if self.on_reset is not None:
            self.on_reset(rec)
        self.wake()
        return rec

    def wake(self) -> None:
        try:
            self._wake_w.send(b"x")
        except OSError:  # full (a wake-up is pending anyway) or closed
            pass

    def _drain_wake(self) -> None:
        try:
            while self._wake_r.recv(64):
                pass
        except OSError:
            pass

    # --- the loop's pieces ----------------------------------------------------------------------------

    def _incoming(self, data: bytes, t: float) -> None:
        self.bytes_in += len(data)
        if self.hook:
            self.hook("host->dev", data, t)
        if self.timed:
            self.board.write(data, t)
        else:
            self._queue_out(self.board.feed(data))

    def _queue_out(self, data: bytes) -> None:
        if not data:
            return
        if not self.connected:
            self.bytes_dropped += len(data)  # the firmware writes only while a client is there
            return
        if self.hook:
            self.hook("dev->host", data, time.monotonic())
        self._out += data

    def _begin(self) -> None:
        """The serving thread's first step: device time 0 is now, if the board has not run yet."""
        if self.timed:
            self.board.start_clock()

    def _tick(self) -> float:
        """Bring a timed board up to now, queue its replies; the seconds the loop may sleep."""
        if not self.timed:
            return self.poll_s
        self._queue_out(self.board.catch_up())
        return float(self.board.wait_s(self.poll_s))

    def _client_opened(self) -> None:
        self.clients += 1
        if self.timed:
            peer = getattr(self, "peer", None)
            name = f"client {self.clients}" + (f" ({peer[0]}:{peer[1]})" if peer else "")
            self.bytes_dropped += len(self.board.client_opened(name))  # written while no client was there
        self.connected = True
        if self.reset_on_open:
            self.reset("a client opened the port (--reset-on-open)")

    def _client_closed(self) -> None:
        self.connected = False
        self._out.clear()

    # --- thread ----------------------------------------------------------------------------------------

    def serve_forever(self) -> None:
        raise NotImplementedError

    def start(self) -> BoardServer:
        """Serve in a daemon thread (the CLI, tests and in-process tools)."""
        self._thread = threading.Thread(target=self.serve_forever, name=self.thread_name, daemon=True)
        self._thread.start()
        return self

    def _close_fds(self) -> None:
        pass

    def stop(self) -> None:
        self._stop.set()
        self.wake()
        if self._thread is not None:
            self._thread.join(timeout=5)
            self._thread = None
        self._close_fds()
        for sock in (self._wake_r, self._wake_w):
            sock.close()

    def __enter__(self) -> BoardServer:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()


def settle(board: RealtimeEmulator, timeout_s: float = 2.0, step_s: float = 0.0005) -> bool:
    """Wait (in wall time) until every byte sent has reached the parser and the parser has read all it
    will read (or is locked, or spins on half a u16).  False if that took longer than ``timeout_s``."""
    deadline = time.monotonic() + timeout_s
    while True:
        with board.lock:
            board.advance_now()
            idle = board.timed.run_until_idle(limit_us=0)
        if idle:
            return True
        if time.monotonic() >= deadline:
            return False
        time.sleep(step_s)


@dataclass(eq=False)
class UsbSerialJtagLines:
    """DTR and RTS as the ESP32-S3's USB Serial/JTAG controller reads them.

    The chip is held in reset while RTS is asserted and DTR is not (EN low on the classic auto-reset
    circuit); the reset ends when that stops.  DTR asserted with RTS not (IO0 low) arms the download
    boot; both lines low disarms it; both high keeps it — which is why esptool's USB-JTAG sequence goes
    ``(DTR,RTS) = (1,0) → (1,1) → (0,1) → (0,0)``: through (1,1), not (0,0), so the chip leaves reset into
    the ROM download mode.  esptool's hard reset (RTS high then low with DTR low) boots the application.
    This is the emulator's reading of the controller's behaviour, consistent with both esptool sequences;
    the ROM bootloader itself is not emulated (in download mode the application does not run)."""

    dtr: bool = False
    rts: bool = False
    held: bool = False
    armed: bool = False
    download_mode: bool = False
    _boot_download: bool = field(default=False, init=False, repr=False)

    def set(self, dtr: bool, rts: bool) -> str | None:
        """New line levels; returns ``"held"`` when the chip enters reset, ``"released"`` when it leaves
        it (``download_mode`` says into what), else ``None``."""
        self.dtr, self.rts = dtr, rts
        event = None
        in_reset = rts and not dtr
        if in_reset and not self.held:
            self.held = True
            self._boot_download = self.armed
            event = "held"
        elif self.held and not in_reset:
            self.held = False
            self.download_mode = self._boot_download
            self.armed = False
            event = "released"
        if dtr and not rts:
            self.armed = True
        elif not dtr and not rts:
            self.armed = False
        return event

    @property
    def running(self) -> bool:
        """The application runs (not held in reset, not in the ROM download mode)."""
        return not self.held and not self.download_mode


class BackgroundSink:
    """Hands a trace sink's work to a writer thread, so writing a waveform file (about 57 000 events per
    second at the TactDeform setting) does not hold up the real-time loop.  Same interface as a
    :class:`~.trace.TraceSink`; :meth:`close` waits until everything is written."""

    def __init__(self, sink: Any) -> None:
        import queue

        self.sink = sink
        self._q: queue.SimpleQueue[tuple[str, tuple[Any, ...]] | None] = queue.SimpleQueue()
        self._thread = threading.Thread(target=self._work, name="etactile-trace", daemon=True)
        self._thread.start()

    def _work(self) -> None:
        while True:
            item = self._q.get()
            if item is None:
                return
            getattr(self.sink, item[0])(*item[1])

    def begin(self, t_ns: int) -> None:
        self._q.put(("begin", (t_ns,)))

    def scan_run(self, run: Any) -> None:
        self._q.put(("scan_run", (run,)))

    def marker(self, t_ns: int, kind: str, detail: dict[str, Any]) -> None:
        self._q.put(("marker", (t_ns, kind, dict(detail))))

    def close(self) -> None:
        self._q.put(None)
        self._thread.join()
        self.sink.close()
