"""Fail-safe: the firmware never goes on stimulating an old pattern with nobody driving it.

The firmware has no host watchdog of its own: once a pattern and a pulse height are set it scans them
forever.  So the host must switch everything off whenever its owner stops, for whatever reason.
:class:`FailSafe` covers:

* **normal close and exceptions** — ``with FailSafe(device):`` closes the device (every channel off, then
  the port) however the block ends;
* **SIGINT, SIGTERM, SIGHUP and SIGQUIT** — one process-wide handler stops every watched device at once
  (if the signal arrived in the middle of a write, it starts with the resync zeros, because the firmware
  may hold half a command), then raises ``KeyboardInterrupt`` (SIGINT) or :class:`SignalStop`, a
  ``SystemExit`` with status 128 + the signal, so the program unwinds and exits with the status a shell
  expects.  A second signal while the first one's all-off is on the wire is ignored.  The handler runs
  wherever the signal caught the main thread — in the middle of a device operation, of an audit line —
  so every lock on the way to the wire is reentrant; and should the all-off still not finish within
  :data:`STOP_DEADLINE_S`, the process exits and the guardian switches the board off;
* **interpreter exit** — an ``atexit`` hook closes every device still open;
* **a stalled renderer** — a watchdog thread sends all-off when no frame (``send_pattern``, ``set_current``
  or ``keepalive``) came for ``watchdog_s`` (default 100 ms): it acts early enough (one poll and the link's
  latency before the deadline) that the all-off reaches the firmware within ``watchdog_s``; the scan in
  progress then finishes, so no channel stays on longer than ``watchdog_s`` plus one scan period.  The
  thread runs while the main thread sleeps, waits for a key or computes; it never starts between the
  commands of the owner's own operation (a frame is written whole or not at all).  The stop keeps the
  target current and the caller's last frame, so when frames come again stimulation resumes — from
  height 0, under the ramp limit when the profile has one;
* **a parser out of step** — optionally, a probe every ``probe_interval_s`` (a measure request must be
  answered with exactly two bytes per channel) and a refresh every ``refresh_interval_s`` (the height and
  the pattern the firmware should hold are written again, overwriting anything a lost or corrupted byte
  changed).  A failed probe, a failed write or a vanished port triggers :meth:`FailSafe.recover`:
  resync (256 zeros, height 0, all-off, the whole configuration), reconnecting the port if it is gone,
  and, if the firmware still does not answer (a locked parser reads nothing, ever), a pulse on the
  board's reset line.

**Every command that can stimulate.**  :class:`StopSession` is the process-wide form: while it is active,
every device opened (by whatever code: a command, the study runner, a renderer) is adopted — watched by a
:class:`FailSafe` with its watchdog thread — and the four signals stop them all.  The command-line tool
runs every command inside one (:func:`tactdeform_hw.cli.common.run_command`), so a new command cannot
forget it.  The watchdog thread runs in wall time; a device paced on a simulated clock (the offline
in-process emulator, whose board dies with the process) is watched for signals and exceptions only.

**Recovery time.**  With probing and refreshing every ``T`` seconds, a fault that the link does not report
is overwritten or detected within ``T`` plus the time of one poll — the probe that falls due while the owner
is calling runs before the owner's next write (:attr:`Device.before_stimulating`), so an owner that never
pauses cannot starve it — plus the probe's own wait for its reply behind as full a queue as the pacer
allows (:meth:`Device.probe_bound_s`); recovery (resync) then takes about 20 payload commands (≈ 25 ms at
the paced rate; on firmware v2 a board whose parser waits for a command's end adds its 2 s timeout), and
the firmware applies the all-off within one parser tick and one scan period.
:meth:`FailSafe.recovery_bound_s` returns that bound for the settings in use; the fault-injection tests
hold every injected fault to it.

**When the owner runs no code.**  A process killed with SIGKILL, or one that crashes in native code, runs
no handler: its guardian process (:mod:`.guardian`), started with every device on a port that can be
guarded, switches the board off.  What neither can do: if the guardian is killed too, or the host loses
power, nothing runs and the firmware keeps stimulating until the board is unplugged (the controller is
USB-powered, so unplugging stops it).  A byte corrupted on a link without a checksum can set any pulse
height until the next refresh or probe.
"""

