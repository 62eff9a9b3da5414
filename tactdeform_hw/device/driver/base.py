"""The device interface the renderer uses, written once; transports implement a few private methods.

Every public method checks its input, passes currents through the safety guard, refuses any sequence
that would trigger a known firmware defect, and only then builds bytes with :mod:`tactdeform_hw.protocol`
and writes them — one write per command.  ``close`` is idempotent and leaves every channel off.

Every byte leaves through the device's :class:`~.wire.Wire`, which passes it through the safety interlock
(:class:`~tactdeform_hw.device.safety.interlock.WireInterlock`), the pacer (:mod:`.pacing`: never faster
than the firmware reads) and the session's audit log (:mod:`.audit`); the dialect's link operations send
through the same wire.  The opening (port, identification, guardian, proof at open) is an
:class:`~.opening.Opener`'s.  Public methods hold one lock, so a fail-safe thread's all-off can never
interleave with a half-written frame.

Nothing that carries a value — a height, a width, an electrode count, a pattern — is written unless the
device has proved its parser at a command boundary with room in its queue: at open, after a failed or cut
write, a short or late reply, a reconnect or a reset, the closed-loop recovery (:class:`LinkState`,
the dialect's ``flush_parser``) gets a reply of the expected length first.  Its states and transitions are
drawn in ``docs/safety.md``.

Firmware v2 speaks other bytes for the same API (one height per electrode, a global waveform mode, the
sync check): the device sends, paces, audits and keeps the proofs; which bytes express an operation is its
dialect's (:mod:`.dialect`; :data:`~.dialects.DIALECTS` holds one per firmware spec, :mod:`.v1_2` and
:mod:`.v2`).  The recovery's states and record are :class:`~tactdeform_hw.device.links.recovery.LinkRecovery`.

Two currents are kept apart: the *target* (what the caller asked for with ``configure`` or
``set_current``) and the *height in force* (what the firmware's pulse-height register holds).  The height
of each frame is the target lowered to the frame's lowest limit (see :mod:`.safety`); when it goes down it
is written before the pattern, when it goes up after it, so no scan — not even one torn between the old
and the new pattern — combines a pattern with a height that is too high for it.
"""

from __future__ import annotations

import functools
import threading
import warnings
from collections.abc import Callable, Sequence
from typing import Concatenate, Generic, ParamSpec, TypedDict, TypeVar, cast, overload

from tactdeform_hw import protocol as p
from tactdeform_hw.clock import Clock, MonotonicClock
from tactdeform_hw.device.driver.audit import AuditLog
from tactdeform_hw.device.driver.checks import ALLOWED_LEVELS, check_levels, checked_config
from tactdeform_hw.device.driver.closing import CLOSE_RECONNECTS, close_link, stop_and_prove
from tactdeform_hw.device.driver.config import StimConfig
from tactdeform_hw.device.driver.dialect import Dialect, DriverState, LinkOps
from tactdeform_hw.device.driver.dialects import DIALECTS
from tactdeform_hw.device.driver.firmware_probe import (
    Detection,
    check_firmware_choice,
    recheck_firmware,
)
from tactdeform_hw.device.driver.opening import GuardianSlot, Opener, check_encoding_choice
from tactdeform_hw.device.driver.pacing import Pacer
from tactdeform_hw.device.driver.wire import Wire
from tactdeform_hw.device.links.port import Port, PortLink
from tactdeform_hw.device.links.recovery import (
    PROBE_LEAD_ZEROS,
    RECOVERY_ATTEMPTS,
    REPLY_POLL_S,
    TRANSITIONS,
    LinkRecovery,
    LinkState,
    probe_bound_s,
)
from tactdeform_hw.device.participant.mapping import ChannelMapping
from tactdeform_hw.device.safety.guard import SafetyGuard
from tactdeform_hw.device.safety.guardian import Guardian
from tactdeform_hw.errors import (
    DeviceTimeoutError,
    LimitError,
    ProtocolMisuseError,
    ReplyLengthError,
    SafetyError,
)
from tactdeform_hw.protocol.firmware import V1_2, FirmwareSpec
from tactdeform_hw.protocol.units import DEFAULT_TRANSFER, CurrentTransfer

