"""The recovery state machine: what the driver has proved about the firmware's parser and receive queue.

A :class:`Device <tactdeform_hw.device.driver.base.Device>` holds one :class:`LinkRecovery`; every write
outside the recovery's own is gated on :attr:`LinkRecovery.in_step`, and every transition is recorded
(with its time and why), so a session's log shows when the host knew the firmware's state and when it did
not.  The states and their edges are drawn in ``docs/safety.md``; tests walk every edge.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Callable, Sequence
from enum import Enum
from typing import TYPE_CHECKING

from tactdeform_hw import protocol as p
from tactdeform_hw.clock import SimulatedClock
from tactdeform_hw.device.driver.config import StimConfig
from tactdeform_hw.device.driver.dialect import worst_scan_s
from tactdeform_hw.device.driver.pacing import Pacer, PacingPolicy, firmware_period_us
from tactdeform_hw.errors import ProtocolMisuseError, ReplyLengthError, TransportError

if TYPE_CHECKING:
    from tactdeform_hw.device.driver.dialect import Dialect, DriverState, LinkOps


class LinkState(str, Enum):
    """What the driver has proved about the firmware's parser and receive queue (see ``docs/safety.md``).

    Only in ``IN_STEP`` may a multi-byte value, an electrode count or a pattern be written.  Every other
    state writes only bytes that no parser state can turn into a current — zeros, 0xF5, 0xFF, each behind
    zeros that complete whatever command could be in progress — or heights of 0 once a reply has proved a
    command boundary.
    """

    IN_STEP = "in_step"  # the parser reads our commands at their boundaries; the queue model runs
    SUSPECT = "suspect"  # fresh open, failed write, short or late reply, reopened port, reset: nothing known
    SYNCING = "syncing"  # zeros then 0xF5 written: waiting for the one-byte reply that proves a boundary
    FLUSHING = "flushing"  # 0xF5 unanswered (swallowed by a pattern, or a slow parser): zeros in chunks
    SAFE = "safe"  # boundary proved and queue drained: pulse height 0, sense height 0, electrode count
    VERIFYING = "verifying"  # 0xFF written: the reply must be exactly 2 x electrode count bytes long
    DRAINING = "draining"  # before the reset line: the last bytes read (proved) and none left on the link
    RESETTING = "resetting"  # the reset line is pulsed
    BOOTING = "booting"  # the firmware boots; nothing is written
    FAILED = "failed"  # no proof within the attempts: a locked or hung parser (only the reset line helps)


#: Which state may follow which (the recovery state machine; tests walk every edge).
TRANSITIONS: dict[LinkState, frozenset[LinkState]] = {
    LinkState.IN_STEP: frozenset({LinkState.SUSPECT, LinkState.DRAINING}),
    LinkState.SUSPECT: frozenset({LinkState.SYNCING, LinkState.DRAINING}),
    LinkState.SYNCING: frozenset({LinkState.SAFE, LinkState.FLUSHING, LinkState.SUSPECT}),
    LinkState.FLUSHING: frozenset({LinkState.SAFE, LinkState.FAILED, LinkState.SUSPECT}),
    LinkState.SAFE: frozenset({LinkState.VERIFYING, LinkState.IN_STEP, LinkState.SUSPECT}),
    LinkState.VERIFYING: frozenset({LinkState.IN_STEP, LinkState.SUSPECT, LinkState.FAILED}),
    LinkState.DRAINING: frozenset({LinkState.RESETTING, LinkState.SUSPECT}),
    LinkState.RESETTING: frozenset({LinkState.BOOTING, LinkState.SUSPECT}),
    LinkState.BOOTING: frozenset({LinkState.SUSPECT}),
    LinkState.FAILED: frozenset({LinkState.SUSPECT, LinkState.DRAINING}),
}

#: Zeros in front of every probe byte: they complete a u8 or u16 command in progress (a zero height, a
#: zero width or rate — which the firmware ignores), so the probe byte itself is read as a command; only a
#: pattern in progress can take it, as one more level (a sense pulse at the sense height already in force).
PROBE_LEAD_ZEROS = 4
#: How often a reply is polled while its deadline runs.
REPLY_POLL_S = 0.0005
#: How long the driver listens past a whole reply for more of it (then two byte times more): one USB
#: full-speed frame, the time a reply longer than a packet takes to send its next packet.  A longer reply
#: than asked for is no proof: on v1.2 it is a 0xFF answered for more channels than the host's count.
REPLY_TAIL_S = 0.001
#: Verification rounds (sync, safe, verify) before the recovery gives up.
RECOVERY_ATTEMPTS = 2


class LinkRecovery:
    """The link's state (:class:`LinkState`), its transitions and proofs, recorded with their times.

    ``pacer`` gives the device's pacer at the time of the call (a device may replace its pacer once its
    port is open): a move to ``SUSPECT`` freezes its queue model, and its clock times the records."""

    def __init__(self, pacer: Callable[[], Pacer]) -> None:
        self._pacer = pacer
        # nothing is known about a board just opened: the first write proves a command boundary first
        self.state = LinkState.SUSPECT
        # (time s, from, to, why) of the latest transitions: the driver's own record of when it knew the
        # firmware's state and when it did not
        self.transitions: deque[tuple[float, str, str, str]] = deque(maxlen=4096)
        self.proofs: deque[float] = deque(maxlen=4096)  # when a reply last proved the parser in step
        #: When this device began writing without proof (its identification); None until then
        self.unproved_since: float | None = None

    @property
    def in_step(self) -> bool:
        return self.state is LinkState.IN_STEP

    def enter(self, state: LinkState, why: str) -> None:
        """One transition of the recovery state machine (only those in :data:`TRANSITIONS`)."""
        old = self.state
        if state not in TRANSITIONS[old]:
            raise ProtocolMisuseError(f"recovery: no transition from {old.value} to {state.value} ({why})")
        pacer = self._pacer()
        if state is LinkState.SUSPECT:
            pacer.suspect()
        self.state = state
        self.transitions.append((pacer.clock.now(), old.value, state.value, why))

    def suspect(self, why: str) -> None:
        """Whatever the state, nothing is proved any more (the queue model freezes too)."""
        self._pacer().suspect()
        if self.state is not LinkState.SUSPECT:
            self.enter(LinkState.SUSPECT, why)

    def proved(self, mark: int) -> None:
        """A reply proved every byte before ``mark`` read: the queue model is emptied up to it."""
        pacer = self._pacer()
        pacer.proven(mark)
        self.proofs.append(pacer.clock.now())

    # --- the procedures ----------------------------------------------------------------------------------

    def recover(self, dialect: Dialect, ops: LinkOps, st: DriverState, reset: Callable[[], object]) -> None:
        """The closed-loop recovery (the dialect's: SUSPECT → … → IN_STEP), and when it ends in FAILED (a
        locked or hung parser, which no byte can reach, while the board may go on stimulating) ``reset``
        — the reset line and its own resync — at once, if there is a line."""
        try:
            dialect.flush_parser(ops, st)
        except ReplyLengthError:
            if self.state is not LinkState.FAILED or ops.resetting() or not ops.can_reset():
                raise
            reset()  # its own resync proves the board in step again, or raises

    def reset_board(
        self,
        ops: LinkOps,
        st: DriverState,
        *,
        in_step: bool,
        pulse: Callable[[], bool],
        boot_s: float,
        who: str,
    ) -> None:
        """DRAINING (:meth:`drain`), RESETTING (``pulse``: the reset line), BOOTING (``boot_s``, nothing
        written), then SUSPECT with the state of a board at power-on: the caller's resync follows."""
        self.enter(LinkState.DRAINING, "hardware_reset")
        self.drain(ops, st, in_step)
        self.enter(LinkState.RESETTING, "nothing left on the link")
        try:
            pulsed = pulse()
        except BaseException:
            self.suspect("the reset line failed")
            raise
        if not pulsed:
            self.suspect("no reset line after all")
            raise TransportError(f"{who}: the reset line could not be pulsed")
        ops.guard.mark_unknown()
        st.current_ua = 0
        st.sense_byte = None
        st.last_pattern = None
        st.scan_us = 0.0  # power-on: electrode count 0, nothing to scan
        st.after_reset = True
        self.enter(LinkState.BOOTING, "reset line pulsed")
        pacer = self._pacer()
        pacer.wait_until(pacer.clock.now() + boot_s)
        self.enter(LinkState.SUSPECT, f"booted ({boot_s * 1e3:g} ms)")

    def drain(self, ops: LinkOps, st: DriverState, in_step: bool) -> None:
        """Before the reset line: in step, a request alone is read as a command and its reply proves the
        queue read; then the wait until every byte written has surely crossed the link (so no pattern
        lands on the freshly reset firmware, whose electrode count is 0)."""
        if in_step:
            try:
                ops.recovery_prove(st.config.electrode_count if st.config is not None else 0)
            except (TransportError, ReplyLengthError):
                # no proof: the reset is the remedy, after the link has surely delivered everything
                if self.state is not LinkState.DRAINING:
                    self.enter(LinkState.DRAINING, "no proof: reset anyway")
        pacer = self._pacer()
        pacer.wait_until(pacer.arrived_by() + pacer.policy.link_latency_s)

    def unproved_spans(self) -> list[tuple[float, float | None]]:
        """(start, end) of every span spent without proof that the parser was in step (end None: still
        open), from :attr:`transitions`: what the host knew it did not know."""
        spans: list[tuple[float, float | None]] = []
        start: float | None = self.unproved_since  # the identification wrote before any transition
        for t, old, new, _ in self.transitions:
            if old != LinkState.IN_STEP.value and start is None and not spans:
                start = t  # unproved since the device was opened
            if old == LinkState.IN_STEP.value and start is None:
                start = t
            if new == LinkState.IN_STEP.value and start is not None:
                spans.append((start, t))
                start = None
        if start is not None:
            spans.append((start, None))
        return spans