from __future__ import annotations

import _thread
import atexit
import logging
import os
import signal
import threading
import weakref
from collections.abc import Callable
from dataclasses import dataclass, field
from types import FrameType, TracebackType
from typing import TYPE_CHECKING, Any

from tactdeform_hw.clock import Clock, InstantClock, MonotonicClock
from tactdeform_hw.device.driver.readback import OFF_READING_CODES
from tactdeform_hw.errors import (
    DecodeError,
    DeviceGoneError,
    LimitError,
    PortNotOpenError,
    ReplyLengthError,
    TactDeformError,
    TransportError,
)

if TYPE_CHECKING:
    from tactdeform_hw.device.driver.base import Device

logger = logging.getLogger("tactdeform_hw.failsafe")

DEFAULT_WATCHDOG_S = 0.100
DEFAULT_POLL_S = 0.002
LINK_MARGIN_S = 0.002

#: The signals that stop a watched device: Ctrl-C, ``kill``, a closed terminal, Ctrl-\.
STOP_SIGNALS: tuple[signal.Signals, ...] = (signal.SIGINT, signal.SIGTERM, signal.SIGHUP, signal.SIGQUIT)
#: The longest the stop handler may take to switch every device off.  Past it the process exits at once
#: (status 128 + the signal) and each device's guardian, seeing its owner gone, switches the board off: a
#: stop that blocks for good (on a lock the code it interrupted holds) must not leave a process that never
#: ends in front of a board that goes on stimulating.
STOP_DEADLINE_S = 10.0

_open_devices: weakref.WeakSet[Device] = weakref.WeakSet()
_atexit_installed = False


def _close_all_at_exit() -> None:
    for dev in list(_open_devices):
        try:
            if not dev.closed:
                dev.close()
        except Exception:  # exiting: nothing else can be done, but say so
            logger.exception("all-off at exit failed for %r", dev)


def register_at_exit(device: Device) -> None:
    """Close ``device`` (all channels off) when the interpreter exits."""
    global _atexit_installed
    _open_devices.add(device)
    if not _atexit_installed:
        atexit.register(_close_all_at_exit)
        _atexit_installed = True


class SignalStop(SystemExit):
    """Raised by the stop handler after every watched device was switched off (``all_off`` says whether
    that worked).  A ``SystemExit`` whose code is 128 + the signal, as a shell reports a signalled tool."""

    def __init__(self, signum: int, all_off: bool = True, devices: int = 0) -> None:
        super().__init__(128 + signum)
        self.signum = signum
        self.all_off = all_off
        self.devices = devices

    @property
    def signal_name(self) -> str:
        return signal.Signals(self.signum).name


@dataclass(frozen=True)
class StopRecord:
    """The last stop by signal: which signal, how many devices it switched off, whether all-off worked."""

    signum: int
    devices: int
    all_off: bool

    @property
    def signal_name(self) -> str:
        return signal.Signals(self.signum).name


#: Every started :class:`FailSafe`; the stop handler switches all of their devices off.
_active: list[FailSafe] = []
_active_lock = threading.RLock()  # the stop handler takes it, maybe while the code it interrupted holds it
_handlers_users = 0
_old_handlers: dict[int, Any] = {}
_stopping = False
last_stop: StopRecord | None = None


def _install_handlers() -> bool:
    """Install the stop handler for :data:`STOP_SIGNALS` (main thread only; counted, so nested users
    restore the original handlers only when the last one leaves)."""
    global _handlers_users
    if threading.current_thread() is not threading.main_thread():
        return False
    if _handlers_users == 0:
        for sig in STOP_SIGNALS:
            _old_handlers[sig] = signal.signal(sig, _on_stop_signal)
    _handlers_users += 1
    return True