_D = TypeVar("_D", bound="Device")
_P = ParamSpec("_P")
_R = TypeVar("_R")
_T = TypeVar("_T")


#: The public operations that keep the board stimulating without proving that its parser reads: before
#: each, a watcher's due check runs (:attr:`Device.before_stimulating`).  The others stop current
#: (``all_off``, ``suspend``, ``close``), prove the link themselves (``measure``, ``probe``,
#: ``hv513_count``) or rebuild it (``resync``, ``reconnect``, ``hardware_reset``).
STIMULATING_OPS = frozenset({"configure", "set_current", "send_pattern", "keepalive", "refresh"})


def _locked(fn: Callable[Concatenate[_D, _P], _R]) -> Callable[Concatenate[_D, _P], _R]:
    """Run a public method under the device lock, and name it as the origin of the bytes it sends."""
    stimulating = fn.__name__ in STIMULATING_OPS

    @functools.wraps(fn)
    def wrapper(self: _D, /, *args: _P.args, **kwargs: _P.kwargs) -> _R:
        with self._lock:
            outer = self._op is None
            if outer and stimulating and self.before_stimulating is not None:
                # before ``_op`` is set: the watcher's own operations are outer ones, named as theirs
                self.before_stimulating()
            if outer:
                self._op = fn.__name__
            try:
                return fn(self, *args, **kwargs)
            finally:
                if outer:
                    self._op = None

    return wrapper


class Part(Generic[_T]):
    """An attribute of a device that is one of its parts' (``part``: ``"state"``, the
    :class:`DriverState` — what the host believes the firmware holds, read-only here since it follows what
    the device sends — or ``"wire"``, the :class:`~.wire.Wire`, so the send path and the device never
    disagree on it)."""

    def __init__(self, part: str) -> None:
        self.part = part

    def __set_name__(self, owner: type, name: str) -> None:
        self.name = name

    @overload
    def __get__(self, obj: None, owner: type) -> Part[_T]: ...
    @overload
    def __get__(self, obj: Device, owner: type) -> _T: ...
    def __get__(self, obj: Device | None, owner: type) -> Part[_T] | _T:
        if obj is None:
            return self
        return cast(_T, getattr(getattr(obj, self.part), self.name))

    def __set__(self, obj: Device, value: _T) -> None:
        if self.part == "state":
            raise AttributeError(f"{self.name} is read-only: it follows what the device sends")
        setattr(getattr(obj, self.part), self.name, value)


class DeviceOptions(TypedDict, total=False):
    """The keyword options of :class:`Device` (each documented there, with its default) that
    :func:`~.serial_driver.open_device` passes on to it: named once, so what opening a device by name
    accepts is what the device takes, and the type checker holds the two together."""

    mapping: ChannelMapping | None
    transfer: CurrentTransfer
    guard: SafetyGuard | None
    pacer: Pacer | None
    audit: AuditLog | None
    guardian: bool | None
    offline_clock: Clock | None
    firmware: str
    settle_s: float | None
    robust_encoding: bool | None