def probe_bound_s(policy: PacingPolicy, cfg: StimConfig, frame: Sequence[bytes]) -> float:
    """The longest a probe (a measure request) waits for its reply at ``cfg`` before it counts as
    unanswered — computed on a simulated clock with a scratch pacer of ``policy``: behind as many frames
    (``frame``: the longest frame's commands, as written) as the pacer lets into the queue (it never plans
    more, so the backlog a probe can meet is at most that), the request, then its reply's deadline."""
    n = cfg.electrode_count
    timing = (firmware_period_us(cfg.rate_hz) / 1e6, worst_scan_s(cfg))

    def scratch() -> Pacer:
        pacer = Pacer(clock=SimulatedClock(), policy=policy)
        pacer.set_timing(*timing)
        return pacer

    # the backlog: the most the queue model holds after any of the frames' writes (the probe may come
    # right after any of them); the request waits at most that long to fit, then is read on its own
    filled = scratch()
    frames = filled.limit_bytes // max(1, sum(len(c) for c in frame)) + 2
    backlog = 0.0
    for _ in range(frames):
        for data in frame:
            filled.write(lambda _chunk: None, data)
            backlog = max(backlog, filled.drained_by() - filled.clock.now())
    alone = scratch()
    alone.write(lambda _chunk: None, p.MEASURE_REQUEST)
    own = alone.drained_by() - alone.clock.now()  # its crossing, a scan, its read, a tick
    slack = 0.003 + 2 * n * alone.policy.byte_s + timing[0]  # as ``Device._reply_slack_s``
    return backlog + own + slack + REPLY_POLL_S


__all__ = [
    "probe_bound_s",
    "PROBE_LEAD_ZEROS",
    "RECOVERY_ATTEMPTS",
    "REPLY_POLL_S",
    "TRANSITIONS",
    "LinkRecovery",
    "LinkState",
]