def _uninstall_handlers() -> None:
    global _handlers_users
    if _handlers_users <= 0:
        return
    _handlers_users -= 1
    if _handlers_users == 0:
        for sig, old in _old_handlers.items():
            try:
                signal.signal(sig, old)
            except (ValueError, TypeError):  # not the main thread any more, or a foreign handler
                pass
        _old_handlers.clear()


def _stop_all(signum: int, extra: FailSafe | None = None) -> StopRecord:
    """Switch off every watched device (and ``extra``'s): the stop handler's work."""
    global last_stop
    with _active_lock:
        watched = list(_active)
    if extra is not None and extra not in watched:
        watched.append(extra)
    for fs in watched:
        fs.halt_watch()
    ok = True
    count = 0
    for fs in watched:
        done = fs.switch_off_for_signal(signum)
        if done is not None:
            count += 1
            ok = ok and done
    last_stop = StopRecord(signum, count, ok)
    return last_stop


def _raise_for(signum: int, record: StopRecord) -> None:
    if signum == signal.SIGINT:
        raise KeyboardInterrupt
    raise SignalStop(signum, record.all_off, record.devices)


def _backstop(signum: int, done: Any, deadline_s: float) -> None:
    """Exit the process when the stop has not finished within ``deadline_s`` (see :data:`STOP_DEADLINE_S`).
    Raw ``_thread`` primitives and ``os.write`` only: it must not need a lock the stuck stop might hold."""
    if done.acquire(True, deadline_s):
        done.release()
        return
    msg = (
        f"tactdeform-hw: stopped by {signal.Signals(signum).name}; the all-off did not finish within "
        f"{deadline_s:g} s: exiting, so the guardian of every guarded port switches its board off "
        "(a board on any other port may still be stimulating: unplug it)\n"
    )
    try:
        os.write(2, msg.encode("utf-8", "replace"))
    finally:
        os._exit(128 + signum)


def _on_stop_signal(signum: int, frame: FrameType | None) -> None:
    global _stopping
    if _stopping:  # the first signal's all-off is on the wire: let it finish
        return
    _stopping = True
    done = _thread.allocate_lock()  # held while the stop runs: a plain thread start takes threading's locks
    done.acquire()
    try:
        try:
            _thread.start_new_thread(_backstop, (signum, done, STOP_DEADLINE_S))
        except RuntimeError:  # the interpreter is shutting down: no new thread, but the stop itself runs
            logger.debug("no stop deadline: cannot start a thread")
        record = _stop_all(signum)
    finally:
        done.release()
        _stopping = False
    _raise_for(signum, record)


def _wall_clock(clock: Clock) -> bool:
    return isinstance(clock, (MonotonicClock, InstantClock))


class StopSession:
    """While active, every device opened in this process is watched (see the module docstring), and
    SIGINT, SIGTERM, SIGHUP and SIGQUIT switch them all off before the program unwinds.  On leaving,
    every device it adopted is closed (every channel off), however the block ends."""

    def __init__(self, **failsafe_kwargs: Any) -> None:
        self.failsafe_kwargs = failsafe_kwargs
        self.watched: list[FailSafe] = []
        self._handlers = False

    def __enter__(self) -> StopSession:
        global last_stop
        last_stop = None
        self._handlers = _install_handlers()
        _sessions.append(self)
        return self

    def adopt(self, device: Device) -> FailSafe:
        kw = dict(self.failsafe_kwargs)
        kw.setdefault("thread", _wall_clock(device.pacer.clock))
        fs = FailSafe(device, signals=False, **kw).start()
        self.watched.append(fs)
        return fs

    def __exit__(self, *exc_info: Any) -> None:
        """Every device watched stopped as its fail-safe's own exit does (``exc_info`` passed on)."""
        exc = exc_info[1]
        try:
            if self in _sessions:
                _sessions.remove(self)
            failed: BaseException | None = None
            for fs in self.watched:
                try:
                    fs.__exit__(*exc_info)
                except BaseException as e:  # close the others first, then report the first failure
                    failed = failed or e
            self.watched.clear()
            if failed is not None and exc is None:
                raise failed
        finally:
            if self._handlers:
                self._handlers = False
                _uninstall_handlers()