class Device:
    """An eTactileKit-compatible stimulator behind ``port``, any pyserial-compatible port (a path, a URL,
    an in-process port; :class:`~tactdeform_hw.device.links.port.Port`), opened or not: an unopened one
    gets DTR/RTS low before it is opened.

    The board is driven only in the firmware version it has proved by a reply only that version gives
    (:mod:`.firmware_probe`): the constructor identifies it first, unless ``probe`` already holds that
    proof for this port.  ``firmware``: "auto" drives whichever version answered; "v1.2" or "v2" refuses a
    board that proved the other (:class:`~.firmware_probe.FirmwareMismatchError`); a board that proves
    neither is refused (:class:`~.firmware_probe.UnidentifiedBoardError`, or
    :class:`~tactdeform_hw.errors.BoardBusyError` on a port that serves one client at a time) after only
    bytes that stop current on both versions.

    ``mapping`` translates application electrode order to hardware channels (identity by default);
    ``transfer`` converts µA to DAC codes; ``guard`` enforces current limits; ``pacer`` spaces writes
    (by default what the port needs; ``offline_clock`` runs a port that answers at once on the caller's
    clock); ``robust_encoding``: the loss-tolerant encoding (True), the plain one (False) or the port's own
    (None; see :func:`~.serial_driver.open_device`).  ``audit`` records every command sent.  ``guardian``
    starts a guardian process with the device (default: when the port declares itself ``guardable``); a
    port that cannot be guarded with ``guardian=True`` is refused.
    """

    #: The firmware's boot after the reset line, during which nothing is written (an ESP32-S3 starts its
    #: application well within this; bytes arriving earlier would be lost).
    boot_s: float = 0.3
    #: Extra wait for a reply while the alarm period is unknown (a board opened in an unknown state).
    unknown_reply_s: float = 0.25
    #: What messages call this device (the eTactileKit driver's name, as users have read it).
    kind: str = "EtactileKitDevice"

    def __init__(
        self,
        port: Port,
        *,
        mapping: ChannelMapping | None = None,
        transfer: CurrentTransfer = DEFAULT_TRANSFER,
        guard: SafetyGuard | None = None,
        pacer: Pacer | None = None,
        audit: AuditLog | None = None,
        guardian: bool | None = None,
        offline_clock: Clock | None = None,
        firmware: str = "auto",
        probe: Detection | None = None,
        settle_s: float | None = None,
        robust_encoding: bool | None = None,
    ) -> None:
        check_firmware_choice(firmware)
        check_encoding_choice(pacer, robust_encoding)
        self._lock = threading.RLock()
        self._op: str | None = None
        #: Called under the device lock before each operation in :data:`STIMULATING_OPS`: a fail-safe's
        #: probe that is due runs there, so an owner that calls without a pause cannot starve it.
        self.before_stimulating: Callable[[], None] | None = None
        if guard is not None:
            # before anything is written: the calibrated channels must be the wired ones
            guard.check_wiring(mapping)
        self.guard = guard if guard is not None else SafetyGuard()
        #: What the host believes the firmware holds, and what the caller asked for.
        self.state = DriverState()
        #: The recovery state machine: what is proved about the firmware's parser (see :class:`LinkState`).
        self.link = LinkRecovery(lambda: self.pacer)
        # (time s, from, to, why) of the latest transitions, and when a reply last proved the parser
        self.transitions = self.link.transitions
        self.proofs = self.link.proofs
        self._resetting = False
        self.last_frame_time: float | None = None
        #: How this board's firmware expresses each operation (v1.2 until the board proves another).
        self.dialect: Dialect = DIALECTS[V1_2]
        self.port_link = PortLink(port, lambda s: self.pacer.clock.sleep(s))
        #: The send path and reply reading (pacer, interlock, audit), shared with the dialect's link ops.
        self.wire = Wire(
            self.port_link,
            self.guard,
            self.link,
            pacer if pacer is not None else Pacer(clock=MonotonicClock()),
            mapping=mapping,
            transfer=transfer,
            kind=self.kind,
            unknown_reply_s=self.unknown_reply_s,
            op=lambda: self._op or "",
        )
        self.audit = audit
        self.guardians = GuardianSlot(lambda: repr(self))
        opener = Opener(self.wire, self.guardians)
        opener.open_port(
            own_pacer=pacer is None, offline_clock=offline_clock, robust_encoding=robust_encoding
        )
        self.identification = (
            probe if probe is not None else opener.identify(self.link, settle_s=settle_s, boot_s=self.boot_s)
        )
        opener.accept(self.identification, firmware, guardian)
        self.speak(self.identification.firmware)
        opener.prove(self._lock, self._recover, self._suspect)
        from tactdeform_hw.device.safety.failsafe import adopt

        adopt(self)  # a command's stop session watches every device opened under it

    def speak(self, firmware: FirmwareSpec) -> None:
        """Drive the board in ``firmware``'s dialect (the version its identification proved): the
        interlock and the audit log read the bytes with that version's table from now on; a change of
        version leaves the interlock knowing nothing of the registers."""
        self.dialect = DIALECTS[firmware]
        if self.guard.firmware is not firmware:
            self.guard.firmware = firmware
            self.guard.mark_unknown()
        audit = self.audit
        if audit is not None:
            # the log says which firmware its bytes were written for
            audit.firmware = firmware
            audit.event("firmware", firmware=firmware.name)
        # v1.2's stop (a few zeros, then 0xFB 00 00 …) would complete a v2 pattern in progress with 0xFB as
        # a height's high byte: the guardian is given the dialect's stop
        self.guardians.set_stop(self.dialect.guardian_open_stop())

    @property
    def port(self) -> Port:
        """The port the device writes to (a caller may put a recording proxy of it in its place)."""
        return self.port_link.port

    @port.setter
    def port(self, port: Port) -> None:
        self.port_link.port = port

    #: The pacer that spaces this device's writes.
    pacer: Part[Pacer] = Part("wire")
    #: Application electrode order to hardware channels (None: identity), as the interlock reads it.
    mapping: Part[ChannelMapping | None] = Part("wire")
    #: µA to DAC codes, as the interlock reads it.
    transfer: Part[CurrentTransfer] = Part("wire")

    @property
    def guardian(self) -> Guardian | None:
        """The guardian process watching this device's owner (None on a port that cannot be guarded)."""
        return self.guardians.guardian

    # --- state ---------------------------------------------------------------------------------------------

    #: The configuration last sent (None until ``configure``).
    config: Part[StimConfig | None] = Part("state")
    #: The pulse height in force (µA): what an active channel receives now.
    current_ua: Part[int] = Part("state")
    #: The current the caller asked for; frames carry it lowered to their limits.
    target_ua: Part[int] = Part("state")
    #: The pattern the firmware should hold, in hardware order (None: unknown, e.g. after a resync).
    last_pattern: Part[bytes | None] = Part("state")
    #: True after a fail-safe stop; the next frame (or keepalive) resumes, ramped.
    suspended: Part[bool] = Part("state")
    #: Patterns written (a rewrite of the same pattern by ``keepalive`` is not one).
    frames_sent: Part[int] = Part("state")

    @property
    def audit(self) -> AuditLog | None:
        return self.wire.audit

    @audit.setter
    def audit(self, log: AuditLog | None) -> None:
        """Enable (or with None, disable) the audit log; the guard's refusals and clips go there too."""
        self.wire.audit = log
        if log is not None and self.guard.sink is None:
            self.guard.sink = log.safety

    @property
    def needs_resync(self) -> bool:
        """True until the device has proved its parser in step (after opening, a failed write, a short or
        late reply, a reopened port or a reset): the next command is preceded by a closed-loop resync."""
        return self.link.state is not LinkState.IN_STEP

    @property
    def link_state(self) -> LinkState:
        """Where the recovery state machine stands (see :class:`LinkState`)."""
        return self.link.state

    @property
    def _needs_resync(self) -> bool:
        return self.link.state is not LinkState.IN_STEP

    @_needs_resync.setter
    def _needs_resync(self, value: bool) -> None:
        # a fail-safe (or a signal handler) that saw a timeout, a bad readback or a cut write says so here
        if value:
            self._suspect("marked for resync")

    @property
    def busy(self) -> bool:
        """True while a public operation runs: another thread must not start one between its commands."""
        return self._op is not None

    @property
    def writing(self) -> bool:
        """True while bytes are being handed to the transport: a stop now may leave half a command."""
        return self.wire.writing

    @property
    def last_state_write(self) -> float | None:
        """When a write last changed what the scans deliver (None: none yet)."""
        return self.wire.last_state_write

    def mark_unknown(self) -> None:
        """Forget what the firmware holds (a cut write, an unanswered probe, a wrong readback): the next
        frame, and the next all-off, start with a resync."""
        with self._lock:
            self.guard.mark_unknown()
            self._needs_resync = True

    @_locked
    def refresh(self, *, sense: bool = True) -> None:
        """Write again what the scans deliver — the pulse height and the pattern the firmware should hold,
        and with ``sense`` the sense height (v2: the mode and the pattern of heights): the same bytes as
        before, so a firmware in step sees no change, and one that lost or mis-read a byte is put right.

        The v1.2 sense height is a current on every channel the pattern has off, and a duplicated ``f9``
        sets it to about 10 mA — including the duplicate of the ``f9`` a refresh writes.  So a caller
        whose readback already watches the off channels (sense current 0) passes ``sense=False`` and
        leaves the wire fewer bytes to turn into that current."""
        if self.state.config is None or self.wire.closed:
            return
        self.wire.run(self.dialect.refresh(self.wire.plan_context(), self.state, sense=sense), self.state)

    @property
    def stimulating(self) -> bool:
        """Whether the firmware, as far as the host knows, is delivering current to any channel."""
        return self.state.stimulating

    @property
    def closed(self) -> bool:
        return self.wire.closed

    @property
    def firmware(self) -> str:
        """The firmware version this device speaks to its board (``"v1.2"`` or ``"v2"``)."""
        return self.dialect.firmware.name

    @property
    def heights_in_force(self) -> list[int] | None:
        """Firmware v2: each application electrode's DAC code the firmware's pattern buffer should hold
        (None on v1.2, whose buffer holds the levels themselves)."""
        return self.dialect.heights_in_force(self.state, self.mapping)

    @property
    def electrodes(self) -> int:
        """Application electrodes a pattern must have (0 until configured)."""
        if self.state.config is None:
            return 0
        return self.mapping.electrodes if self.mapping is not None else self.state.config.electrode_count

    # --- commands ------------------------------------------------------------------------------------------

    @_locked
    def configure(self, config: StimConfig) -> None:
        """Send a whole configuration in an order that never stimulates with a half-set state.

        The height goes to 0 and every channel off first (so no pulse uses a mixture of old and new
        settings), the electrode count is followed at once by an all-off pattern of the new length (so no
        stale channel above the old count comes back), polarity changes while all is off, and the
        participant's current comes last.  The order and bytes are the dialect's.
        """
        self.wire.check_open()
        config = checked_config(
            config,
            dialect=self.dialect,
            guard=self.guard,
            transfer=self.transfer,
            mapping=self.mapping,
            robust=self.pacer.robust,
            stimulating=self.stimulating,
            polarity_in_force=self.state.config.polarity if self.state.config is not None else None,
        )
        # the caller's frame is superseded now, whether or not the writes below get through: no keepalive
        # after a failed configure brings the old frame back
        self.state.requested = None
        self.state.suspended = False
        self.dialect.check_configuration(self.wire.guard, config)
        if self._needs_resync:
            self._recover()
        plan = self.dialect.configure(self.wire.plan_context(), self.state, config, self.wire.pace_in_force())
        self.wire.run(plan, self.state, prove=self._prove)
        self.guardians.tell(self.dialect, self.state.config)

    @_locked
    def set_current(self, current_ua: int) -> None:
        """Change the target current; the pulse height follows at once, lowered to the limits of the
        pattern in force (and to the ramp step)."""
        cfg = self._require_config("set_current")
        target = self.guard.request(self.guard.validate_current(current_ua, self.transfer))
        self.state.target_ua = target
        self.state.config = cfg.with_current(target)
        self._mark_frame()
        if self._needs_resync:
            self.resync()
            return
        levels = None if self.state.suspended else self.state.application_levels(self.mapping)
        self.wire.run(self.dialect.set_current(self.wire.plan_context(), self.state, levels), self.state)

    @_locked
    def send_pattern(self, levels: Sequence[int]) -> None:
        """Send a pattern in application order: 0 off, 1 monophasic, 2 biphasic.

        The frame's pulse height is the target lowered to the lowest limit of the electrodes it activates
        (see :mod:`.safety`); a needed height change is written before the pattern when it lowers the
        height and after it when it raises it."""
        self._require_config("send_pattern")
        check_levels(levels, self.electrodes, self.dialect, self.guard)
        previous = self.state.requested
        self.state.requested = list(levels)
        try:
            if self._needs_resync:
                self.resync()
            self._frame(self.state.requested, force_pattern=True)
        except SafetyError:
            # A refused frame is not the caller's frame in force: keepalive must not resend it, and it
            # does not feed the fail-safe watchdog (a renderer whose every frame is refused is stopped).
            self.state.requested = previous
            raise
        self._mark_frame()

    @_locked
    def keepalive(self) -> None:
        """The caller produced a frame identical to the last one (an event-driven renderer sends nothing
        then): feed the fail-safe watchdog, and if a fail-safe stop or a ramp left the firmware short of
        that frame, send what is missing (ramped)."""
        self.wire.check_open()
        self._mark_frame()
        if self.state.config is None or self.state.requested is None:
            return
        if self._needs_resync:
            self.resync()
        self._frame(self.state.requested, force_pattern=False)

    @_locked
    def all_off(self) -> None:
        """Every channel off and the pulse height at 0 (safe to call at any time after configure); the
        target current becomes 0 too, so nothing stimulates until the caller sets a current again."""
        self._off(keep_target=False)

    @_locked
    def suspend(self) -> None:
        """Every channel off and the pulse height at 0, keeping the target and the caller's last frame:
        the fail-safe's stop.  The next frame or keepalive resumes, from height 0 (ramped)."""
        self._off(keep_target=True)

    def _off(self, *, keep_target: bool) -> None:
        self.wire.check_open()
        if self.state.config is None:
            return
        if not keep_target:
            # the caller's stop holds even if the writes below fail: no later keepalive resumes the frame
            self.state.target_ua = 0
            self.state.requested = None
            self.state.suspended = False
            self.state.config = self.state.config.with_current(0)
        if self._needs_resync:
            self._recover()  # closed loop: heights 0 and every channel off once the device proves it
        self.wire.run(self.dialect.off(self.state, self.mapping, self.pacer.scan_s), self.state)
        if keep_target:
            self.state.suspended = self.state.requested is not None

    @_locked
    def measure(self) -> list[int]:
        """ADC codes (``raw >> 2``) of each hardware channel's last pulse, in hardware channel order.  A
        reply of the right length proves the parser read everything written before the request."""
        cfg = self._require_config("measure")
        n = cfg.electrode_count
        if self._needs_resync:
            self._recover()
        return self.wire.measured(n, "measure")

    @_locked
    def probe(self) -> bool:
        """Is the firmware's parser in step?  A measure request must be answered with exactly two bytes
        per channel; a parser that swallowed it as payload, a locked one, or one rebooted to electrode
        count 0 does not.  A failed probe (or a device not yet proved in step) marks the device for a
        resync and returns False."""
        self.wire.check_open()
        if self._needs_resync:
            return False
        if self.state.config is None:
            return True
        try:
            self.measure()
        except (ReplyLengthError, LimitError, DeviceTimeoutError):
            self._suspect("probe failed")
            return False
        return True

    @_locked
    def hv513_count(self) -> int:
        """Ask the board how many HV513 chips it detects (this re-initialises their outputs)."""
        self.wire.check_open()
        if self._needs_resync:
            self._recover()
        return p.parse_hv513_reply(self.wire.request(p.HV513_COUNT_REQUEST, 1, "hv513_count"))

    @_locked
    def resync(self) -> None:
        """Bring a parser of unknown state back in step, closed loop (the dialect's ``flush_parser``): the
        device proves a command boundary and an empty queue, pulse height and sense height go to 0, the
        electrode count is written and proved by the length of a measure reply, every channel goes off;
        then the whole configuration again.  No pattern follows: the caller's next frame (or keepalive)
        brings it back, ramped from 0.

        Without a configuration (a fresh session on a board in unknown state) the electrode count is
        unknown, so no pattern can be sent safely; pulse height 0 and sense height 0 already stop every
        current the firmware can deliver."""
        self.wire.check_open()
        self._suspect("resync")
        self._recover()
        self._reconfigure()

    def _reconfigure(self) -> None:
        """After a recovery: the whole configuration again (no pattern; see :meth:`resync`)."""
        cfg = self.state.config
        if cfg is not None:
            requested = self.state.requested
            self.state.config = None
            try:
                self.configure(cfg.with_current(self.state.target_ua))
            except BaseException:
                self.state.config = cfg  # still the session's configuration: the next resync tries again
                self._suspect("configure after resync failed")
                raise
            self.state.requested = requested
            self.state.suspended = requested is not None

    def _recover(self) -> None:
        """The closed-loop recovery, and when it ends in FAILED (a locked or hung parser, which no byte
        can reach, while the board may go on stimulating) the reset line at once, if there is one."""
        self.link.recover(self.dialect, self._ops(), self.state, self.hardware_reset)

    def resync_bound_s(self) -> float:
        """The longest a failing resync of this session waited, or would wait now, for its proofs before
        the reset line (the larger; configured recoveries only): see :meth:`_resync_bound_now_s`.  On
        firmware v2 that includes the 2 s command timeout its recovery waits out."""
        return max(self.state.bound_seen_s, self._resync_bound_now_s())

    def _resync_bound_now_s(self) -> float:
        """The longest a resync that fails waits for its proofs at the configuration in force (the
        dialect's recovery, behind one frame still in flight, each request until its deadline): what a
        fail-safe adds to its recovery time before it reaches for the reset line."""
        return self.dialect.resync_bound_now_s(self._ops(), self.state)

    def probe_bound_s(self) -> float:
        """The longest a probe (a measure request: the fail-safe's) waits for its reply at the configuration
        in force before it counts as unanswered (:func:`~tactdeform_hw.device.links.recovery.probe_bound_s`);
        0 before a configuration (the fail-safe does not probe then).  What may still be in flight is the
        longest frame this driver writes, each critical command twice under the loss-tolerant encoding."""
        cfg = self.state.config
        if cfg is None:
            return 0.0
        copies = 2 if self.pacer.robust else 1
        frame = [c for c in self.dialect.frame_commands(cfg.electrode_count) for _ in range(copies)]
        return probe_bound_s(self.pacer.policy, cfg, frame)

    @_locked
    def reconnect(self) -> None:
        """Reopen the link after it failed, then resynchronise before any pattern (the firmware may still
        hold a half-received command from before the failure, and the bytes written before it may still
        be in its queue: they are not assumed gone)."""
        self.wire.check_open()
        self._suspect("reconnect")
        self.guardians.reopen(self.wire)
        self.guard.mark_unknown()
        self.state.scan_us = None
        self._recover()
        # the link was lost: the board at its end is asked again which firmware it runs before any pattern
        self.verify_firmware()
        self._reconfigure()

    def verify_firmware(self) -> None:
        """At a proved command boundary, ask again which firmware answers
        (:func:`~.firmware_probe.recheck_firmware`): a board that now answers as another version, or as
        none, is stopped with bytes that stop current on both versions and refused
        (:class:`~.firmware_probe.FirmwareMismatchError`)."""
        cfg = self.config
        count = None
        if self.dialect.signature_proves_count:
            count = cfg.electrode_count if cfg is not None else 0
        recheck_firmware(self._ops(), self.dialect.firmware, count, repr(self))

    @_locked
    def hardware_reset(self) -> bool:
        """Reset the board through its reset line — the only way to reach a locked parser — and bring it
        back to the configuration: DRAINING (a reply proves the queue read, if the parser answers; and
        nothing of ours is left on the link, so no pattern lands on the freshly reset firmware whose
        electrode count is 0), RESETTING, BOOTING (``boot_s``, nothing written), then the closed-loop
        resync.  False when the transport has no reset line."""
        self.wire.check_open()
        if not self.port_link.can_reset():
            return False
        in_step = self.link.state is LinkState.IN_STEP
        self._resetting = True
        try:
            reset = self.port_link.reset
            self.link.reset_board(
                self._ops(), self.state, in_step=in_step, pulse=reset, boot_s=self.boot_s, who=self.kind
            )
            self.resync()
        finally:
            self._resetting = False
        return True

    def _recovery_prove(self, electrodes: int) -> None:
        """:meth:`_prove` as a write of the recovery itself (allowed before the proof: the drain's)."""
        with self.wire.recovery():
            self._prove(electrodes)

    @_locked
    def close(self) -> None:
        """All channels off, proved read (so the next program to open the board finds its queue empty),
        then release the port.  Safe to call twice.  A board that does not prove the all-off read is
        recovered (with the reset line if need be) and switched off again; a link that failed is reopened
        first: nothing after close could stop the board.  The guardian is let go only after that all-off
        succeeded — otherwise it switches the board off itself before it exits."""
        done = False
        try:
            close_link(self.wire, stop=self._stop_and_prove, reconnect=self.reconnect)
            done = True
        finally:
            self.guardians.let_go(switched_off=done)

    def _stop_and_prove(self) -> None:
        stop_and_prove(
            self.link,
            configured=lambda: self.state.config is not None,
            all_off=self.all_off,
            prove_stopped=lambda: self.dialect.prove_stopped(self._ops(), self.state),
            recover=self._recover,
        )

    def __enter__(self) -> Device:
        return self

    def __exit__(self, *exc_info: object) -> None:
        self.close()

    def __repr__(self) -> str:
        return f"{self.kind}({self.port_link.name}, closed={self.wire.closed})"

    def __del__(self) -> None:
        wire = getattr(self, "wire", None)
        if wire is not None and not wire.closed:
            warnings.warn(f"{self.kind} was never closed", ResourceWarning, stacklevel=1)

    # --- helpers -------------------------------------------------------------------------------------------

    def _send(self, data: bytes, *, pad: bool | None = None) -> None:
        """One command through the wire (:meth:`.wire.Wire.send`): gate, interlock, pacing, transport,
        audit."""
        self.wire.send(data, pad=pad)

    def _enter(self, state: LinkState, why: str) -> None:
        """One transition of the recovery state machine (only those in :data:`TRANSITIONS`)."""
        self.link.enter(state, why)

    def unproved_spans(self) -> list[tuple[float, float | None]]:
        """(start, end) of every span the driver spent without proof that the parser was in step (end None:
        still open), from :attr:`transitions`: what the host knew it did not know."""
        return self.link.unproved_spans()

    def _suspect(self, why: str) -> None:
        """Whatever the state, nothing is proved any more (the queue model freezes too)."""
        self.link.suspect(why)

    def _prove(self, electrodes: int) -> None:
        """In step: the dialect's request whose reply proves every byte written before it read (and
        empties the queue model).  No whole reply: the device is marked for a resync and
        :class:`~tactdeform_hw.errors.ReplyLengthError` raised."""
        self.dialect.prove(self._ops(), electrodes)

    def _frame(self, levels: Sequence[int], *, force_pattern: bool) -> None:
        """Put one application-order frame on the firmware (the dialect's order of heights and pattern,
        planned from the state in force; the wire sends it and puts each write's state in force)."""
        assert self.state.config is not None
        plan = self.dialect.frame(self.wire.plan_context(), self.state, levels, force_pattern=force_pattern)
        self.wire.run(plan, self.state)

    def _ops(self) -> LinkOps:
        """The link operations a dialect is handed (looked up now: a transport hook replaced on this
        device is the one the dialect uses; the wire keeps them while nothing they bind changes)."""
        return self.wire.link_ops(
            prove=self._prove,
            recovery_prove=self._recovery_prove,
            resetting=self._is_resetting,
        )

    def _is_resetting(self) -> bool:
        """True while the reset line's sequence runs (:meth:`hardware_reset`)."""
        return self._resetting

    def _mark_frame(self) -> None:
        self.last_frame_time = self.pacer.clock.now()

    def _require_config(self, what: str) -> StimConfig:
        self.wire.check_open()
        if self.state.config is None:
            raise ProtocolMisuseError(
                f"{what} before configure(): the firmware's electrode count is still 0, and a pattern now "
                "would lock its parser"
            )
        return self.state.config


__all__ = [
    "ALLOWED_LEVELS",
    "CLOSE_RECONNECTS",
    "PROBE_LEAD_ZEROS",
    "RECOVERY_ATTEMPTS",
    "REPLY_POLL_S",
    "STIMULATING_OPS",
    "TRANSITIONS",
    "Device",
    "LinkState",
]
