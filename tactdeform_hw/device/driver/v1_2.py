"""How the device layer speaks firmware v1.2: one pulse height per scan, levels in the pattern buffer.

The height of each frame is the target lowered to the frame's lowest limit (see :mod:`..safety`); when it
goes down it is written before the pattern, when it goes up after it, so no scan — not even one torn
between the old and the new pattern — combines a pattern with a height that is too high for it.

Recovery (:meth:`V12Dialect.flush_parser`): zeros that complete any u8 or u16 in progress, then a request
whose reply of the expected length proves a command boundary and the queue read; then heights 0, the
electrode count, and 0xFF whose reply length proves the count before any pattern.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import TYPE_CHECKING

from tactdeform_hw import protocol as p
from tactdeform_hw.device.driver.config import POLARITY_CODE, StimConfig, sense_code
from tactdeform_hw.device.driver.dialect import (
    DriverState,
    Note,
    PaceFor,
    Plan,
    PlanBuilder,
    Prove,
    Settle,
    Step,
    Write,
    begin_recovery,
    count_raise_timing,
    rehearsal_in_flight,
    scan_of,
    timing_before_count,
    worst_scan_s,
)
from tactdeform_hw.device.driver.pacing import COMMAND_BYTE_MIN, SCAN_GAP_MIN_US, firmware_period_us
from tactdeform_hw.device.driver.readback import OFF_READING_CODES
from tactdeform_hw.device.links.recovery import (
    PROBE_LEAD_ZEROS,
    RECOVERY_ATTEMPTS,
    REPLY_POLL_S,
    REPLY_TAIL_S,
    LinkState,
)
from tactdeform_hw.device.participant.mapping import ChannelMapping
from tactdeform_hw.device.safety.guard import SafetyGuard
from tactdeform_hw.device.safety.guardian import off_packet
from tactdeform_hw.errors import NotStoppedError, ShortReplyError
from tactdeform_hw.protocol.constants import CURRENT_STEP_UA, RX_QUEUE_SIZE
from tactdeform_hw.protocol.firmware import V1_2
from tactdeform_hw.protocol.units import CurrentTransfer

if TYPE_CHECKING:
    from tactdeform_hw.device.driver.dialect import LinkOps, PaceInForce, PlanContext


#: Why :func:`encodable` lowers a height (the guard's record of the clip).
ENCODING_CLIP = "pulse-height code whose low byte looks like a command byte"


def encodable_height(ctx: PlanContext, height_ua: int) -> int:
    """Under robust encoding no payload byte may look like a command byte: the height lowered so that
    none does (unrecorded; :func:`encodable` records the clip)."""
    if not ctx.robust or height_ua <= 0:
        return height_ua
    h = height_ua
    while h > 0 and (ctx.transfer.to_code(h) & 0xFF) >= COMMAND_BYTE_MIN:
        h -= CURRENT_STEP_UA
    return h


def encodable(ctx: PlanContext, height_ua: int) -> int:
    """:func:`encodable_height`, the clip recorded by the guard."""
    h = encodable_height(ctx, height_ua)
    if h != height_ua:
        ctx.guard.note_clip("encoding", height_ua, h, ENCODING_CLIP)
    return h


class V12Dialect:
    """Firmware v1.2 (see the module docstring)."""

    firmware = V1_2
    signature_proves_count = False

    # --- configuration --------------------------------------------------------------------------------------

    def validated(self, config: StimConfig, transfer: CurrentTransfer) -> StimConfig:
        return config.validated(transfer)

    def check_idle_scan(self, guard: SafetyGuard, config: StimConfig) -> None:
        # v1.2 gives every channel the pattern has off a sense pulse and a discharge: a configuration whose
        # all-off scan fills the period starves the parser (it could not even read an all-off), so it is
        # refused before any byte
        n = config.electrode_count
        guard.check_scan(scan_of(config, bytes(n)), firmware_period_us(config.rate_hz), SCAN_GAP_MIN_US)

    def check_levels(self, levels: Sequence[int]) -> None:
        """Every valid level is expressible on v1.2."""

    def check_configuration(self, guard: SafetyGuard, config: StimConfig) -> None:
        """v1.2 refuses its idle scan before the caller's frame is superseded (:meth:`check_idle_scan`)."""

    def configure(self, ctx: PlanContext, st: DriverState, config: StimConfig, pace: PaceInForce) -> Plan:
        """The height to 0 and every channel off first (no pulse uses a mixture of old and new settings),
        the electrode count followed at once by an all-off pattern of the new length (no stale channel
        above the old count comes back), polarity while all is off, the participant's current last.  A
        count that rises goes after the rate and widths, so its longer scan never meets the old period
        (:func:`~.dialect.timing_before_count`)."""
        n = config.electrode_count
        old = st.config
        new_period = firmware_period_us(config.rate_hz)
        idle_scan = scan_of(config, bytes(n))
        # until the new rate and widths are read, the old ones run: pace for the slower of the two
        timings = [(new_period, idle_scan)]
        if old is not None:
            before = st.scan_us if st.scan_us is not None else worst_scan_s(old) * 1e6
            timings.append(
                (firmware_period_us(old.rate_hz), max(before, scan_of(old, bytes(old.electrode_count))))
            )
        elif pace.period_s is not None and pace.scan_s is not None:
            timings.append((pace.period_s * 1e6, pace.scan_s * 1e6))  # from the resync
        # nothing known of the firmware's timing (a board just opened): the queue was proved empty and the
        # configuration fits it (a long pattern waits for a proof first); the new rate is proved in force
        # before anything else is paced by it
        unknown_timing = old is None and (pace.period_s is None or pace.scan_s is None)
        b = PlanBuilder(st)
        b.add(PaceFor(tuple(timings)))
        self._write_configuration(b, ctx, config, unknown_timing)
        st = b.st
        target = ctx.guard.frame_height(
            None, config.current_ua, 0, config.pulse_width_us, raise_when_idle=True
        )
        height = encodable_height(ctx, target)
        if height != target:
            b.add(Note("encoding", target, height, ENCODING_CLIP))
        b.add(Write(p.encode_pulse_height(ctx.transfer.to_code(height))))
        st.config = config
        st.current_ua = height
        st.target_ua = config.current_ua
        st.requested = None
        st.suspended = False
        st.scan_us = idle_scan
        # a faster pace for the new timing only once the device proves it has read every command above
        b.add(Settle((new_period / 1e6, idle_scan / 1e6), n, always=unknown_timing))
        return b.done()

    def _write_configuration(
        self, b: PlanBuilder, ctx: PlanContext, config: StimConfig, unknown_timing: bool
    ) -> None:
        """Everything but the participant's current, in the order :meth:`configure` gives."""
        st = b.st
        n = config.electrode_count
        old = st.config
        in_force = [old.electrode_count if old is not None else 0]

        def send(data: bytes) -> None:
            if unknown_timing and data[0] == p.Opcode.PATTERN:
                b.add(
                    Prove(in_force[0], unless_room_for=len(data))
                )  # a long pattern: into a queue proved empty
            b.add(Write(data))
            if data[0] == p.Opcode.ELECTRODE_NUM:
                in_force[0] = data[1]

        send(p.encode_pulse_height(0))
        st.current_ua = 0
        if old is not None:
            send(p.encode_pattern(bytes(old.electrode_count)))
        send(p.encode_sense_height(0))
        st.sense_byte = 0
        timing_first = timing_before_count(old, config)
        if timing_first:
            self._write_timing(send, config, old)
        send(p.encode_electrode_num(n))
        if timing_first:
            # behind the raised count, until its all-off pattern is read, the new count's longest scan runs
            b.add(PaceFor((count_raise_timing(config),), with_current=True))
        send(p.encode_pattern(bytes(n)))
        st.last_pattern = bytes(n)
        if not timing_first:
            self._write_timing(send, config, old)
        send(p.encode_sense_height(sense_code(config.sense_current_ua, ctx.transfer)))
        st.sense_byte = sense_code(config.sense_current_ua, ctx.transfer)

    @staticmethod
    def _write_timing(send: Callable[[bytes], None], config: StimConfig, old: StimConfig | None) -> None:
        """Rate, polarity and widths.  A longer period goes first and a shorter one last, so no scan of the
        new widths meets the old, shorter period (the board's own period is unknown after opening or a
        reset: 10 ms at power-on)."""
        longer = old is None or firmware_period_us(config.rate_hz) >= firmware_period_us(old.rate_hz)
        if longer:
            send(p.encode_frequency(config.rate_hz))
        send(p.encode_polarity(POLARITY_CODE[config.polarity]))
        send(p.encode_pulse_width(config.pulse_width_us))
        send(p.encode_sense_width(config.sense_width_us))
        send(p.encode_discharge(config.discharge_us))
        if not longer:
            send(p.encode_frequency(config.rate_hz))

    # --- frames ---------------------------------------------------------------------------------------------

    def frame(self, ctx: PlanContext, st: DriverState, levels: Sequence[int], *, force_pattern: bool) -> Plan:
        """Height down first, pattern, height up last; the sense height likewise."""
        cfg = st.config
        assert cfg is not None
        height = self._frame_height(ctx, st, levels, raise_when_idle=False)
        hw = ctx.mapping.to_hardware(levels) if ctx.mapping is not None else bytes(levels)
        period = firmware_period_us(cfg.rate_hz)
        scan = scan_of(cfg, hw)
        ctx.guard.check_scan(scan, period, SCAN_GAP_MIN_US)
        before = st.scan_us if st.scan_us is not None else worst_scan_s(cfg) * 1e6
        # each write puts its own fields in force (spelled out: every frame is planned here)
        sense = sense_code(cfg.sense_current_ua, ctx.transfer)  # an all-off stop set it to 0
        sense_byte = st.sense_byte
        current_ua = st.current_ua
        writes: list[Step] = []
        if sense_byte is None or sense < sense_byte:
            writes.append(Write(p.encode_sense_height(sense), critical=True, puts={"sense_byte": sense}))
            sense_byte = sense
        if height < current_ua:
            data = p.encode_pulse_height(ctx.transfer.to_code(height))
            writes.append(Write(data, critical=True, puts={"current_ua": height}))
            current_ua = height
        if force_pattern or hw != st.last_pattern:
            data = p.encode_pattern(hw, electrode_num=cfg.electrode_count)
            puts = {"last_pattern": hw, "frames_sent": st.frames_sent + 1}
            writes.append(Write(data, critical=True, puts=puts))
        if height > current_ua:
            data = p.encode_pulse_height(ctx.transfer.to_code(height))
            writes.append(Write(data, critical=True, puts={"current_ua": height}))
        if sense > sense_byte:
            writes.append(Write(p.encode_sense_height(sense), critical=True, puts={"sense_byte": sense}))
        done = {"suspended": False, "scan_us": scan}
        if writes:
            writes[-1].puts.update(done)
            done = {}
        return Plan(
            writes,
            done,
            pace_after=(period / 1e6, scan / 1e6),
            pace_before=(period / 1e6, max(before, scan) / 1e6),
        )

    @staticmethod
    def _frame_height(
        ctx: PlanContext, st: DriverState, levels: Sequence[int] | None, *, raise_when_idle: bool
    ) -> int:
        """The height of the frame ``levels``: the target lowered to its lowest limit and ramp, and to a
        code the encoding can carry."""
        cfg = st.config
        assert cfg is not None
        return encodable(
            ctx,
            ctx.guard.frame_height(
                levels, st.target_ua, st.current_ua, cfg.pulse_width_us, raise_when_idle=raise_when_idle
            ),
        )

    def set_current(self, ctx: PlanContext, st: DriverState, levels: list[int] | None) -> Plan:
        cfg = st.config
        assert cfg is not None
        height = self._frame_height(ctx, st, levels, raise_when_idle=True)
        if height == st.current_ua:
            return Plan()
        return Plan(
            [
                Write(
                    p.encode_pulse_height(ctx.transfer.to_code(height)),
                    critical=True,
                    puts={"current_ua": height},
                )
            ]
        )

    def off(self, st: DriverState, mapping: ChannelMapping | None, scan_s: float | None) -> Plan:
        cfg = st.config
        assert cfg is not None
        n = cfg.electrode_count
        scan_us = scan_of(cfg, bytes(n))
        return Plan(
            [
                Write(p.encode_pattern(bytes(n)), critical=True),
                Write(
                    p.encode_pulse_height(0), critical=True, puts={"last_pattern": bytes(n), "current_ua": 0}
                ),
                # the sense pulse is a current too, and a fault may have set it whatever the host believes
                Write(p.encode_sense_height(0), critical=True, puts={"sense_byte": 0, "scan_us": scan_us}),
            ],
            pace_after=(firmware_period_us(cfg.rate_hz) / 1e6, scan_us / 1e6),
        )

    def refresh(self, ctx: PlanContext, st: DriverState, *, sense: bool) -> Plan:
        transfer = ctx.transfer
        cfg = st.config
        assert cfg is not None
        pattern = st.last_pattern if st.last_pattern is not None else bytes(cfg.electrode_count)
        writes: list[Step] = []
        if sense and st.sense_byte is not None:
            writes.append(Write(p.encode_sense_height(st.sense_byte)))
        writes.append(Write(p.encode_pulse_height(transfer.to_code(st.current_ua))))
        writes.append(Write(p.encode_pattern(pattern, electrode_num=cfg.electrode_count)))
        return Plan(writes)

    def heights_in_force(self, st: DriverState, mapping: ChannelMapping | None) -> list[int] | None:
        return None

    def guardian_stop(self, electrode_count: int) -> bytes:
        return off_packet(electrode_count)

    def guardian_open_stop(self) -> bytes | None:
        return None  # the guardian's own default is v1.2's stop

    # --- recovery -------------------------------------------------------------------------------------------

    def prove(self, ops: LinkOps, electrodes: int) -> None:
        """0xFF when the firmware's electrode count is ``electrodes`` >= 1 (cheap, and its length proves the
        count too), else 0xF5 (about a millisecond of board detection)."""
        if electrodes >= 1:
            request, size, what = p.MEASURE_REQUEST, 2 * electrodes, "measure"
        else:
            request, size, what = p.HV513_COUNT_REQUEST, 1, "hv513 count"
        ops.request(request, size, f"{what} (proof that the queue was read)")

    def flush_parser(self, ops: LinkOps, st: DriverState) -> None:
        """SUSPECT → SYNCING (→ FLUSHING) → SAFE → VERIFYING → IN_STEP.

        * SYNCING: four zeros (they complete any u8 or u16 in progress, so the request after them is read
          as a command, or — by a pattern in progress — as one more level), then 0xFF when the firmware
          should hold the configuration's electrode count, else 0xF5.  A reply of the expected length
          proves the parser read the request as a command and every byte written before it.
        * FLUSHING: no such reply: 256 zeros finish any pattern in progress, then the request again (and
          0xF5 after a silent 0xFF, as a zero may have set the count to 0).  Still silent: FAILED, a locked
          or hung parser that only the reset line reaches.
        * SAFE: pulse height 0, sense height 0 and the electrode count, each with the loss-tolerant
          padding so that one lost byte still cannot make a current.
        * VERIFYING: 0xFF must be answered with exactly 2 × electrode count bytes; then an all-off pattern.
          Otherwise one more round, then FAILED.

        Time alone never proves anything here: each deadline only decides when to stop waiting."""
        cfg, n = begin_recovery(ops, st, self.resync_bound_now_s)
        for attempt in range(1, RECOVERY_ATTEMPTS + 1):
            if ops.link_state() is not LinkState.SUSPECT:
                ops.enter(LinkState.SUSPECT, f"recovery attempt {attempt}")
            ops.discard_input()
            self._sync(ops, 0 if st.after_reset else n)
            st.after_reset = False
            ops.enter(LinkState.SAFE, "answered: command boundary, queue drained")
            ops.recovery_send(p.encode_pulse_height(0), pad=True)
            st.current_ua = 0
            ops.recovery_send(p.encode_sense_height(0), pad=True)
            st.sense_byte = 0
            st.last_pattern = None
            if cfg is None:
                ops.enter(LinkState.IN_STEP, "heights 0; no electrode count to prove")
                return
            ops.recovery_send(p.encode_electrode_num(n), pad=True)
            ops.enter(LinkState.VERIFYING, f"electrode count {n} written")
            ops.discard_input()
            # the padding above ends every command before it
            mark = ops.recovery_send(p.MEASURE_REQUEST, pad=True)
            reply = ops.await_reply(2 * n, whole=True)
            if len(reply) == 2 * n:
                ops.proved(mark)
                ops.enter(LinkState.IN_STEP, f"0xFF answered with {2 * n} bytes")
                break
            if attempt == RECOVERY_ATTEMPTS:
                ops.enter(LinkState.FAILED, f"0xFF answered with {len(reply)} of {2 * n} bytes")
                raise ShortReplyError("measure after resync", 2 * n, reply)
            ops.enter(LinkState.SUSPECT, f"0xFF answered with {len(reply)} of {2 * n} bytes")
        assert cfg is not None
        ops.send(p.encode_pattern(bytes(n)))
        st.last_pattern = bytes(n)
        st.scan_us = scan_of(cfg, bytes(n))
        ops.pacer().set_timing(firmware_period_us(cfg.rate_hz) / 1e6, st.scan_us / 1e6)

    def _sync(self, ops: LinkOps, electrodes: int) -> None:
        """SYNCING, then FLUSHING if need be; returns in SAFE's entry condition or raises (FAILED)."""
        ops.enter(LinkState.SYNCING, "zeros and a request")
        if electrodes >= 1:
            first = ops.recovery_send(bytes(PROBE_LEAD_ZEROS) + p.MEASURE_REQUEST, pad=True)
            if len(ops.await_reply(2 * electrodes, whole=True)) == 2 * electrodes:
                ops.proved(first)
                return
            ops.discard_input()
            why = "0xFF unanswered or answered short"
        else:
            first = ops.recovery_send(bytes(PROBE_LEAD_ZEROS) + p.HV513_COUNT_REQUEST, pad=True)
            if ops.await_reply(1):
                ops.proved(first)
                return
            why = "0xF5 unanswered"
        ops.enter(LinkState.FLUSHING, why)
        if electrodes >= 1:
            # 0xFF again: cheap, and its length proves the count
            ops.recovery_send(bytes(RX_QUEUE_SIZE) + p.MEASURE_REQUEST, pad=True)
            reply = ops.await_reply(2 * electrodes, whole=True)
            if len(reply) == 2 * electrodes:
                ops.proved(first)
                return
            if reply:  # answered, but not for this electrode count: SAFE writes the count, VERIFY checks it
                ops.proved(first)
                ops.discard_input()
                return
            # silence: a hung or locked parser — or a zero that landed as electrode count 0 (0xFF then
            # answers nothing; nothing is scanned either).  Only 0xF5 tells them apart, at a millisecond
            # of board detection spread over the gaps between scans; with a reset line at hand, the
            # reset comes first instead (a hung board may be stimulating)
            if ops.can_reset() and not ops.resetting():
                ops.enter(LinkState.FAILED, f"0xFF unanswered after {RX_QUEUE_SIZE + PROBE_LEAD_ZEROS} zeros")
                raise ShortReplyError(
                    "0xFF after resync zeros (parser locked or hung: reset the board)", 2 * electrodes, b""
                )
            lead = PROBE_LEAD_ZEROS
        else:
            lead = RX_QUEUE_SIZE
        ops.recovery_send(bytes(lead) + p.HV513_COUNT_REQUEST, pad=True)
        if ops.await_reply(1):
            # some 0xF5 of this recovery was read as a command, so every byte before the first one was
            # read; the other may still answer (a stale byte the next request discards)
            ops.proved(first)
            return
        ops.enter(LinkState.FAILED, f"unanswered after {RX_QUEUE_SIZE + PROBE_LEAD_ZEROS} zeros")
        raise ShortReplyError("0xF5 after resync zeros (parser locked or hung: reset the board)", 1, b"")

    def resync_bound_now_s(self, ops: LinkOps, st: DriverState) -> float:
        """The request behind the zeros, then 256 zeros and the request again (and 0xF5 after 0xFF), each
        until its deadline, behind one frame still in flight; on a simulated clock with a scratch pacer."""
        n, clock, scratch = rehearsal_in_flight(ops, st, self.frame_commands, pad=None)
        request, reply = (p.MEASURE_REQUEST, 2 * n) if n else (p.HV513_COUNT_REQUEST, 1)
        steps = [(bytes(PROBE_LEAD_ZEROS) + request, reply), (bytes(RX_QUEUE_SIZE) + request, reply)]
        if n and not ops.can_reset():
            steps.append((bytes(PROBE_LEAD_ZEROS) + p.HV513_COUNT_REQUEST, 1))
        for data, size in steps:
            scratch.write(lambda _chunk: None, data)
            period = scratch.period_s if scratch.period_s is not None else ops.unknown_reply_s
            deadline = scratch.drained_by() + 0.003 + size * scratch.policy.byte_s + period
            # the deadline, or a reply by it and the listening for more (REPLY_TAIL_S)
            clock.advance(deadline - clock.now() + REPLY_POLL_S + REPLY_TAIL_S + 2 * scratch.policy.byte_s)
        return clock.now()

    def frame_commands(self, n: int) -> list[bytes]:
        height = p.encode_pulse_height(0)
        return [height, p.encode_pattern(bytes(n), electrode_num=n), height]

    def prove_stopped(self, ops: LinkOps, st: DriverState) -> None:
        """Every byte read (the proof), then — a whole period and scan later, when every channel's last
        pulse is the all-off's — each channel's reading at (almost) 0.  The reply's length proves only
        that the bytes were read: a duplicated 0xF9 turns ``F9 00`` into a sense height of 0xF9 (about
        10 mA on every channel), and nothing but the readings shows it."""
        cfg = st.config
        n = cfg.electrode_count if cfg is not None else 0
        ops.prove(n)
        if cfg is None or n == 0:
            return
        pacer = ops.pacer()
        scan_s = st.scan_us / 1e6 if st.scan_us is not None else worst_scan_s(cfg)
        pacer.wait_until(pacer.drained_by() + firmware_period_us(cfg.rate_hz) / 1e6 + scan_s)
        volts = ops.measured(n, "measure (the all-off's readings)")
        live = [ch for ch, v in enumerate(volts) if v > OFF_READING_CODES]
        if live:
            ops.suspect("a channel reads current after the all-off")
            raise NotStoppedError(
                f"after the all-off, channel(s) {', '.join(map(str, live[:8]))}"
                f"{' …' if len(live) > 8 else ''} still read current (above {OFF_READING_CODES} ADC codes)"
            )


__all__ = ["V12Dialect", "encodable"]
