"""The device interface the renderer uses, written once; transports implement a few private methods.

Every public method checks its input, passes currents through the safety guard, refuses any sequence
that would trigger a known firmware defect, and only then builds bytes with :mod:`tactdeform_hw.protocol`
and writes them — one write per command.  ``close`` is idempotent and leaves every channel off.

Every byte leaves through :meth:`Device._send`, which passes it through the safety interlock
(:meth:`SafetyGuard.check_wire`), the pacer (:mod:`.pacing`: never faster than the firmware reads) and the
session's audit log (:mod:`.audit`).  Public methods hold one lock, so a fail-safe thread's all-off can
never interleave with a half-written frame.

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
from abc import ABC, abstractmethod
from collections.abc import Callable, Sequence
from types import TracebackType
from typing import Concatenate, ParamSpec, TypeVar

from .. import protocol as p
from ..clock import MonotonicClock
from ..errors import (
    LimitError,
    PortNotOpenError,
    ProtocolMisuseError,
    SafetyError,
    ShortReplyError,
    TransportError,
)
from ..protocol.constants import (
    CURRENT_STEP_UA,
    PATTERN_BIPHASIC,
    PATTERN_MONOPHASIC,
    PATTERN_SENSE,
    RX_QUEUE_SIZE,
)
from ..protocol.units import DEFAULT_TRANSFER, CurrentTransfer
from .audit import AuditLog
from .config import POLARITY_CODE, StimConfig, sense_code
from .mapping import ChannelMapping
from .pacing import (
    COMMAND_BYTE_MIN,
    SCAN_GAP_MIN_US,
    Pacer,
    command_like_payload,
    estimate_scan_us,
    firmware_period_us,
)
from .safety import SafetyGuard

#: Pattern levels a host may send: off (a sense pulse, 0 µA while sense current is 0), mono, biphasic.
ALLOWED_LEVELS = frozenset({PATTERN_SENSE, PATTERN_MONOPHASIC, PATTERN_BIPHASIC})
_ACTIVE = (PATTERN_MONOPHASIC, PATTERN_BIPHASIC)
#: Commands that change what the scans deliver (a measure right after one reads the old pulses).
#: Requests sent after a resync's zeros before the board counts as not answering.
_PROOF_ATTEMPTS = 2
_STATE_OPCODES = frozenset(
    {p.Opcode.PATTERN, p.Opcode.PULSE_HEIGHT, p.Opcode.PULSE_WIDTH, p.Opcode.SENSE_HEIGHT, p.Opcode.SENSE_WIDTH,
     p.Opcode.ELECTRODE_NUM, p.Opcode.POLARITY, p.Opcode.FREQUENCY}
)

_D = TypeVar("_D", bound="Device")
_P = ParamSpec("_P")
_R = TypeVar("_R")


def _locked(fn: Callable[Concatenate[_D, _P], _R]) -> Callable[Concatenate[_D, _P], _R]:
    """Run a public method under the device lock, and name it as the origin of the bytes it sends."""

    @functools.wraps(fn)
    def wrapper(self: _D, /, *args: _P.args, **kwargs: _P.kwargs) -> _R:
        with self._lock:
            outer = self._op is None
            if outer:
                self._op = fn.__name__
            try:
                return fn(self, *args, **kwargs)
            finally:
                if outer:
                    self._op = None

    return wrapper


class Device(ABC):
    """An eTactileKit-compatible stimulator.

    ``mapping`` translates application electrode order to hardware channels (identity by default);
    ``transfer`` converts µA to DAC codes; ``guard`` enforces current limits; ``pacer`` spaces writes
    (wall-clock pacing by default); ``audit`` records every command sent.
    """

    def __init__(
        self,
        *,
        mapping: ChannelMapping | None = None,
        transfer: CurrentTransfer = DEFAULT_TRANSFER,
        guard: SafetyGuard | None = None,
        pacer: Pacer | None = None,
        audit: AuditLog | None = None,
    ) -> None:
        self._lock = threading.RLock()
        self._op: str | None = None
        self.mapping = mapping
        self.transfer = transfer
        self.guard = guard if guard is not None else SafetyGuard()
        self.pacer = pacer if pacer is not None else Pacer(clock=MonotonicClock())
        self._audit: AuditLog | None = None
        self.audit = audit
        self._config: StimConfig | None = None
        self._current_ua = 0  # pulse height in force on the firmware
        self._target_ua = 0  # what the caller asked for
        self._last_pattern: bytes | None = None  # hardware order, as on the firmware
        self._requested: list[int] | None = None  # the caller's last frame, application order
        self._suspended = False
        self._needs_resync = False
        self.frames_sent = 0
        self.last_frame_time: float | None = None
        self.last_state_write: float | None = None  # the last write that changed what the scans deliver
        self._writing = False  # True while bytes are being handed to the transport
        self._scan_us: float | None = None  # estimated scan of the pattern in force (None: unknown)
        self._closed = False

    # --- transport (implemented by subclasses) --------------------------------------------------------------

    @abstractmethod
    def _write(self, data: bytes) -> None:
        """Write one whole command."""

    @abstractmethod
    def _read(self, size: int) -> bytes:
        """Read up to ``size`` bytes, honouring the transport's timeout."""

    @abstractmethod
    def _close_transport(self) -> None:
        """Release the port."""

    def _discard_input(self) -> None:  # noqa: B027 - optional hook, a no-op by default
        """Drop stale bytes waiting from the device (optional for transports)."""

    def _reopen_transport(self) -> None:
        """Close and reopen the link (after the device vanished); transports that can, override this."""
        raise TransportError(f"{type(self).__name__} cannot reconnect")

    def _reset_transport(self) -> bool:
        """Pulse the board's reset line; False when the transport has none."""
        return False

    # --- state ---------------------------------------------------------------------------------------------

    @property
    def config(self) -> StimConfig | None:
        """The configuration last sent (None until ``configure``)."""
        return self._config

    @property
    def current_ua(self) -> int:
        """The pulse height in force (µA): what an active channel receives now."""
        return self._current_ua

    @property
    def target_ua(self) -> int:
        """The current the caller asked for; frames carry it lowered to their limits."""
        return self._target_ua

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
        """True after a failed write: the next frame is preceded by a resync."""
        return self._needs_resync

    @property
    def suspended(self) -> bool:
        """True after a fail-safe stop; the next frame (or keepalive) resumes, ramped."""
        return self._suspended

    @property
    def stimulating(self) -> bool:
        """Whether the firmware, as far as the host knows, is delivering current to any channel."""
        if self._config is None:
            return False
        if self._config.sense_current_ua:
            return True
        return bool(self._current_ua) and self._last_pattern is not None and any(
            v in _ACTIVE for v in self._last_pattern
        )

    @property
    def closed(self) -> bool:
        return self._closed

    @property
    def electrodes(self) -> int:
        """Application electrodes a pattern must have (0 until configured)."""
        if self._config is None:
            return 0
        return self.mapping.electrodes if self.mapping is not None else self._config.electrode_count

    # --- commands ------------------------------------------------------------------------------------------

    @_locked
    def configure(self, config: StimConfig) -> None:
        """Send a whole configuration in an order that never stimulates with a half-set state.

        The height goes to 0 and every channel off first (so no pulse uses a mixture of old and new
        settings), the electrode count is followed at once by an all-off pattern of the new length (so no
        stale channel above the old count comes back), polarity changes while all is off, and the
        participant's current comes last.
        """
        self._check_open()
        try:
            config = config.validated(self.transfer)
        except LimitError as exc:
            self.guard.note_refusal(exc)
            raise
        config = self.guard.check_config(
            config,
            stimulating=self.stimulating,
            polarity_in_force=self._config.polarity if self._config is not None else None,
            transfer=self.transfer,
        )
        if self.mapping is not None and self.mapping.hw_channels != config.electrode_count:
            raise LimitError(
                "electrode_count",
                config.electrode_count,
                f"the channel mapping's hardware channel count {self.mapping.hw_channels}",
            )
        if self.pacer.robust:
            self._check_robust(config)
        n = config.electrode_count
        old = self._config
        new_period = firmware_period_us(config.rate_hz)
        idle_scan = self._scan_of(config, bytes(n))
        if old is None or self._scan_us is None:
            self.pacer.set_timing(max(new_period, 10_000.0) / 1e6, None if old is None else self._worst_scan_s(old))
        else:
            self.pacer.set_timing(firmware_period_us(old.rate_hz) / 1e6, max(self._scan_us, idle_scan) / 1e6)
        if self._needs_resync:
            self._flush_parser()
        self._send(p.encode_pulse_height(0))
        self._current_ua = 0
        if self._config is not None:
            self._send(p.encode_pattern(bytes(self._config.electrode_count)))
        self._send(p.encode_sense_height(0))
        self._send(p.encode_electrode_num(n))
        self._send(p.encode_pattern(bytes(n)))
        self._last_pattern = bytes(n)
        self._send(p.encode_polarity(POLARITY_CODE[config.polarity]))
        self._send(p.encode_pulse_width(config.pulse_width_us))
        self._send(p.encode_sense_width(config.sense_width_us))
        self._send(p.encode_discharge(config.discharge_us))
        self._send(p.encode_frequency(config.rate_hz))
        self._send(p.encode_sense_height(sense_code(config.sense_current_ua, self.transfer)))
        height = self._encodable(
            self.guard.frame_height(None, config.current_ua, 0, config.pulse_width_us, raise_when_idle=True)
        )
        self._send(p.encode_pulse_height(self.transfer.to_code(height)))
        self._config = config
        self._current_ua = height
        self._target_ua = config.current_ua
        self._requested = None
        self._suspended = False
        self._scan_us = idle_scan
        self.pacer.set_timing(new_period / 1e6, idle_scan / 1e6)

    @_locked
    def set_current(self, current_ua: int) -> None:
        """Change the target current; the pulse height follows at once, lowered to the limits of the
        pattern in force (and to the ramp step)."""
        cfg = self._require_config("set_current")
        target = self.guard.request(self.guard.validate_current(current_ua, self.transfer))
        self._target_ua = target
        self._config = cfg.with_current(target)
        self._mark_frame()
        if self._needs_resync:
            self.resync()
            return
        levels = None if self._suspended else self._application_levels()
        height = self._encodable(
            self.guard.frame_height(levels, target, self._current_ua, cfg.pulse_width_us, raise_when_idle=True)
        )
        if height != self._current_ua:
            self._send_critical(p.encode_pulse_height(self.transfer.to_code(height)))
            self._current_ua = height

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
        previous = self._requested
        self._requested = list(levels)
        try:
            if self._needs_resync:
                self.resync()
            self._frame(self._requested, force_pattern=True)
        except SafetyError:
            # A refused frame is not the caller's frame in force: keepalive must not resend it, and it
            # does not feed the fail-safe watchdog (a renderer whose every frame is refused is stopped).
            self._requested = previous
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

    @_locked
    def keepalive(self) -> None:
        """The caller produced a frame identical to the last one (an event-driven renderer sends nothing
        then): feed the fail-safe watchdog, and if a fail-safe stop or a ramp left the firmware short of
        that frame, send what is missing (ramped)."""
        self._check_open()
        self._mark_frame()
        if self._config is None or self._requested is None:
            return
        if self._needs_resync:
            self.resync()
        self._frame(self._requested, force_pattern=False)

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
        if self._config is None:
            return
        n = self._config.electrode_count
        if self._needs_resync:
            self._flush_parser()
        self._send_critical(p.encode_pattern(bytes(n)))
        self._send_critical(p.encode_pulse_height(0))
        self._last_pattern = bytes(n)
        self._current_ua = 0
        self._scan_us = self._scan_of(self._config, bytes(n))
        self.pacer.set_timing(firmware_period_us(self._config.rate_hz) / 1e6, self._scan_us / 1e6)
        if keep_target:
            self._suspended = self._requested is not None
        else:
            self._target_ua = 0
            self._requested = None
            self._suspended = False
            self._config = self._config.with_current(0)

    @_locked
    def measure(self) -> list[int]:
        """ADC codes (``raw >> 2``) of each hardware channel's last pulse, in hardware channel order."""
        cfg = self._require_config("measure")
        n = cfg.electrode_count
        self._discard_input()
        self._send(p.MEASURE_REQUEST)
        data = self._read_exact(2 * n, "measure")
        return p.parse_measure_reply(data, n)

    @_locked
    def probe(self) -> bool:
        """Is the firmware's parser in step?  A measure request must be answered with exactly two bytes
        per channel; a parser that swallowed it as payload, a locked one, or one rebooted to electrode
        count 0 does not.  A failed probe marks the device for a resync (and returns False)."""
        if self._config is None:
            return True
        try:
            self.measure()
        except (ShortReplyError, LimitError):
            self._needs_resync = True
            return False
        return True

    @_locked
    def hv513_count(self) -> int:
        """Ask the board how many HV513 chips it detects (this re-initialises their outputs)."""
        self._check_open()
        self._discard_input()
        self._send(p.HV513_COUNT_REQUEST)
        return p.parse_hv513_reply(self._read_exact(1, "hv513_count"))

    @_locked
    def resync(self) -> None:
        """Bring a parser of unknown state back in step, in the order the protocol reference gives:
        256 zeros finish any command in progress; then pulse height 0 and the sense height 0 (a zero may
        have landed as the high byte of a half-received u16, so the height could be anything) and an
        all-off pattern — preceded by the electrode count, because a zero may have landed as electrode
        count 0 and a pattern then would lock the parser; then the whole configuration again.  No pattern
        follows: the caller's next frame (or keepalive) brings it back, ramped from 0.

        Without a configuration (a fresh session on a board in unknown state) the electrode count is
        unknown, so no pattern can be sent safely; pulse height 0 and sense height 0 already stop every
        current the firmware can deliver."""
        self._check_open()
        self._flush_parser()
        if self._needs_resync:
            return  # the board did not answer after the zeros
        cfg = self._config
        if cfg is not None:
            requested = self._requested
            self._config = None
            try:
                self.configure(cfg.with_current(self._target_ua))
            except BaseException:
                self._config = cfg  # still the session's configuration: the next resync tries again
                self._needs_resync = True
                raise
            self._requested = requested
            self._suspended = requested is not None
        self._needs_resync = False

    def _flush_parser(self) -> None:
        self._needs_resync = True
        cfg = self._config
        # pace for the last pattern known to be in force (a fault on the link rarely lengthens the scan, and
        # pacing too fast here costs only skipped zeros and a failed probe); unknown: every channel active
        if cfg is not None:
            last = self._scan_us / 1e6 if self._scan_us is not None else self._worst_scan_s(cfg)
            self.pacer.set_timing(firmware_period_us(cfg.rate_hz) / 1e6, last)
        else:
            self.pacer.set_timing(None, None)
        self._send(bytes(RX_QUEUE_SIZE))
        if not self._prove_in_step():
            return  # no answer (a locked parser, a dead link): nothing may follow; still needs a resync
        self._send(p.encode_pulse_height(0))
        self._current_ua = 0
        self._send(p.encode_sense_height(0))
        cfg = self._config
        self._last_pattern = None
        if cfg is not None:
            n = cfg.electrode_count
            self._send(p.encode_electrode_num(n))
            self._send(p.encode_pattern(bytes(n)))
            self._last_pattern = bytes(n)
            self._scan_us = self._scan_of(cfg, bytes(n))
            self.pacer.set_timing(firmware_period_us(cfg.rate_hz) / 1e6, self._scan_us / 1e6)
        self._needs_resync = False

    def _prove_in_step(self) -> bool:
        """After the zeros the board must answer a request before any value follows: until it has, its
        queue may still be full of zeros, and a command whose packet lost its tail there would take the next
        command's bytes as its value (pulse height 0 then a sense height reads as 0xF900 → 4095).  A request
        lost to that full queue changes nothing, so it is asked again (the read's timeout lets the parser
        drain the zeros meanwhile)."""
        for _ in range(_PROOF_ATTEMPTS):
            self._discard_input()
            self._send(p.HV513_COUNT_REQUEST)
            if len(self._read(1)) == 1:
                self.guard.note_in_step()
                return True
        return False

    @_locked
    def reconnect(self) -> None:
        """Reopen the link after it failed, then resynchronise before any pattern (the firmware may still
        hold a half-received command from before the failure)."""
        self._check_open()
        self._reopen_transport()
        self.guard.mark_unknown()
        self.pacer.reset()
        self._scan_us = None
        self._needs_resync = True
        self.resync()

    @_locked
    def hardware_reset(self) -> bool:
        """Reset the board through its reset line — the only way to reach a locked parser — and bring it
        back to the configuration.  False when the transport has no reset line."""
        self._check_open()
        if not self._reset_transport():
            return False
        self.guard.mark_unknown()
        self.pacer.reset()
        self._scan_us = 0.0  # power-on: electrode count 0, nothing to scan
        self._needs_resync = True
        self.resync()
        return True

    @_locked
    def close(self) -> None:
        """All channels off, then release the port.  Safe to call twice."""
        if self._closed:
            return
        try:
            if self._config is not None:
                self.all_off()
        finally:
            self._closed = True
            self._close_transport()

    def __enter__(self) -> Device:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()

    def __del__(self) -> None:
        if not getattr(self, "_closed", True):
            warnings.warn(f"{type(self).__name__} was never closed", ResourceWarning, stacklevel=1)

    # --- helpers -------------------------------------------------------------------------------------------

    def _send(self, data: bytes) -> None:
        """The one exit for bytes: interlock, pacing, transport, audit.  A failed write leaves the
        firmware's state unknown, so the interlock forgets it and the next frame resyncs first."""
        self._check_open()
        data = bytes(data)
        if not data:
            return
        shadow = self.guard.check_wire(data, mapping=self.mapping, transfer=self.transfer)
        audit = self._audit
        op = self._op or ""

        def write(chunk: bytes) -> None:
            self._writing = True
            try:
                self._write(chunk)
            except BaseException:
                if audit is not None:
                    audit.tx(chunk, t=self.pacer.clock.now(), ok=False, op=op, logical=data[:1] + chunk[1:])
                raise
            finally:
                self._writing = False
            if audit is not None:
                logical = data if chunk[:1] == data[:1] and chunk[0] >= COMMAND_BYTE_MIN else chunk
                audit.tx(chunk, t=self.pacer.clock.now(), op=op, logical=logical)

        try:
            self.pacer.write(write, data)
        except BaseException:
            self.guard.mark_unknown()
            self._needs_resync = True
            raise
        changed = self.guard.commit(shadow)
        if changed and (data[0] in _STATE_OPCODES or data[0] < COMMAND_BYTE_MIN):
            self.last_state_write = self.pacer.clock.now()  # a rewrite of the same state does not count

    def _frame(self, levels: Sequence[int], *, force_pattern: bool) -> None:
        """Put one application-order frame on the firmware: height down first, pattern, height up last."""
        cfg = self._config
        assert cfg is not None
        height = self._encodable(
            self.guard.frame_height(levels, self._target_ua, self._current_ua, cfg.pulse_width_us, raise_when_idle=False)
        )
        hw = self.mapping.to_hardware(levels) if self.mapping is not None else bytes(levels)
        period = firmware_period_us(cfg.rate_hz)
        scan = self._scan_of(cfg, hw)
        self.guard.check_scan(scan, period, SCAN_GAP_MIN_US)
        before = self._scan_us if self._scan_us is not None else self._worst_scan_s(cfg) * 1e6
        self.pacer.set_timing(period / 1e6, max(before, scan) / 1e6)
        if height < self._current_ua:
            self._send_critical(p.encode_pulse_height(self.transfer.to_code(height)))
            self._current_ua = height
        if force_pattern or hw != self._last_pattern:
            self._send_critical(p.encode_pattern(hw, electrode_num=cfg.electrode_count))
            self._last_pattern = hw
            self.frames_sent += 1
        if height > self._current_ua:
            self._send_critical(p.encode_pulse_height(self.transfer.to_code(height)))
            self._current_ua = height
        self._suspended = False
        self._scan_us = scan
        self.pacer.set_timing(period / 1e6, scan / 1e6)

    def _scan_of(self, cfg: StimConfig, hw: bytes) -> float:
        return estimate_scan_us(hw, cfg.pulse_width_us, cfg.discharge_us, cfg.sense_width_us)

    def _worst_scan_s(self, cfg: StimConfig) -> float:
        """The longest scan a frame the guard allows can have (every channel active, just within the
        period): what to pace for when the firmware's pattern is unknown."""
        period = firmware_period_us(cfg.rate_hz)
        full = self._scan_of(cfg, bytes([1]) * cfg.electrode_count)
        return min(full, period - SCAN_GAP_MIN_US) / 1e6

    def _send_critical(self, data: bytes) -> None:
        """Heights and patterns: under robust encoding written twice, so a byte lost, corrupted or
        duplicated in one copy is put right by the other a millisecond later (the copies are identical,
        so a firmware in step sees no change)."""
        self._send(data)
        if self.pacer.robust:
            self._send(data)

    def _mark_frame(self) -> None:
        self.last_frame_time = self.pacer.clock.now()

    def _encodable(self, height_ua: int) -> int:
        """Under robust encoding no payload byte may look like a command byte: lower such heights."""
        if not self.pacer.robust or height_ua <= 0:
            return height_ua
        h = height_ua
        while h > 0 and (self.transfer.to_code(h) & 0xFF) >= COMMAND_BYTE_MIN:
            h -= CURRENT_STEP_UA
        if h != height_ua:
            self.guard.note_clip("encoding", height_ua, h, "pulse-height code whose low byte looks like a command byte")
        return h

    def _check_robust(self, config: StimConfig) -> None:
        cmds = {
            "electrode_count": p.encode_electrode_num(config.electrode_count),
            "pulse_width_us": p.encode_pulse_width(config.pulse_width_us),
            "discharge_us": p.encode_discharge(config.discharge_us),
            "rate_hz": p.encode_frequency(config.rate_hz),
            "sense_width_us": p.encode_sense_width(config.sense_width_us),
            "sense_current_ua": p.encode_sense_height(sense_code(config.sense_current_ua, self.transfer)),
        }
        for name, data in cmds.items():
            if command_like_payload(data) is not None:
                exc = LimitError(
                    name,
                    getattr(config, name),
                    "a value whose bytes are all below 0xF5 (robust encoding: a payload byte must never look "
                    "like a command byte)",
                )
                self.guard.note_refusal(exc)
                raise exc

    def _read_exact(self, size: int, what: str) -> bytes:
        data = self._read(size)
        if len(data) != size:
            raise ShortReplyError(what, size, data)
        return data

    def _check_open(self) -> None:
        if self._closed:
            raise PortNotOpenError(f"{type(self).__name__} is closed")

    def _require_config(self, what: str) -> StimConfig:
        self._check_open()
        if self._config is None:
            raise ProtocolMisuseError(
                f"{what} before configure(): the firmware's electrode count is still 0, and a pattern now "
                "would lock its parser"
            )
        return self._config

    def _application_levels(self) -> list[int] | None:
        if self._last_pattern is None:
            return None
        if self.mapping is not None:
            return self.mapping.to_application(self._last_pattern)
        return list(self._last_pattern)