_sessions: list[StopSession] = []


def adopt(device: Device) -> FailSafe | None:
    """Called by every device as it opens: watched when a :class:`StopSession` is active."""
    if not _sessions:
        return None
    return _sessions[-1].adopt(device)


@dataclass
class FailSafeEvent:
    kind: str
    t: float
    detail: dict[str, Any] = field(default_factory=dict)


class FailSafe:
    """Watches one device.  Use as a context manager, or ``start()`` / ``stop()``.

    ``clock`` defaults to the device's pacing clock, so in a simulated session (a timed emulator) the
    watchdog runs in simulated time: drive it with :meth:`poll` (``thread=False``).  ``signals`` installs
    the process-wide stop handler (main thread only); every started fail-safe is stopped by it either way.
    """

    def __init__(
        self,
        device: Device,
        *,
        watchdog_s: float | None = DEFAULT_WATCHDOG_S,
        probe_interval_s: float | None = None,
        refresh_interval_s: float | None = None,
        poll_s: float = DEFAULT_POLL_S,
        verify_readback: bool = False,
        signals: bool = True,
        at_exit: bool = True,
        thread: bool = True,
        clock: Clock | None = None,
        on_event: Callable[[FailSafeEvent], None] | None = None,
    ) -> None:
        for name, value in (
            ("watchdog_s", watchdog_s),
            ("probe_interval_s", probe_interval_s),
            ("refresh_interval_s", refresh_interval_s),
        ):
            if value is not None and not (isinstance(value, (int, float)) and value > 0 and value == value):
                raise TactDeformError(f"{name}={value!r} must be a positive number of seconds or None")
        self.device = device
        self.watchdog_s = watchdog_s
        self.probe_interval_s = probe_interval_s
        self.refresh_interval_s = refresh_interval_s
        self.poll_s = poll_s
        #: The all-off must reach the firmware within ``watchdog_s`` of the last frame: act that much
        #: earlier than the deadline (one poll, the USB frame and a packet's wire time).
        self.watchdog_trigger_s = (
            max(0.0, watchdog_s - poll_s - LINK_MARGIN_S) if watchdog_s is not None else None
        )
        self.verify_readback = verify_readback
        self.readback = Readback()
        self.clock: Clock = clock if clock is not None else device.pacer.clock
        self.on_event = on_event
        self.events: list[FailSafeEvent] = []
        self.watchdog_trips = 0
        self.recoveries = 0
        #: Time the owner's calls spent waiting for probes (and recoveries) run before their writes.
        self.owner_wait_s = 0.0
        self._want_signals = signals
        self._want_atexit = at_exit
        self._want_thread = thread
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        self._handlers = False
        self._last_probe: float | None = None
        self._last_refresh: float | None = None
        self._turn = threading.Lock()  # held while a look at the device runs (a poll, or before a write)
        self._probe_failure: str | None = None
        self._transport_failed = False

    # --- lifecycle -----------------------------------------------------------------------------------------

    def start(self) -> FailSafe:
        if self._want_atexit:
            register_at_exit(self.device)
        with _active_lock:
            if self not in _active:
                _active.append(self)
        if self._want_signals and not self._handlers:
            self._handlers = _install_handlers()
        if self.device.before_stimulating is None:
            self.device.before_stimulating = self._before_stimulating
        if self._want_thread and self._thread is None:
            self._stop.clear()
            self._thread = threading.Thread(target=self._run, name="tactdeform-failsafe", daemon=True)
            self._thread.start()
        return self

    def halt_watch(self) -> None:
        """Tell the watcher thread to end at its next wake-up (without waiting for it: a signal handler's
        stop switches every device off first)."""
        self._stop.set()

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join(timeout=2.0)
        self._thread = None
        if self.device.before_stimulating == self._before_stimulating:
            self.device.before_stimulating = None
        with _active_lock:
            if self in _active:
                _active.remove(self)
        if self._handlers:
            self._handlers = False
            _uninstall_handlers()

    def __enter__(self) -> FailSafe:
        return self.start()

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.stop()
        try:
            self.device.close()
        except TactDeformError:
            if exc is None:
                raise
            logger.exception("all-off on exit failed")

    # --- what the owner's absence triggers -----------------------------------------------------------------

    def _event(self, kind: str, **detail: Any) -> FailSafeEvent:
        ev = FailSafeEvent(kind, self.clock.now(), detail)
        self.events.append(ev)
        audit = self.device.audit
        if audit is not None:
            audit.event(kind, t=ev.t, **detail)
        log = logger.warning if kind not in ("refresh", "probe_ok", "signal") else logger.debug
        log("fail-safe %s %s", kind, detail)
        if self.on_event is not None:
            self.on_event(ev)
        return ev

    def switch_off_for_signal(self, signum: int) -> bool | None:
        """Every channel off and the port closed; True when that worked, None when already closed."""
        dev = self.device
        if dev.closed:
            return None
        ok = True
        try:
            if dev.writing:  # the signal cut a write: the firmware may hold half a command
                dev.mark_unknown()
            dev.close()
        except Exception:
            ok = False
            logger.exception("all-off on signal %s failed", signum)
        try:
            self._event("signal", signal=signal.Signals(signum).name, all_off=ok)
        except Exception:  # an audit log that cannot be written must not stop the stop
            logger.exception("recording the signal failed")
        return ok

    def _on_signal(self, signum: int, frame: FrameType | None) -> None:
        """The stop handler, as seen from this fail-safe: switch off every watched device, this one
        included, then raise."""
        _raise_for(signum, _stop_all(signum, extra=self))

    def _run(self) -> None:
        while not self._stop.wait(self.poll_s):
            try:
                self.poll()
            except PortNotOpenError:
                return
            except Exception:
                logger.exception("fail-safe poll failed")

    def poll(self, now: float | None = None) -> None:
        """One look at the device: watchdog, then probe and refresh when due.  Re-entrant calls (a poll
        whose own writes advance a simulated clock) and calls while another look runs are ignored."""
        if self.device.closed or self.device.busy:
            # never in the middle of the owner's own operation: a frame is written whole or not at all
            return
        if not self._turn.acquire(blocking=False):
            return
        try:
            self._poll(self.clock.now() if now is None else now)
        finally:
            self._turn.release()

    def _before_stimulating(self) -> None:
        """The owner is about to write (a frame, a height, a configuration): a probe that is due runs
        first.  Between back-to-back calls the poll never finds the device free, and a frame proves
        nothing (on a link without replies the bytes may go nowhere), so without this an owner that never
        pauses would keep a stalled or desynchronised parser from ever being noticed.  A failed probe
        recovers before the owner's call goes on (:meth:`recover`)."""
        if self.probe_interval_s is None or self.device.closed:
            return
        if not self._turn.acquire(blocking=False):
            return  # the fail-safe is looking already (its own refresh, or its thread waiting its turn)
        now = self.clock.now()
        try:
            if self.device.config is not None and self._probe_due(now):
                self._probe_now(now)
        finally:
            self.owner_wait_s += self.clock.now() - now
            self._turn.release()

    def _probe_due(self, now: float) -> bool:
        interval = self.probe_interval_s
        return interval is not None and (self._last_probe is None or now - self._last_probe >= interval)

    def _probe_now(self, now: float) -> bool:
        """Probe; on failure recover (True when the probe passed)."""
        self._last_probe = now
        if not self._guarded(lambda: self._probe(now)):
            self.recover(self._probe_failure or "probe unanswered")
            return False
        return True

    def _poll(self, now: float) -> None:
        dev = self.device
        if dev.config is None:
            return
        last = dev.last_frame_time
        trigger = self.watchdog_trigger_s
        if trigger is not None and last is not None and now - last > trigger and dev.stimulating:
            self.watchdog_trips += 1
            self._guarded(dev.suspend)
            self._event("watchdog", idle_s=round(now - last, 6), limit_s=self.watchdog_s)
        if dev.needs_resync:
            self.recover("a write failed", transport=self._transport_failed)
            return
        if self._probe_due(now) and not self._probe_now(now):
            return
        if self.refresh_interval_s is not None and (
            self._last_refresh is None or now - self._last_refresh >= self.refresh_interval_s
        ):
            self._last_refresh = now
            cfg = dev.config
            # the readback sees a sense current on the off channels when none is configured: there the
            # sense height is left out (each write of it is one more byte a duplicate can raise)
            watched = self.verify_readback and cfg is not None and not cfg.sense_current_ua
            self._guarded(lambda: dev.refresh(sense=not watched))

    def _probe(self, now: float) -> bool:
        """A measure must come back whole; with ``verify_readback`` its voltages must also fit what the
        host set (see :class:`Readback`)."""
        dev = self.device
        self._probe_failure = None
        cfg = dev.config
        if cfg is None:
            return True
        try:
            volts = dev.measure()
        except (ReplyLengthError, LimitError, DecodeError):
            dev.mark_unknown()
            self._probe_failure = "probe unanswered"
            return False
        if not self.verify_readback:
            return True
        settled = dev.last_state_write is None or now - dev.last_state_write > 1.5 / cfg.rate_hz + 0.003
        pattern = dev.last_pattern
        if not settled or pattern is None or cfg.sense_current_ua:
            return True
        problem = self.readback.check(volts, pattern, dev.current_ua)
        if problem is not None:
            self._probe_failure = f"readback: {problem}"
            dev.mark_unknown()
            return False
        return True

    def _guarded(self, fn: Callable[[], Any]) -> Any:
        """Run a device operation; a transport failure marks the device for recovery instead of raising."""
        try:
            return fn()
        except (TransportError, TactDeformError) as exc:
            if isinstance(exc, PortNotOpenError) and self.device.closed:
                raise
            self._transport_failed = isinstance(exc, TransportError)
            self.device.mark_unknown()
            self._event("error", error=f"{type(exc).__name__}: {exc}")
            return False

    def recover(self, reason: str, *, transport: bool = False) -> bool:
        """Bring the firmware back in step: resync; reset if it still does not answer (a hung or locked
        parser reads nothing, ever); reconnect when the port itself failed (then that comes first).
        Raises :class:`DeviceGoneError` when nothing works (stimulation state unknown: unplug the board)."""
        dev = self.device
        self.recoveries += 1
        self._transport_failed = False
        self._event("recover", reason=reason)
        steps: list[tuple[str, Callable[[], Any]]] = [
            ("resync", dev.resync),
            ("reset", dev.hardware_reset),
            ("reconnect", dev.reconnect),
        ]
        if transport:
            steps = [steps[2], steps[0], steps[1]]
        tried: set[str] = set()
        while steps:
            name, step = steps.pop(0)
            if name in tried:
                continue
            tried.add(name)
            try:
                if step() is False or dev.needs_resync:
                    continue  # no transport for it, or the board did not answer the step's own request
                if dev.probe():
                    self._event("recovered", by=name)
                    return True
            except (TransportError, TactDeformError) as exc:
                if isinstance(exc, PortNotOpenError) and dev.closed:
                    raise
                self._event("recover_step_failed", step=name, error=f"{type(exc).__name__}: {exc}")
                if isinstance(exc, TransportError) and "reconnect" not in tried:
                    # the port itself failed: reopen it before anything else
                    steps = [s for s in steps if s[0] == "reconnect"] + [
                        s for s in steps if s[0] != "reconnect"
                    ]
        self._event("unrecoverable", reason=reason)
        raise DeviceGoneError(
            f"the firmware does not answer after resync, reconnect and reset ({reason}); it may still be "
            "stimulating: unplug the board"
        )

    def recovery_bound_s(
        self, scan_period_s: float = 0.008, resync_s: float | None = None, probe_s: float | None = None
    ) -> float:
        """The longest a fault the link does not report can affect stimulation with these settings: it is
        noticed by the next probe (or overwritten by the next refresh) — due within one interval and one
        poll, and run before the owner's next write even when the owner never pauses — the probe waits for
        its reply until its deadline, a resync is tried and probed again, and the reset that follows stops
        everything at once; the scan in progress finishes.  Infinite without probing or refreshing.  The
        owner's operation that is running when the probe falls due comes on top (the fail-safe never cuts
        into it).

        ``probe_s`` (the longest the probe waits, behind as full a queue as the pacer allows) and
        ``resync_s`` (the longest a failing resync waits before the reset line) default to the device's
        own :meth:`~tactdeform_hw.device.driver.base.Device.probe_bound_s` and
        :meth:`~tactdeform_hw.device.driver.base.Device.resync_bound_s`, which know its firmware (v2 waits
        out a
        2 s command timeout).  A read that blocks for the port's timeout past a deadline counts twice."""
        if resync_s is None:
            resync_s = self.device.resync_bound_s()
        if probe_s is None:
            probe_s = self.device.probe_bound_s()
        interval = min(
            x for x in (self.probe_interval_s, self.refresh_interval_s, float("inf")) if x is not None
        )
        if interval == float("inf"):
            return float("inf")
        timeout = float(getattr(getattr(self.device, "port", None), "timeout", None) or 0.0)
        return interval + self.poll_s + probe_s + 2 * timeout + resync_s + scan_period_s + 0.002


