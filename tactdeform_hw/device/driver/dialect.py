"""What a firmware dialect is given and what it must provide: the device's side of the v1.2/v2 split.

A :class:`~tactdeform_hw.device.driver.base.Device` sends, paces, audits and keeps the link's proofs; a
:class:`Dialect` decides which bytes express an operation on its firmware version, from the state in force
(:class:`DriverState`).  A dialect never sees the device, so both versions are read and tested against the
same interface, and :data:`~tactdeform_hw.device.driver.dialects.DIALECTS` picks one per firmware spec.

The dialect is a pure planner: it returns an operation's steps (a :class:`Plan`) and the device's wire
carries them out — ``configure``, ``frame``, ``set_current``, ``refresh``, ``off`` (the all-off), the
guardian's stops, the longest frame, and on v2 the count raised without stale channels and the covered
pattern, which its other steps run as sub-plans.  A plan is made on a copy of the state
(:class:`PlanBuilder`) against a :class:`PlanContext` (the guard, which judges its currents before any
byte, the mapping, the transfer, the encoding) and, for a configuration, the pace in force
(:class:`PaceInForce`).  Its steps (:data:`Step`) are writes, proofs (:class:`Prove`: the dialect's
request and its reply; a proof that is not answered stops the plan), changes of pace (:class:`Pace`,
:class:`PaceFor`, :class:`Settle`) and the guard's records where the operation makes them
(:class:`Note`); every step carries the state it puts in force, applied only once it is done: a write cut
half way leaves the state of the writes that got through, as it always did, so the next frame writes the
same bytes.  A refusal part way that must leave a change in force (v2 restarts the ramp on a change of
mode before a refusal can come, and that restart is kept even when the frame is refused) is a plan too:
the change, then the refusal, and no write.

The dialect is handed the link operations (:class:`LinkOps`) only where a step depends on a reply in a
way a plan does not express: the closed-loop recovery (``flush_parser``), whose branches follow the
replies, the proofs themselves, close's proof and the firmware check.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, NamedTuple, Protocol

from tactdeform_hw.clock import SimulatedClock
from tactdeform_hw.device.driver.config import StimConfig
from tactdeform_hw.device.driver.pacing import SCAN_GAP_MIN_US, Pacer
from tactdeform_hw.protocol.constants import PATTERN_BIPHASIC, PATTERN_MONOPHASIC
from tactdeform_hw.protocol.firmware import FirmwareSpec
from tactdeform_hw.protocol.firmware_math import estimate_scan_us, firmware_period_us

if TYPE_CHECKING:
    from tactdeform_hw.device.links.recovery import LinkState
    from tactdeform_hw.device.participant.mapping import ChannelMapping
    from tactdeform_hw.device.safety.guard import SafetyGuard
    from tactdeform_hw.protocol.units import CurrentTransfer


@dataclass
class DriverState:
    """What the host believes the firmware holds, and what the caller asked for.

    Two currents are kept apart: the *target* (what the caller asked for) and the *height in force* (what
    the firmware's pulse-height register holds; on v2 the highest of the electrodes' heights)."""

    config: StimConfig | None = None  # the configuration last sent
    current_ua: int = 0  # pulse height in force on the firmware
    sense_byte: int | None = None  # the 0xF9 byte in force (None: unknown)
    target_ua: int = 0  # what the caller asked for
    last_pattern: bytes | None = None  # hardware order, as on the firmware (levels)
    requested: list[int] | None = None  # the caller's last frame, application order
    suspended: bool = False
    scan_us: float | None = None  # estimated scan of the pattern in force (None: unknown)
    frames_sent: int = 0
    after_reset: bool = False  # the reset line was pulsed: the firmware's electrode count is 0
    bound_seen_s: float = 0.0  # the largest failing-resync bound at the start of any recovery
    # firmware v2's registers (unused on v1.2, whose pattern buffer holds the levels themselves)
    mode: int | None = None  # the stimulation mode in force (None: unknown)
    codes: list[int] | None = None  # DAC code per hardware channel in force (None: unknown)
    heights_ua: list[int] = field(default_factory=list)  # height per application electrode in force
    answered: bool = False  # the board has answered a sync check in this session (it runs v2)
    covers: int = 0  # patterns written under the mode-2 cover

    @property
    def stimulating(self) -> bool:
        """Whether the firmware, as far as the host knows, is delivering current to any channel."""
        if self.config is None:
            return False
        if self.config.sense_current_ua:
            return True
        active = (PATTERN_MONOPHASIC, PATTERN_BIPHASIC)
        return (
            bool(self.current_ua)
            and self.last_pattern is not None
            and any(v in active for v in self.last_pattern)
        )

    def application_levels(self, mapping: ChannelMapping | None) -> list[int] | None:
        """The pattern in force in application order (None: unknown)."""
        if self.last_pattern is None:
            return None
        if mapping is not None:
            return mapping.to_application(self.last_pattern)
        return list(self.last_pattern)


@dataclass(slots=True)
class Write:
    """One planned write: ``data`` (one command), or ``commands`` written at once (v2's parser applies
    them back to back).  ``critical`` ones (heights, patterns) go twice under robust encoding; a
    ``recovery`` one is the recovery's own (allowed before the proof); ``pad`` forces the loss-tolerant
    padding on or off.  ``puts``: the fields of :class:`DriverState` in force once this write is written
    (applied only then: after a write that fails, the state is that of the writes that got through)."""

    data: bytes = b""
    commands: tuple[bytes, ...] = ()
    critical: bool = False
    recovery: bool = False
    pad: bool | None = None
    puts: dict[str, Any] = field(default_factory=dict)


@dataclass(frozen=True)
class Prove:
    """A proof at this point of a plan: the dialect's request whose reply proves every byte written before
    it read, at electrode count ``electrodes`` (no whole reply: the plan stops there,
    :class:`~tactdeform_hw.errors.ShortReplyError`).  ``unless_room_for``: only when the pacer's queue
    model, at that moment, has no room for a write of that many bytes (a long pattern goes into a queue
    proved empty)."""

    electrodes: int
    unless_room_for: int | None = None
    puts: dict[str, Any] = field(default_factory=dict)


@dataclass(frozen=True)
class Pace:
    """From here on the pacer paces for ``timing`` (period s, scan s; None: unknown)."""

    timing: tuple[float | None, float | None]
    puts: dict[str, Any] = field(default_factory=dict)


@dataclass(frozen=True)
class PaceFor:
    """From here on the pacer paces for the slowest of ``timings`` (period µs, scan µs) that may be in
    force, with ``with_current`` the timing it paces for now among them (when known)."""

    timings: tuple[tuple[float, float], ...]
    with_current: bool = False
    puts: dict[str, Any] = field(default_factory=dict)


@dataclass(frozen=True)
class Settle:
    """The pacer paces for ``timing`` (period s, scan s) from here on; when that is faster than the pace
    in force (or ``always``), a proof at electrode count ``electrodes``, paced as before, comes first: the
    faster pace only once the device proves it has read every command written at the slower one."""

    timing: tuple[float, float]
    electrodes: int
    always: bool = False
    puts: dict[str, Any] = field(default_factory=dict)


@dataclass(frozen=True)
class Note:
    """A height lowered to what the encoding can carry, recorded by the guard at this point of the plan
    (where the operation computed it)."""

    rule: str
    requested_ua: int
    sent_ua: int
    why: str
    puts: dict[str, Any] = field(default_factory=dict)


#: One step of a plan: a write, or what the executor does between writes.
Step = Write | Prove | Pace | PaceFor | Settle | Note


class PaceInForce(NamedTuple):
    """The pacer's timing when a plan is made (period s, scan s; None: unknown), and its choice of the
    slowest of several (period µs, scan µs) that may be in force (what :class:`PaceFor` paces for)."""

    period_s: float | None
    scan_s: float | None
    slowest: Callable[[Sequence[tuple[float, float]]], tuple[float, float]]


@dataclass
class Plan:
    """The steps of a planned operation, in order (:data:`Step`: mostly writes; a configuration's proofs
    and changes of pace between them); ``puts_before``, the state put in force before the first (a change
    that needs no byte, e.g. a ramp restarted); ``pace_before``, the (period s, scan s) the pacer paces the
    writes for; ``pace_after``, the one it paces for once the last is written.

    ``refusal``: the planning refused the operation part way, after a change that must hold all the same
    (v2's ramp restarted by a change of mode): the executor puts ``puts_before`` in force and raises it,
    writing nothing."""

    writes: list[Step] = field(default_factory=list)
    puts_before: dict[str, Any] = field(default_factory=dict)
    pace_after: tuple[float, float] | None = None
    pace_before: tuple[float, float] | None = None
    refusal: Exception | None = None


class PlanContext(NamedTuple):
    """What a plan is made against besides the state in force: the guard that judges its currents (and
    records its clips and refusals), the channel mapping, the µA-to-code transfer, and whether the pacer
    writes the loss-tolerant encoding (no payload byte may then look like a command byte)."""

    guard: SafetyGuard
    mapping: ChannelMapping | None
    transfer: CurrentTransfer
    robust: bool


class PlannedState(DriverState):
    """A copy of the state in force that notes the name of every field the planning code assigns (for
    :class:`PlanBuilder`: what it notes since the last step is put in force with that step)."""

    __slots__ = ("assigned",)
    assigned: list[str]

    def __setattr__(self, name: str, value: Any) -> None:
        self.__dict__[name] = value
        self.assigned.append(name)


class PlanBuilder:
    """Plans writes against a copy of the state in force: the planning code reads and changes ``st`` as
    if each write had been written, and every change is recorded on the write it follows (so it is put
    in force only once that write is), or before the first write.  The dialects' code assigns new values
    to the state's fields and never changes a list in place, so a shallow copy is the whole state.  Every
    frame is planned here, so the copy is one of the fields' dictionary and the record follows the
    assignments (``copy.copy`` and a comparison of every field cost several times as much)."""

    def __init__(self, st: DriverState) -> None:
        planned = PlannedState.__new__(PlannedState)
        planned.__dict__.update(st.__dict__)
        object.__setattr__(planned, "assigned", [])
        self.st: DriverState = planned
        self._assigned = planned.assigned
        self._fields = planned.__dict__
        self.plan = Plan()
        self._target = self.plan.puts_before

    def _record(self) -> None:
        assigned = self._assigned
        if assigned:
            fields_ = self._fields
            target = self._target
            for name in assigned:
                target[name] = fields_[name]
            assigned.clear()

    def add(self, step: Step) -> None:
        self._record()
        self.plan.writes.append(step)
        self._target = step.puts

    def done(self, pace_after: tuple[float, float] | None = None) -> Plan:
        self._record()
        self.plan.pace_after = pace_after
        return self.plan

    def refused(self, error: Exception) -> Plan:
        """The operation refused by ``error`` after the changes made so far (before any write): they are
        put in force, nothing is written, and the executor raises ``error``."""
        self._record()
        assert not self.plan.writes, "a refusal comes before any write"
        return Plan(puts_before=self.plan.puts_before, refusal=error)


@dataclass(frozen=True)
class LinkOps:
    """The link operations a dialect may use (bound by the device): each write passes the device's gate,
    interlock, pacer and audit; replies are read to their deadline; proofs go to the recovery record."""

    pacer: Callable[[], Pacer]
    guard: SafetyGuard
    mapping: ChannelMapping | None
    unknown_reply_s: float
    #: one command (``pad``: None the pacer's policy, True/False forced)
    send: Callable[..., None]
    #: a write of the recovery itself (allowed before the proof); the written offset just past it
    recovery_send: Callable[..., int]
    discard_input: Callable[[], None]
    #: up to n bytes of a reply until its deadline (``whole=True``: and any more that follow at once)
    await_reply: Callable[..., bytes]
    #: a reply proved every byte before the mark read
    proved: Callable[[int], None]
    suspect: Callable[[str], None]
    enter: Callable[[LinkState, str], None]
    link_state: Callable[[], LinkState]
    #: the proof of the dialect in force (a request whose reply proves the queue read)
    prove: Callable[[int], None]
    #: the same proof as a write of the recovery itself (the drain before the reset line)
    recovery_prove: Callable[[int], None]
    #: a request byte and its whole reply of the given size, which proves every byte before it read (a
    #: short or a longer one: the link suspect and a :class:`ReplyLengthError` naming the request)
    request: Callable[[bytes, int, str], bytes]
    #: a dialect's planned writes (:class:`Plan`), each putting its state in force once written
    run: Callable[[Plan, DriverState], None]
    #: 0xFF and its whole reply (levels of each hardware channel's last pulse)
    measured: Callable[[int, str], list[int]]
    can_reset: Callable[[], bool]
    resetting: Callable[[], bool]


def scan_of(cfg: StimConfig, hw: bytes) -> float:
    """v1.2's firmware-order estimate of a scan of the pattern ``hw`` at ``cfg``'s widths (µs)."""
    return estimate_scan_us(hw, cfg.pulse_width_us, cfg.discharge_us, cfg.sense_width_us)


def worst_scan_s(cfg: StimConfig) -> float:
    """The longest scan a frame the guard allows can have (every channel biphasic, just within the
    period): what to pace for when the firmware's pattern is unknown."""
    period = firmware_period_us(cfg.rate_hz)
    full = scan_of(cfg, bytes([PATTERN_BIPHASIC]) * cfg.electrode_count)  # two phases: the longest
    return min(full, period - SCAN_GAP_MIN_US) / 1e6


def timing_before_count(old: StimConfig | None, new: StimConfig) -> bool:
    """Whether a configuration writes its rate and widths before its electrode count: when the count
    rises — above the configuration in force, or from the count 0 the identification leaves (the first
    configuration of a device).

    The firmware scans the new count at whatever rate and widths are in force when it reads the count.
    Written after it, the old rate runs the longer scan for as long as the rest of the configuration takes
    to read: from 32 to 255 channels at 100 Hz (a configuration in force, or the rate a previous program
    left on the board) that scan is longer than the period, the alarm fires back to back, the main loop
    never reads again and everything written behind the count is lost in the queue.  Written first, the
    new timing is in force when the count rises, so the scans of the transition are the old count's at the
    new timing (no longer than the new count's, which the guard checked; none at all at count 0) and the
    new count's own.  A count that stays or falls keeps the order it always had."""
    return old is None or new.electrode_count > old.electrode_count


def count_raise_timing(new: StimConfig) -> tuple[float, float]:
    """(period µs, scan µs) that paces the bytes behind a raised electrode count (the new timing is in
    force, :func:`timing_before_count`): the new period and the longest scan the new count can run until
    its all-off pattern is read — the channels above the old count hold whatever they last held, so every
    channel counts as biphasic (:func:`worst_scan_s`)."""
    return firmware_period_us(new.rate_hz), worst_scan_s(new) * 1e6


def recovery_timing(state: DriverState) -> tuple[float | None, float | None]:
    """(period s, scan s) to pace and time the recovery for: the scan of the pattern last sent (a
    pattern the host does not know — after a reset, a reconnect, or before any — counts as every channel
    biphasic).  Should a fault have left a longer scan in force, zeros and 0xF5 may be lost: the proof
    then fails and the reset line follows — the safe direction."""
    cfg = state.config
    if cfg is None:
        return None, None
    scan = state.scan_us / 1e6 if state.scan_us is not None else worst_scan_s(cfg)
    return firmware_period_us(cfg.rate_hz) / 1e6, scan


def begin_recovery(
    ops: LinkOps, st: DriverState, bound_now_s: Callable[[LinkOps, DriverState], float]
) -> tuple[StimConfig | None, int]:
    """What every version's recovery does first; returns the configuration in force and its electrode
    count (None and 0 before a configuration).  On a configured board the resync bound at this
    configuration (``bound_now_s``, the dialect's own) is kept in ``st.bound_seen_s`` before any byte, so
    :meth:`~.base.Device.resync_bound_s` covers the recovery under way; then the pacer is timed for the
    recovery (:func:`recovery_timing`).  Before a configuration the wait is the unknown board's,
    ``unknown_reply_s``."""
    cfg = st.config
    n = cfg.electrode_count if cfg is not None else 0
    if cfg is not None:
        st.bound_seen_s = max(st.bound_seen_s, bound_now_s(ops, st))
    ops.pacer().set_timing(*recovery_timing(st))
    return cfg, n


def rehearsal_in_flight(
    ops: LinkOps, st: DriverState, frame_commands: Callable[[int], list[bytes]], *, pad: bool | None
) -> tuple[int, SimulatedClock, Pacer]:
    """Where a resync's bound starts, rehearsed without touching the port: (the electrode count in force,
    a simulated clock, a scratch pacer on it with the live pacer's policy and the recovery's timing) with
    the all-off frame of that count already written through the pacer (twice under robust encoding, as
    the live path writes it) — the frame the failing resync finds still in flight.  ``pad``: as
    :meth:`~tactdeform_hw.device.driver.pacing.Pacer.write`.  Each dialect then adds its own probes and
    reply deadlines."""
    cfg = st.config
    n = cfg.electrode_count if cfg is not None else 0
    clock = SimulatedClock()
    scratch = Pacer(clock=clock, policy=ops.pacer().policy)
    scratch.set_timing(*recovery_timing(st))
    copies = 2 if ops.pacer().robust else 1
    for data in [c for c in frame_commands(n) for _ in range(copies)]:
        scratch.write(lambda _chunk: None, data, pad=pad)
    return n, clock, scratch


class Dialect(Protocol):
    """How one firmware version expresses the device's operations (see :mod:`.v1_2` and :mod:`.v2`).

    Every method takes the state in force and the link operations; none keeps state of its own, so one
    instance serves every device (:data:`~tactdeform_hw.device.driver.dialects.DIALECTS`)."""

    firmware: FirmwareSpec
    #: the identification's signature answers the electrode count in force (v2's 0xF4)
    signature_proves_count: bool

    def validated(self, config: StimConfig, transfer: CurrentTransfer) -> StimConfig:
        """``config`` checked against this firmware's encodable values (:class:`LimitError` if not)."""

    def check_idle_scan(self, guard: SafetyGuard, config: StimConfig) -> None:
        """Refuse, before any byte and before the caller's frame is superseded, a configuration whose idle
        scan starves the parser (where the version refuses it there)."""

    def check_levels(self, levels: Sequence[int]) -> None:
        """Refuse a frame of valid levels this firmware cannot express."""

    def check_configuration(self, guard: SafetyGuard, config: StimConfig) -> None:
        """Refuse, before any byte but once the caller's frame is superseded, a configuration this version
        cannot run (where the version refuses it there)."""

    def configure(self, ctx: PlanContext, st: DriverState, config: StimConfig, pace: PaceInForce) -> Plan:
        """A whole configuration in an order that never stimulates with a half-set state, planned from the
        state in force once the link is proved in step (its proofs are steps of the plan)."""

    def frame(self, ctx: PlanContext, st: DriverState, levels: Sequence[int], *, force_pattern: bool) -> Plan:
        """One application-order frame on the firmware (refused before any byte when the guard refuses
        it)."""

    def set_current(self, ctx: PlanContext, st: DriverState, levels: list[int] | None) -> Plan:
        """The target changed: the frame in force (``levels``, None when suspended or unknown) follows."""

    def off(self, st: DriverState, mapping: ChannelMapping | None, scan_s: float | None) -> Plan:
        """Every channel off and every height 0 (at a proved boundary); ``scan_s`` is the scan the pacer
        paces for now (None: unknown)."""

    def refresh(self, ctx: PlanContext, st: DriverState, *, sense: bool) -> Plan:
        """The same registers again, so a firmware that lost or mis-read a byte is put right."""

    def flush_parser(self, ops: LinkOps, st: DriverState) -> None:
        """The closed-loop recovery: SUSPECT → … → IN_STEP, or raise (FAILED)."""

    def prove(self, ops: LinkOps, electrodes: int) -> None:
        """In step: a request whose reply proves every byte written before it read."""

    def prove_stopped(self, ops: LinkOps, st: DriverState) -> None:
        """``close``'s proof that nothing stimulates after the all-off."""

    def resync_bound_now_s(self, ops: LinkOps, st: DriverState) -> float:
        """The longest a resync that fails waits for its proofs at the configuration in force."""

    def frame_commands(self, n: int) -> list[bytes]:
        """The longest frame this dialect writes at electrode count ``n``, command by command."""

    def heights_in_force(self, st: DriverState, mapping: ChannelMapping | None) -> list[int] | None:
        """Each application electrode's DAC code in the pattern buffer (None where it holds levels)."""

    def guardian_stop(self, electrode_count: int) -> bytes:
        """The guardian's stop packet for this firmware at ``electrode_count``."""

    def guardian_open_stop(self) -> bytes | None:
        """The guardian's stop once the board proved this firmware (None: keep the guardian's default)."""


__all__ = [
    "Dialect",
    "DriverState",
    "LinkOps",
    "Note",
    "Pace",
    "PaceFor",
    "PaceInForce",
    "Plan",
    "PlanBuilder",
    "PlanContext",
    "PlannedState",
    "Prove",
    "Settle",
    "Step",
    "Write",
    "begin_recovery",
    "count_raise_timing",
    "recovery_timing",
    "rehearsal_in_flight",
    "scan_of",
    "timing_before_count",
    "worst_scan_s",
]
