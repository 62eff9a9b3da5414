"""The one exit for a device's bytes and the one entrance for its replies.

A :class:`Wire` owns the pacer (:mod:`.pacing`: never faster than the firmware reads) and the session's
audit log (:mod:`.audit`), and every write passes it in the same order: the gate (nothing that carries a
value leaves unless the recovery has proved the parser in step, :class:`LinkState`), the safety interlock
(:class:`~tactdeform_hw.device.safety.interlock.WireInterlock`), the pacer, the transport, the audit, and
the interlock's commit.  Replies are read to their worst-case deadline and their proofs recorded.

A dialect's plans (:class:`~tactdeform_hw.device.driver.dialect.Plan`) are carried out here
(:meth:`Wire.run`), and the :class:`~tactdeform_hw.device.driver.base.Device` and the link operations it
hands its dialect's recovery (:class:`~tactdeform_hw.device.driver.dialect.LinkOps`) send through it too,
so there is one path for bytes whichever object decided them.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field
from typing import Any

from tactdeform_hw import protocol as p
from tactdeform_hw.clock import InstantClock
from tactdeform_hw.device.driver.audit import AuditLog
from tactdeform_hw.device.driver.dialect import (
    DriverState,
    LinkOps,
    Note,
    Pace,
    PaceFor,
    PaceInForce,
    Plan,
    PlanContext,
    Prove,
    Settle,
    Step,
    Write,
)
from tactdeform_hw.device.driver.pacing import COMMAND_BYTE_MIN, Pacer, paddings
from tactdeform_hw.device.links.port import PortLink
from tactdeform_hw.device.links.recovery import REPLY_POLL_S, REPLY_TAIL_S, LinkRecovery, LinkState
from tactdeform_hw.device.participant.mapping import ChannelMapping
from tactdeform_hw.device.safety.guard import SafetyGuard
from tactdeform_hw.errors import LongReplyError, PortNotOpenError, ProtocolMisuseError, ShortReplyError
from tactdeform_hw.protocol.constants import USB_PACKET_SIZE
from tactdeform_hw.protocol.units import CurrentTransfer

#: Commands that change what the scans deliver (a measure right after one reads the old pulses).
STATE_OPCODES = frozenset(
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


@dataclass(eq=False, repr=False)
class Wire:
    """A device's send path and reply reading, over ``port_link``.

    ``guard`` checks and commits every write; ``link`` gates it and records the proofs; ``pacer`` spaces
    the writes; ``audit`` (None: none) records them, each named after ``op()`` (the public operation that
    sent it).  ``kind`` names the device in the error a closed one raises; ``unknown_reply_s`` is the
    extra wait for a reply while the alarm period is unknown."""

    port_link: PortLink
    guard: SafetyGuard
    link: LinkRecovery
    pacer: Pacer
    mapping: ChannelMapping | None
    transfer: CurrentTransfer
    kind: str
    unknown_reply_s: float
    op: Callable[[], str]
    audit: AuditLog | None = None
    #: True once the device is closed (or refused its board): nothing more is written.
    closed: bool = False
    #: True while bytes are being handed to the transport: a stop now may leave half a command.
    writing: bool = False
    #: True during a write of the recovery itself, the only writes allowed before the proof.
    recovery_write: bool = False
    #: When a write last changed what the scans deliver (a rewrite of the same state does not count).
    last_state_write: float | None = None
    #: The link operations last built (:meth:`link_ops`), with the tuple of what they bind.
    _ops_cache: tuple[tuple[Any, ...], LinkOps] | None = field(default=None, init=False)

    def check_open(self) -> None:
        if self.closed:
            raise PortNotOpenError(f"{self.kind} is closed")

    # --- sending -------------------------------------------------------------------------------------------

    def send(self, data: bytes, *, pad: bool | None = None) -> None:
        """One command: gate, interlock, pacing, transport, audit.  Outside the recovery's own writes
        nothing leaves unless the parser is proved in step (:class:`LinkState`).  A failed write leaves the
        firmware's state unknown, so the interlock forgets it and the next frame resyncs first."""
        self._send_paced(bytes(data), None, pad)

    def send_commands(self, commands: Sequence[bytes], *, pad: bool | None = None) -> None:
        """Whole commands in one write (:meth:`Pacer.write_commands`): they reach the device's queue
        together, so v2's parser applies them back to back.  Gated, checked and audited as :meth:`send`
        does a single command (the interlock reads the commands in order, every state between them
        included)."""
        cmds = [bytes(c) for c in commands if c]
        self._send_paced(b"".join(cmds), cmds, pad)

    def send_critical(self, data: bytes) -> None:
        """Heights and patterns: under robust encoding written twice, so a byte lost, corrupted or
        duplicated in one copy is put right by the other a millisecond later (the copies are identical,
        so a firmware in step sees no change)."""
        self.send(data)
        if self.pacer.robust:
            self.send(data)

    def send_critical_commands(self, commands: Sequence[bytes]) -> None:
        """:meth:`send_commands` with :meth:`send_critical`'s second copy under robust encoding."""
        self.send_commands(commands)
        if self.pacer.robust:
            self.send_commands(commands)

    def plan_context(self) -> PlanContext:
        """What a dialect plans against besides the state: this wire's guard, mapping, transfer and
        encoding."""
        return PlanContext(self.guard, self.mapping, self.transfer, self.pacer.robust)

    def run(self, plan: Plan, st: DriverState, prove: Callable[[int], None] | None = None) -> None:
        """A dialect's planned operation: its state put in force before the first step, then (a refused
        one) its refusal raised; else its pace for the writes, its steps in order — each write (a critical
        one twice under robust encoding), each proof (``prove``, the dialect's proof at an electrode
        count) and each change of pace putting its state in force in ``st`` once done — and the pace the
        plan ends with."""
        for name, value in plan.puts_before.items():
            setattr(st, name, value)
        if plan.refusal is not None:
            raise plan.refusal
        if plan.pace_before is not None:
            self.pacer.set_timing(*plan.pace_before)
        for w in plan.writes:
            if type(w) is not Write:
                self._step(w, prove)
            elif w.commands:
                if w.critical:
                    self.send_critical_commands(w.commands)
                else:
                    self.send_commands(w.commands, pad=w.pad)
            elif w.recovery:
                self.recovery_send(w.data, pad=w.pad)
            elif w.critical:
                self.send_critical(w.data)
            else:
                self.send(w.data, pad=w.pad)
            for name, value in w.puts.items():
                setattr(st, name, value)
        if plan.pace_after is not None:
            self.pacer.set_timing(*plan.pace_after)

    def _step(self, step: Step, prove: Callable[[int], None] | None) -> None:
        """One step of a plan that is not a write (see :data:`~.dialect.Step`)."""
        pacer = self.pacer
        if isinstance(step, Prove):
            if step.unless_room_for is not None:
                if pacer.queue_estimate() + step.unless_room_for + 4 <= pacer.limit_bytes:
                    return
            if prove is None:
                raise ProtocolMisuseError("a plan with a proof run without the dialect's proof")
            prove(step.electrodes)
        elif isinstance(step, Pace):
            pacer.set_timing(*step.timing)
        elif isinstance(step, PaceFor):
            timings = list(step.timings)
            if step.with_current:
                if pacer.period_s is None or pacer.scan_s is None:
                    return
                timings.insert(0, (pacer.period_s * 1e6, pacer.scan_s * 1e6))
            self.pace_for(timings)
        elif isinstance(step, Settle):
            slower = pacer.payload_interval_s(), pacer.period_s, pacer.scan_s
            pacer.set_timing(*step.timing)
            if step.always or pacer.payload_interval_s() < slower[0]:
                pacer.set_timing(slower[1], slower[2])
                if prove is None:
                    raise ProtocolMisuseError("a plan with a proof run without the dialect's proof")
                prove(step.electrodes)
                pacer.set_timing(*step.timing)
        elif isinstance(step, Note):
            self.guard.note_clip(step.rule, step.requested_ua, step.sent_ua, step.why)

    @contextmanager
    def recovery(self) -> Iterator[None]:
        """The writes inside are the recovery's own (allowed before the proof)."""
        self.recovery_write = True
        try:
            yield
        finally:
            self.recovery_write = False

    def recovery_send(self, data: bytes, *, pad: bool | None = True) -> int:
        """A write of the recovery itself (by default with the loss-tolerant padding); the written offset
        just past it, for :meth:`Pacer.proven`."""
        with self.recovery():
            self.send(data, pad=pad)
        return self.pacer.offset

    def _send_paced(self, data: bytes, commands: list[bytes] | None, pad: bool | None) -> None:
        self.check_open()
        if not data:
            return
        if self.link.state is not LinkState.IN_STEP and not self.recovery_write:
            raise ProtocolMisuseError(
                f"0x{data[0]:02X} while the firmware's parser is not proved in step "
                f"({self.link.state.value}): resync first"
            )
        shadow = self.guard.interlock.check_wire(data, mapping=self.mapping, transfer=self.transfer)
        audit = self.audit
        op = self.op()

        def write(chunk: bytes) -> None:
            self.writing = True
            try:
                self.port_link.write(chunk)
            except BaseException:
                if audit is not None:
                    audit.tx(chunk, t=self.pacer.clock.now(), ok=False, op=op, logical=data[:1] + chunk[1:])
                raise
            finally:
                self.writing = False
            if audit is None:
                return
            now = self.pacer.clock.now()
            if commands is not None:
                # one write of several commands: one record per command (its padding with it), so a
                # reader of the log sees every command as the firmware reads it
                padded = self.pacer.policy.robust_encoding if pad is None else pad
                pos = 0
                pads = paddings(commands, self.pacer.policy.firmware) if padded else [b""] * len(commands)
                n = len(commands)
                for k, (c, pad_) in enumerate(zip(commands, pads, strict=True), start=1):
                    size = len(c) + len(pad_)
                    part = (k, n) if n > 1 else None
                    audit.tx(chunk[pos : pos + size], t=now, op=op, logical=c, part=part)
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
            self.link.suspect("write failed")
            raise
        changed = self.guard.commit(shadow)
        if changed and (data[0] in STATE_OPCODES or data[0] < COMMAND_BYTE_MIN):
            self.last_state_write = self.pacer.clock.now()  # a rewrite of the same state does not count

    def pace_for(self, timings: Sequence[tuple[float, float]]) -> None:
        """Pace for the slowest of several (period µs, scan µs) that may be in force."""
        period_us, scan_us = self.slowest(timings)
        self.pacer.set_timing(period_us / 1e6, scan_us / 1e6)

    def slowest(self, timings: Sequence[tuple[float, float]]) -> tuple[float, float]:
        """The slowest of several (period µs, scan µs) to pace for (the pace in force is left as it was)."""
        pacer = self.pacer
        was = pacer.period_s, pacer.scan_s

        def cost(t: tuple[float, float]) -> tuple[float, float]:
            pacer.set_timing(t[0] / 1e6, t[1] / 1e6)
            return (pacer.payload_interval_s(), pacer.skip_s(USB_PACKET_SIZE))

        try:
            return max(timings, key=cost)
        finally:
            pacer.set_timing(*was)

    def pace_in_force(self) -> PaceInForce:
        """The pacer's timing now, and its choice among timings, for a dialect's plan."""
        return PaceInForce(self.pacer.period_s, self.pacer.scan_s, self.slowest)

    # --- replies -------------------------------------------------------------------------------------------

    def proved(self, mark: int) -> None:
        """A reply proved every byte before ``mark`` read, the parser at a command boundary."""
        self.link.proved(mark)
        self.guard.note_in_step()  # the interlock stops assuming a full queue could cut this write's packets

    def reply_slack_s(self, size: int) -> float:
        """How long after the queue model's worst drain time a reply of ``size`` bytes may still come:
        its transfer (a USB frame), one alarm period of margin, and more when the period is unknown."""
        period = self.pacer.period_s
        extra = period if period is not None else self.unknown_reply_s
        return 0.003 + size * self.pacer.policy.byte_s + extra

    def await_reply(self, size: int, whole: bool = False) -> bytes:
        """Read up to ``size`` bytes until the reply's deadline (the worst case, not the typical).

        ``whole``: once ``size`` bytes are in, listen :data:`REPLY_TAIL_S` and two byte times more and
        take what else came, so a reply longer than asked for shows as longer (a caller comparing its
        length sees it) instead of passing, read to its expected length, for the proof it is not."""
        if size <= 0:
            return b""
        clock = self.pacer.clock
        deadline = self.pacer.drained_by() + self.reply_slack_s(size)
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
                if whole and len(got) >= size:
                    got += self._reply_tail()
                return bytes(got)
            if len(got) == had:
                clock.sleep(min(REPLY_POLL_S, max(0.0, deadline - clock.now())))

    def _reply_tail(self) -> bytes:
        """What arrives in the :data:`REPLY_TAIL_S` (and two byte times) after a whole reply."""
        clock = self.pacer.clock
        if not isinstance(clock, InstantClock):
            clock.sleep(REPLY_TAIL_S + 2 * self.pacer.policy.byte_s)
        waiting = self.port_link.waiting()
        return self.port_link.read(waiting) if waiting else b""

    def request(self, data: bytes, size: int, what: str) -> bytes:
        """``data`` (a request byte) and its whole reply of exactly ``size`` bytes, which proves every byte
        before it read; a short or a longer one marks the link suspect and raises (``what`` names the
        request): a longer one is a board whose state is not the host's (v1.2: its electrode count)."""
        self.port_link.discard_input()
        self.send(data)
        mark = self.pacer.offset
        reply = self.await_reply(size, whole=True)
        if len(reply) < size:
            self.link.suspect(f"short reply to 0x{data[0]:02X}")
            raise ShortReplyError(what, size, reply)
        if len(reply) > size:
            self.link.suspect(f"reply to 0x{data[0]:02X} longer than {size} bytes")
            raise LongReplyError(what, size, reply)
        self.proved(mark)
        return reply

    def measured(self, n: int, what: str) -> list[int]:
        """0xFF and its whole reply of two bytes per channel (the levels of each hardware channel's last
        pulse), which proves every byte before it read; a short one marks the link suspect and raises."""
        return p.parse_measure_reply(self.request(p.MEASURE_REQUEST, 2 * n, what), n)

    def current_pacer(self) -> Pacer:
        """The pacer in force (a caller may put another in its place)."""
        return self.pacer

    def link_state(self) -> LinkState:
        """Where the recovery state machine stands."""
        return self.link.state

    def link_ops(
        self,
        *,
        prove: Callable[[int], None],
        recovery_prove: Callable[[int], None],
        resetting: Callable[[], bool],
    ) -> LinkOps:
        """The link operations a dialect is handed: this wire's, and the device's proof and reset state.
        Each is looked up now, so a hook replaced on the wire, its port link or recovery record, or the
        device, is the one the dialect uses.

        Building the operations costs more than a frame's bookkeeping, so they are kept between calls:
        the cache's key is the very tuple of what they bind, field by field (:meth:`_bindings`), and the
        operations are built again from that tuple whenever it differs (a bound method compares equal to
        another only when it binds the same function to the same object; the values are compared as
        Python does, and the mutable ones — the guard — compare by identity).  A stale cache is thus
        impossible by construction: whatever the operations bind is what was looked up on this call."""
        bound = self._bindings(prove, recovery_prove, resetting)
        cached = self._ops_cache
        if cached is not None and cached[0] == bound:
            return cached[1]
        ops = LinkOps(*bound)
        self._ops_cache = (bound, ops)
        return ops

    def _bindings(
        self,
        prove: Callable[[int], None],
        recovery_prove: Callable[[int], None],
        resetting: Callable[[], bool],
    ) -> tuple[Any, ...]:
        """What :class:`LinkOps` binds, in the order of its fields."""
        link = self.link
        port_link = self.port_link
        return (
            self.current_pacer,
            self.guard,
            self.mapping,
            self.unknown_reply_s,
            self.send,
            self.recovery_send,
            port_link.discard_input,
            self.await_reply,
            self.proved,
            link.suspect,
            link.enter,
            self.link_state,
            prove,
            recovery_prove,
            self.request,
            self.run,
            self.measured,
            port_link.can_reset,
            resetting,
        )


__all__ = ["STATE_OPCODES", "Wire"]