class Readback:
    """Checks a measure reply (each channel's voltage during its last pulse) against what the host set.

    * A channel the pattern has off (with sense current 0) is pulsed at height 0: it must read (almost)
      0.  A voltage there means current reaches a channel meant off.
    * A channel the pattern has on, at a height of at least ``min_ua``, must read clearly above 0.
    * Per channel, the ratio voltage / set current is learned from readings that passed; a reading far
      above ``ratio × current`` means the height in force is higher than the host set.

    It is a heuristic on a real finger (contact changes impedance), exact on the emulator's skin model,
    and opt-in (``FailSafe(verify_readback=True)``): a false alarm costs one resync, a missed fault is
    still bounded by the refresh.
    """

    def __init__(
        self,
        *,
        off_codes: int = OFF_READING_CODES,
        min_ua: int = 200,
        rise: float = 1.3,
        slack_codes: int = 3,
    ) -> None:
        self.off_codes = off_codes
        self.min_ua = min_ua
        self.rise = rise
        self.slack_codes = slack_codes
        self.ratio: dict[int, float] = {}

    def check(self, volts: list[int], pattern: bytes, height_ua: int) -> str | None:
        n = min(len(volts), len(pattern))
        learned: dict[int, float] = {}
        for ch in range(n):
            on = pattern[ch] in (1, 2)
            v = volts[ch]
            if not on or height_ua == 0:
                if v > self.off_codes:
                    return f"channel {ch} is meant off but reads {v}"
                continue
            if height_ua < self.min_ua:
                continue
            if v <= self.off_codes:
                return f"channel {ch} is meant on at {height_ua} µA but reads {v}"
            r = self.ratio.get(ch)
            if r is not None and v > r * height_ua * self.rise + self.slack_codes:
                return f"channel {ch} reads {v}, more than {height_ua} µA gives ({r * height_ua:.0f})"
            learned[ch] = v / height_ua
        self.ratio.update(learned)
        return None


def refresh(device: Device) -> None:
    """Write again the height and the pattern the firmware should hold (see :meth:`Device.refresh`)."""
    device.refresh()
