"""The device interface the renderer uses, written once; transports implement a few private methods.

Every public method checks its input, passes currents through the safety guard, refuses any sequence
that would trigger a known firmware defect, and only then builds bytes with :mod:`tactdeform_hw.protocol`
and writes them — one write per command.  ``close`` is idempotent and leaves every channel off.

Every byte leaves through :meth:`Device._send`, which passes it through the safety interlock
(:class:`~tactdeform_hw.device.safety.interlock.WireInterlock`), the pacer (:mod:`.pacing`: never faster
than the firmware reads) and the session's audit log (:mod:`.audit`).  Public methods hold one lock, so a
fail-safe thread's all-off can never interleave with a half-written frame.

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
from types import TracebackType
from typing import Concatenate, ParamSpec, TypeVar

from tactdeform_hw import protocol as p
from tactdeform_hw.clock import Clock, InstantClock, MonotonicClock
from tactdeform_hw.device.driver.audit import AuditLog
from tactdeform_hw.device.driver.config import StimConfig, robust_refusal
from tactdeform_hw.device.driver.dialect import Dialect, DriverState, LinkOps, worst_scan_s
from tactdeform_hw.device.driver.dialects import DIALECTS
from tactdeform_hw.device.driver.firmware_probe import (
    Detection,
    FirmwareMismatchError,
    check_firmware,
    check_firmware_choice,
    identify,
    recheck_firmware,
)
from tactdeform_hw.device.driver.pacing import COMMAND_BYTE_MIN, Pacer, default_pacer, padding_for
from tactdeform_hw.device.links.port import Port, PortLink, no_delay
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
from tactdeform_hw.device.safety.guardian import Guardian, pace_for, start_guardian
from tactdeform_hw.errors import (
    DeviceTimeoutError,
    LimitError,
    NotStoppedError,
    PortNotOpenError,
    ProtocolMisuseError,
    SafetyError,
    ShortReplyError,
    TactDeformError,
    TransportError,
)
from tactdeform_hw.ports import is_instant
from tactdeform_hw.protocol.constants import (
    PATTERN_BIPHASIC,
    PATTERN_MONOPHASIC,
    PATTERN_SENSE,
    USB_PACKET_SIZE,
)
from tactdeform_hw.protocol.firmware import V1_2, FirmwareSpec
from tactdeform_hw.protocol.units import DEFAULT_TRANSFER, CurrentTransfer

#: Pattern levels a host may send: off (a sense pulse, 0 µA while sense current is 0), mono, biphasic.
ALLOWED_LEVELS = frozenset({PATTERN_SENSE, PATTERN_MONOPHASIC, PATTERN_BIPHASIC})
_ACTIVE = (PATTERN_MONOPHASIC, PATTERN_BIPHASIC)
#: Commands that change what the scans deliver (a measure right after one reads the old pulses).
_STATE_OPCODES = frozenset(
    {
        p.Opcode.PATTERN,
        p.Opcode.PULSE_HEIGHT,
        p.Opcode.PULSE_WIDTH,
        p.Opcode.SENSE_HEIGHT,
        p.Opcode.SENSE_WIDTH,
        p.Opcode.ELECTRODE_NUM,
        p.Opcode.POLARITY,
        p.Opcode.FREQUENCY,
    }
)


#: Times ``close`` reopens a link that failed under its all-off before it gives up and says so.
CLOSE_RECONNECTS = 3


_D = TypeVar("_D", bound="Device")
_P = ParamSpec("_P")
_R = TypeVar("_R")


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
    clock); ``audit`` records every command sent.  ``guardian`` starts a guardian process with the device
    (default: when the port declares itself ``guardable``); a port that cannot be guarded with
    ``guardian=True`` is refused.
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
    ) -> None:
        check_firmware_choice(firmware)
        self._init_state(mapping, transfer, guard, pacer, audit)
        self.port_link = PortLink(port, lambda s: self.pacer.clock.sleep(s))
        self._guardian: Guardian | None = None
        if not port.is_open:
            try:
                self.port_link.open()
            except BaseException:
                self._closed = True
                raise
        no_delay(port)
        if pacer is None:  # what a port needs is known only once it is open (a URL builds its device then)
            self.pacer = default_pacer(port)
            if offline_clock is not None and is_instant(port):
                # a port that answers at once (the in-process emulator) runs the session on the caller's clock
                self.pacer = Pacer(clock=offline_clock, policy=self.pacer.policy)
        self.identification = probe if probe is not None else self._identify(settle_s)
        self._open(firmware, guardian)

    def _init_state(
        self,
        mapping: ChannelMapping | None,
        transfer: CurrentTransfer,
        guard: SafetyGuard | None,
        pacer: Pacer | None,
        audit: AuditLog | None,
    ) -> None:
        self._lock = threading.RLock()
        self._op: str | None = None
        #: Called under the device lock before each operation in :data:`STIMULATING_OPS`: a fail-safe's
        #: probe that is due runs there, so an owner that calls without a pause cannot starve it.
        self.before_stimulating: Callable[[], None] | None = None
        if guard is not None:
            # before anything is written: the calibrated channels must be the wired ones
            guard.check_wiring(mapping)
        self.mapping = mapping
        self.transfer = transfer
        self.guard = guard if guard is not None else SafetyGuard()
        self.pacer = pacer if pacer is not None else Pacer(clock=MonotonicClock())
        self._audit: AuditLog | None = None
        self.audit = audit
        #: What the host believes the firmware holds, and what the caller asked for.
        self.state = DriverState()
        #: The recovery state machine: what is proved about the firmware's parser (see :class:`LinkState`).
        self.link = LinkRecovery(lambda: self.pacer)
        # (time s, from, to, why) of the latest transitions, and when a reply last proved the parser
        self.transitions = self.link.transitions
        self.proofs = self.link.proofs
        self._recovery_write = False
        self._resetting = False
        self.last_frame_time: float | None = None
        self.last_state_write: float | None = None  # the last write that changed what the scans deliver
        self._writing = False  # True while bytes are being handed to the transport
        self._closed = False
        #: How this board's firmware expresses each operation (v1.2 until the board proves another).
        self.dialect: Dialect = DIALECTS[V1_2]

    def _open(self, firmware: str, guardian: bool | None) -> None:
        """After the identification: its bytes counted and logged, the version checked, the guardian, the
        dialect, the proof at open, and the stop session's watch."""
        probe = self.identification
        # the identification wrote before anything else: its bytes are this device's own
        self.pacer.stats.bytes_written += probe.bytes_sent
        if self.audit is not None:
            self.audit.event(
                "firmware_probe",
                firmware=probe.name,
                attempts=probe.attempts,
                bytes=probe.bytes_sent,
                reply=probe.reply.hex(),
                settle_s=probe.settle_s,
            )
        if firmware != "auto" and probe.name != firmware:
            self._refuse()
            check_firmware(firmware, probe, self.port_link.name)
        self._want_guardian = bool(getattr(self.port, "guardable", False)) if guardian is None else guardian
        if self._want_guardian:
            try:
                self._start_guardian()
            except BaseException:
                self._closed = True
                self.port_link.close()
                raise
        self.speak(probe.firmware)
        try:
            self._open_proof()
        except FirmwareMismatchError:
            self._refuse()  # the board answered as another firmware: stopped, refused, released
            raise  # a board in an unknown state: nothing is sent before it proves its parser
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
        stop = self.dialect.guardian_open_stop()
        if stop is not None and self._guardian is not None:
            self._guardian.set_stop(stop)

    def _identify(self, settle_s: float | None) -> Detection:
        """Prove which firmware runs the board (:func:`~.firmware_probe.identify`); refuse it otherwise."""
        self.link.unproved_since = self.pacer.clock.now()
        try:
            return identify(
                self.port_link, self.pacer.clock, self.audit, settle_s=settle_s, boot_s=self.boot_s
            )
        except BaseException:
            self._refuse()
            raise

    def _refuse(self) -> None:
        """Give up a board before driving it: the guardian let go, the port closed, nothing more written."""
        self._closed = True
        g, self._guardian = self._guardian, None
        if g is not None:
            g.release()
        self.port_link.close()

    @property
    def port(self) -> Port:
        """The port the device writes to (a caller may put a recording proxy of it in its place)."""
        return self.port_link.port

    @port.setter
    def port(self, port: Port) -> None:
        self.port_link.port = port

    # --- the guardian ---------------------------------------------------------------------------------------

    @property
    def guardian(self) -> Guardian | None:
        """The guardian process watching this device's owner (None on a port that cannot be guarded)."""
        return self._guardian

    def _start_guardian(self) -> None:
        self._guardian = start_guardian(self.port, repr(self))
        self._tell_guardian()

    def _tell_guardian(self) -> None:
        g, cfg = self._guardian, self.config
        if g is None or cfg is None:
            return
        drain_s, zeros_s = pace_for(
            cfg.rate_hz, cfg.electrode_count, cfg.pulse_width_us, cfg.discharge_us, cfg.sense_width_us
        )
        g.configure(self.dialect.guardian_stop(cfg.electrode_count), drain_s, zeros_s)

    def _reopen_transport(self) -> None:
        # the guardian shares the old descriptor (and its lock): let it try to switch off through it, then
        # start a new one on the new descriptor
        g, self._guardian = self._guardian, None
        if g is not None:
            g.abandon()
        self.port_link.reopen()
        if self._want_guardian:
            self._start_guardian()

    # --- state ---------------------------------------------------------------------------------------------

    @property
    def config(self) -> StimConfig | None:
        """The configuration last sent (None until ``configure``)."""
        return self.state.config

    @property
    def current_ua(self) -> int:
        """The pulse height in force (µA): what an active channel receives now."""
        return self.state.current_ua

    @property
    def target_ua(self) -> int:
        """The current the caller asked for; frames carry it lowered to their limits."""
        return self.state.target_ua

    @property
    def audit(self) -> AuditLog | None:
        return self._audit

    @audit.setter
    def audit(self, log: AuditLog | None) -> None:
        """Enable (or with None, disable) the audit log; the guard's refusals and clips go there too."""
        self._audit = log
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
    def last_pattern(self) -> bytes | None:
        """The pattern the firmware should hold, in hardware order (None: unknown, e.g. after a resync)."""
        return self.state.last_pattern

    @property
    def busy(self) -> bool:
        """True while a public operation runs: another thread must not start one between its commands."""
        return self._op is not None

    @property
    def writing(self) -> bool:
        """True while bytes are being handed to the transport: a stop now may leave half a command."""
        return self._writing

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
        if self.state.config is None or self._closed:
            return
        self.dialect.refresh(self._ops(), self.state, sense=sense)

    @property
    def suspended(self) -> bool:
        """True after a fail-safe stop; the next frame (or keepalive) resumes, ramped."""
        return self.state.suspended

    @property
    def stimulating(self) -> bool:
        """Whether the firmware, as far as the host knows, is delivering current to any channel."""
        if self.state.config is None:
            return False
        if self.state.config.sense_current_ua:
            return True
        return (
            bool(self.state.current_ua)
            and self.state.last_pattern is not None
            and any(v in _ACTIVE for v in self.state.last_pattern)
        )

    @property
    def closed(self) -> bool:
        return self._closed

    @property
    def firmware(self) -> str:
        """The firmware version this device speaks to its board (``"v1.2"`` or ``"v2"``)."""
        return self.dialect.firmware.name

    @property
    def frames_sent(self) -> int:
        """Patterns written (a rewrite of the same pattern by ``keepalive`` is not one)."""
        return self.state.frames_sent

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
        self._check_open()
        try:
            config = self.dialect.validated(config, self.transfer)
        except LimitError as exc:
            self.guard.note_refusal(exc)
            raise
        config = self.guard.check_config(
            config,
            stimulating=self.stimulating,
            polarity_in_force=self.state.config.polarity if self.state.config is not None else None,
            transfer=self.transfer,
        )
        if self.mapping is not None and self.mapping.hw_channels != config.electrode_count:
            raise LimitError(
                "electrode_count",
                config.electrode_count,
                f"the channel mapping's hardware channel count {self.mapping.hw_channels}",
            )
        refusal = robust_refusal(config, self.transfer) if self.pacer.robust else None
        if refusal is not None:
            self.guard.note_refusal(refusal)
            raise refusal
        self.dialect.check_idle_scan(self.guard, config)
        # the caller's frame is superseded now, whether or not the writes below get through: no keepalive
        # after a failed configure brings the old frame back
        self.state.requested = None
        self.state.suspended = False
        self.dialect.configure(self._ops(), self.state, config)
        self._tell_guardian()

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
        levels = None if self.state.suspended else self._application_levels()
        self.dialect.set_current(self._ops(), self.state, levels)

    @_locked
    def send_pattern(self, levels: Sequence[int]) -> None:
        """Send a pattern in application order: 0 off, 1 monophasic, 2 biphasic.

        The frame's pulse height is the target lowered to the lowest limit of the electrodes it activates
        (see :mod:`.safety`); a needed height change is written before the pattern when it lowers the
        height and after it when it raises it."""
        self._require_config("send_pattern")
        try:
            self._check_levels(levels)
        except (LimitError, ProtocolMisuseError) as exc:
            self.guard.note_refusal(exc)
            raise
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

    def _check_levels(self, levels: Sequence[int]) -> None:
        expected = self.electrodes
        try:
            count = len(levels)
        except TypeError as exc:
            raise LimitError("pattern", levels, "a sequence of levels") from exc
        if count != expected:
            raise ProtocolMisuseError(
                f"pattern has {count} level(s) but the device is configured for {expected} electrode(s); "
                "a short pattern would swallow the next command and a long one would leak into it"
            )
        for i, v in enumerate(levels):
            if isinstance(v, bool) or not isinstance(v, int) or v not in ALLOWED_LEVELS:
                raise LimitError(f"pattern[{i}]", v, "0 (off), 1 (monophasic) or 2 (biphasic)")
        self.dialect.check_levels(levels)

    @_locked
    def keepalive(self) -> None:
        """The caller produced a frame identical to the last one (an event-driven renderer sends nothing
        then): feed the fail-safe watchdog, and if a fail-safe stop or a ramp left the firmware short of
        that frame, send what is missing (ramped)."""
        self._check_open()
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
        self._check_open()
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
        self.dialect.off(self._ops(), self.state)
        if keep_target:
            self.state.suspended = self.state.requested is not None

    def _open_proof(self) -> None:
        """Right after opening, prove the parser in step (best effort: a board that does not answer yet is
        proved by the first command, which raises if it still cannot be)."""
        with self._lock:
            try:
                self._recover()  # a locked or hung board (perhaps still stimulating) gets the reset line
            except FirmwareMismatchError:
                raise  # another firmware than the one this device speaks: refused, never driven
            except TactDeformError:
                self._suspect("no proof at open")

    @_locked
    def measure(self) -> list[int]:
        """ADC codes (``raw >> 2``) of each hardware channel's last pulse, in hardware channel order.  A
        reply of the right length proves the parser read everything written before the request."""
        cfg = self._require_config("measure")
        n = cfg.electrode_count
        if self._needs_resync:
            self._recover()
        return self._measured(n, "measure")

    def _measured(self, n: int, what: str) -> list[int]:
        """0xFF and its whole reply, which proves every byte before it read; a short one marks the device
        for a resync and raises (``what`` names the request in the error)."""
        self.port_link.discard_input()
        mark = self._send_marked(p.MEASURE_REQUEST)
        data = self._await_reply(2 * n)
        if len(data) != 2 * n:
            self._suspect("short reply to 0xFF")
            raise ShortReplyError(what, 2 * n, data)
        self._proved(mark)
        return p.parse_measure_reply(data, n)

    @_locked
    def probe(self) -> bool:
        """Is the firmware's parser in step?  A measure request must be answered with exactly two bytes
        per channel; a parser that swallowed it as payload, a locked one, or one rebooted to electrode
        count 0 does not.  A failed probe (or a device not yet proved in step) marks the device for a
        resync and returns False."""
        self._check_open()
        if self._needs_resync:
            return False
        if self.state.config is None:
            return True
        try:
            self.measure()
        except (ShortReplyError, LimitError, DeviceTimeoutError):
            self._suspect("probe failed")
            return False
        return True

    @_locked
    def hv513_count(self) -> int:
        """Ask the board how many HV513 chips it detects (this re-initialises their outputs)."""
        self._check_open()
        if self._needs_resync:
            self._recover()
        self.port_link.discard_input()
        mark = self._send_marked(p.HV513_COUNT_REQUEST)
        data = self._await_reply(1)
        if len(data) != 1:
            self._suspect("short reply to 0xF5")
            raise ShortReplyError("hv513_count", 1, data)
        self._proved(mark)
        return p.parse_hv513_reply(data)

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
        self._check_open()
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

    def _frame_commands(self, n: int) -> list[bytes]:
        """The longest frame this driver writes at electrode count ``n``, command by command (under the
        loss-tolerant encoding each critical command goes twice): what may still be in flight."""
        copies = 2 if self.pacer.robust else 1
        return [c for c in self.dialect.frame_commands(n) for _ in range(copies)]

    def probe_bound_s(self) -> float:
        """The longest a probe (a measure request: the fail-safe's) waits for its reply at the configuration
        in force before it counts as unanswered (:func:`~tactdeform_hw.device.links.recovery.probe_bound_s`);
        0 before a configuration (the fail-safe does not probe then)."""
        cfg = self.state.config
        if cfg is None:
            return 0.0
        return probe_bound_s(self.pacer.policy, cfg, self._frame_commands(cfg.electrode_count))

    @_locked
    def reconnect(self) -> None:
        """Reopen the link after it failed, then resynchronise before any pattern (the firmware may still
        hold a half-received command from before the failure, and the bytes written before it may still
        be in its queue: they are not assumed gone)."""
        self._check_open()
        self._suspect("reconnect")
        self._reopen_transport()
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
        self._check_open()
        if not self.port_link.can_reset():
            return False
        in_step = self.link.state is LinkState.IN_STEP
        self._resetting = True
        try:
            self._hardware_reset(in_step)
        finally:
            self._resetting = False
        return True

    def _hardware_reset(self, in_step: bool) -> None:
        self.link.reset_board(
            self._ops(),
            self.state,
            in_step=in_step,
            pulse=self.port_link.reset,
            boot_s=self.boot_s,
            who=self.kind,
        )
        self.resync()

    def _recovery_prove(self, electrodes: int) -> None:
        """:meth:`_prove` as a write of the recovery itself (allowed before the proof: the drain's)."""
        self._recovery_write = True
        try:
            self._prove(electrodes)
        finally:
            self._recovery_write = False

    @_locked
    def close(self) -> None:
        """All channels off, proved read (so the next program to open the board finds its queue empty),
        then release the port.  Safe to call twice.  A board that does not prove the all-off read is
        recovered (with the reset line if need be) and switched off again; a link that failed is reopened
        first: nothing after close could stop the board.  The guardian is let go only after that all-off
        succeeded — otherwise it switches the board off itself before it exits."""
        done = False
        try:
            self._close_link()
            done = True
        finally:
            g, self._guardian = self._guardian, None
            if g is not None:
                if done:
                    g.release()
                else:
                    g.abandon()

    def _close_link(self) -> None:
        if self._closed:
            return
        try:
            try:
                self._stop_and_prove()
            except TransportError as failed:
                for attempt in range(CLOSE_RECONNECTS):
                    try:
                        self.reconnect()
                        self._stop_and_prove()
                        break
                    except TransportError:
                        if attempt == CLOSE_RECONNECTS - 1:
                            raise failed from None
                    except TactDeformError:
                        raise failed from None
        finally:
            self._closed = True
            self.port_link.close()

    def _stop_and_prove(self) -> None:
        """All off, and proof that nothing stimulates.  A proof that fails (a board that rebooted or hung
        under the all-off, or one whose answer shows current still flowing) is followed by a recovery —
        with the reset line if need be — and the all-off and its proof again."""
        for attempt in range(1, RECOVERY_ATTEMPTS + 2):
            if self.state.config is not None:
                self.all_off()
            if self.link.state is not LinkState.IN_STEP:
                return
            try:
                # v1.2: the readings of the all-off; v2: count 0, proved by the sync reply's value
                self.dialect.prove_stopped(self._ops(), self.state)
                return
            except (ShortReplyError, NotStoppedError):
                if attempt > RECOVERY_ATTEMPTS:
                    raise
                self._recover()

    def __enter__(self) -> Device:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()

    def __repr__(self) -> str:
        return f"{self.kind}({self.port_link.name}, closed={self._closed})"

    def __del__(self) -> None:
        if not getattr(self, "_closed", True):
            warnings.warn(f"{self.kind} was never closed", ResourceWarning, stacklevel=1)

    # --- helpers -------------------------------------------------------------------------------------------

    def _send(self, data: bytes, *, pad: bool | None = None) -> None:
        """The one exit for bytes: gate, interlock, pacing, transport, audit.  Outside the recovery's own
        writes nothing leaves unless the parser is proved in step (:class:`LinkState`).  A failed write
        leaves the firmware's state unknown, so the interlock forgets it and the next frame resyncs first."""
        self._send_paced(bytes(data), None, pad)

    def _send_commands(self, commands: Sequence[bytes], *, pad: bool | None = None) -> None:
        """Whole commands in one write (:meth:`Pacer.write_commands`): they reach the device's queue
        together, so v2's parser applies them back to back.  Gated, checked and audited as :meth:`_send`
        does a single command (the interlock reads the commands in order, every state between them
        included)."""
        cmds = [bytes(c) for c in commands if c]
        self._send_paced(b"".join(cmds), cmds, pad)

    def _send_paced(self, data: bytes, commands: list[bytes] | None, pad: bool | None) -> None:
        self._check_open()
        if not data:
            return
        if self.link.state is not LinkState.IN_STEP and not self._recovery_write:
            raise ProtocolMisuseError(
                f"0x{data[0]:02X} while the firmware's parser is not proved in step "
                f"({self.link.state.value}): resync first"
            )
        shadow = self.guard.interlock.check_wire(data, mapping=self.mapping, transfer=self.transfer)
        audit = self._audit
        op = self._op or ""

        def write(chunk: bytes) -> None:
            self._writing = True
            try:
                self.port_link.write(chunk)
            except BaseException:
                if audit is not None:
                    audit.tx(chunk, t=self.pacer.clock.now(), ok=False, op=op, logical=data[:1] + chunk[1:])
                raise
            finally:
                self._writing = False
            if audit is None:
                return
            now = self.pacer.clock.now()
            if commands is not None:
                # one write of several commands: one record per command (its padding with it), so a
                # reader of the log sees every command as the firmware reads it
                padded = self.pacer.policy.robust_encoding if pad is None else pad
                pos = 0
                for c in commands:
                    size = len(c) + (len(padding_for(c, self.pacer.policy.firmware)) if padded else 0)
                    audit.tx(chunk[pos : pos + size], t=now, op=op, logical=c)
                    pos += size
                return
            logical = data if chunk[:1] == data[:1] and chunk[0] >= COMMAND_BYTE_MIN else chunk
            audit.tx(chunk, t=now, op=op, logical=logical)

        try:
            if commands is None:
                self.pacer.write(write, data, pad=pad)
            else:
                self.pacer.write_commands(write, commands, pad=pad)
        except BaseException:
            self.guard.mark_unknown()
            self._suspect("write failed")
            raise
        changed = self.guard.commit(shadow)
        if changed and (data[0] in _STATE_OPCODES or data[0] < COMMAND_BYTE_MIN):
            self.last_state_write = self.pacer.clock.now()  # a rewrite of the same state does not count

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

    def _recovery_send(self, data: bytes, *, pad: bool | None = True) -> int:
        """A write of the recovery itself (by default with the loss-tolerant padding); the written offset
        just past it, for :meth:`Pacer.proven`."""
        self._recovery_write = True
        try:
            self._send(data, pad=pad)
        finally:
            self._recovery_write = False
        return self.pacer.offset

    def _proved(self, mark: int) -> None:
        """A reply proved every byte before ``mark`` read, the parser at a command boundary."""
        self.pacer.proven(mark)
        self.guard.note_in_step()  # the interlock stops assuming a full queue could cut this write's packets
        self.link.proofs.append(self.pacer.clock.now())

    def _prove(self, electrodes: int) -> None:
        """In step: the dialect's request whose reply proves every byte written before it read (and
        empties the queue model).  No whole reply: the device is marked for a resync and
        :class:`ShortReplyError` raised."""
        self.dialect.prove(self._ops(), electrodes)

    def _pace_for(self, timings: Sequence[tuple[float, float]]) -> None:
        """Pace for the slowest of several (period µs, scan µs) that may be in force."""

        def cost(t: tuple[float, float]) -> tuple[float, float]:
            self.pacer.set_timing(t[0] / 1e6, t[1] / 1e6)
            return (self.pacer.payload_interval_s(), self.pacer.skip_s(USB_PACKET_SIZE))

        period_us, scan_us = max(timings, key=cost)
        self.pacer.set_timing(period_us / 1e6, scan_us / 1e6)

    def _send_marked(self, data: bytes) -> int:
        self._send(data)
        return self.pacer.offset

    def _reply_slack_s(self, size: int) -> float:
        """How long after the queue model's worst drain time a reply of ``size`` bytes may still come:
        its transfer (a USB frame), one alarm period of margin, and more when the period is unknown."""
        period = self.pacer.period_s
        extra = period if period is not None else self.unknown_reply_s
        return 0.003 + size * self.pacer.policy.byte_s + extra

    def _await_reply(self, size: int) -> bytes:
        """Read up to ``size`` bytes until the reply's deadline (the worst case, not the typical)."""
        if size <= 0:
            return b""
        clock = self.pacer.clock
        deadline = self.pacer.drained_by() + self._reply_slack_s(size)
        got = bytearray()
        while True:
            waiting = self.port_link.waiting()
            had = len(got)
            if waiting is None or waiting >= size - len(got):
                got += self.port_link.read(size - len(got))
            elif waiting:
                # what has arrived (a socket says only "readable": at least one byte); the rest follows
                got += self.port_link.read(waiting)
            if len(got) >= size or isinstance(clock, InstantClock) or clock.now() >= deadline:
                return bytes(got)
            if len(got) == had:
                clock.sleep(min(REPLY_POLL_S, max(0.0, deadline - clock.now())))

    def _frame(self, levels: Sequence[int], *, force_pattern: bool) -> None:
        """Put one application-order frame on the firmware (the dialect's order of heights and pattern)."""
        assert self.state.config is not None
        self.dialect.frame(self._ops(), self.state, levels, force_pattern=force_pattern)

    def _worst_scan_s(self, cfg: StimConfig) -> float:
        """The longest scan a frame the guard allows can have (see :func:`.dialect.worst_scan_s`)."""
        return worst_scan_s(cfg)

    def _ops(self) -> LinkOps:
        """The link operations a dialect is handed (bound now: a transport hook replaced on this device
        is the one the dialect uses)."""
        return LinkOps(
            pacer=lambda: self.pacer,
            guard=self.guard,
            mapping=self.mapping,
            transfer=self.transfer,
            unknown_reply_s=self.unknown_reply_s,
            send=self._send,
            send_critical=self._send_critical,
            send_critical_commands=self._send_critical_commands,
            recovery_send=self._recovery_send,
            discard_input=self.port_link.discard_input,
            await_reply=self._await_reply,
            proved=self._proved,
            suspect=self._suspect,
            enter=self._enter,
            link_state=lambda: self.link.state,
            prove=self._prove,
            recovery_prove=self._recovery_prove,
            recover=self._recover,
            measured=self._measured,
            pace_for=self._pace_for,
            can_reset=self.port_link.can_reset,
            resetting=lambda: self._resetting,
            needs_resync=lambda: self._needs_resync,
        )

    def _send_critical(self, data: bytes) -> None:
        """Heights and patterns: under robust encoding written twice, so a byte lost, corrupted or
        duplicated in one copy is put right by the other a millisecond later (the copies are identical,
        so a firmware in step sees no change)."""
        self._send(data)
        if self.pacer.robust:
            self._send(data)

    def _send_critical_commands(self, commands: Sequence[bytes]) -> None:
        """:meth:`_send_commands` with :meth:`_send_critical`'s second copy under robust encoding."""
        self._send_commands(commands)
        if self.pacer.robust:
            self._send_commands(commands)

    def _mark_frame(self) -> None:
        self.last_frame_time = self.pacer.clock.now()

    def _check_open(self) -> None:
        if self._closed:
            raise PortNotOpenError(f"{self.kind} is closed")

    def _require_config(self, what: str) -> StimConfig:
        self._check_open()
        if self.state.config is None:
            raise ProtocolMisuseError(
                f"{what} before configure(): the firmware's electrode count is still 0, and a pattern now "
                "would lock its parser"
            )
        return self.state.config

    def _application_levels(self) -> list[int] | None:
        if self.state.last_pattern is None:
            return None
        if self.mapping is not None:
            return self.mapping.to_application(self.state.last_pattern)
        return list(self.state.last_pattern)


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
