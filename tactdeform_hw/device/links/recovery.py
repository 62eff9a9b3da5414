"""The recovery state machine: what the driver has proved about the firmware's parser and receive queue.

A :class:`Device <tactdeform_hw.device.driver.base.Device>` holds one :class:`LinkRecovery`; every write
outside the recovery's own is gated on :attr:`LinkRecovery.in_step`, and every transition is recorded
(with its time and why), so a session's log shows when the host knew the firmware's state and when it did
not.  The states and their edges are drawn in ``docs/safety.md``; tests walk every edge.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Callable
from enum import Enum

from tactdeform_hw.device.driver.pacing import Pacer
from tactdeform_hw.errors import ProtocolMisuseError


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


__all__ = [
    "PROBE_LEAD_ZEROS",
    "RECOVERY_ATTEMPTS",
    "REPLY_POLL_S",
    "TRANSITIONS",
    "LinkRecovery",
    "LinkState",
]
