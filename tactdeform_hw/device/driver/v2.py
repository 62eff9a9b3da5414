"""How the device layer speaks firmware v2: one height per electrode, a global waveform mode, the sync check.

:class:`~tactdeform_hw.device.driver.base.Device` is written once; the bytes that express its operations on
v2 are :class:`V2Dialect`'s (the registry :data:`~tactdeform_hw.device.driver.dialects.DIALECTS`; v1.2's are
in :mod:`.v1_2`).  The safety contract is v1.2's, translated:

* **Per-electrode heights.**  ``send_pattern`` still takes levels (0 off, 1 monophasic, 2 biphasic); on v2
  each active electrode's height is the target lowered to *its own* limit (cap, charge, its region) and to
  its own ramp from the height it had — no "lowest limit over the frame".  Every height is clipped on the
  host: the firmware's only clamp is 4095 (40.95 mA).
* **One waveform per frame.**  v2 chooses monophasic or biphasic for the whole scan (0xFB mode 0 or 1), so
  a frame that mixes levels 1 and 2 is refused (:class:`~tactdeform_hw.errors.LimitError` on ``pattern``)
  rather than silently turning monophasic electrodes biphasic.
* **No torn scan: every new pattern is copied under a cover.**  A scan that pre-empts the firmware's copy
  loop would mix old and new heights, and no pacing can keep the copy clear of the scans (the host does not
  see them).  So a pattern that may differ from the one in force goes in one write between ``FB 02`` and
  ``FB mode`` at sense height 0 (:func:`covered_pattern`): a scan that starts inside delivers no current
  (a dropout), every other one runs the old pattern in the old mode or the new one in the new mode.  A
  change of mode is the same write: no scan combines the new mode with the old heights.
* **Off is a zero pattern in mode 0 or 1.**  Mode 2 gives every channel the sense pulse, so a zero pattern
  would not stop current there.  The driver writes mode 2 only while the sense height is 0 and the sense
  width 0 are proved in force (every pulse then has height 0): when the electrode count rises, the channels
  above the old count would otherwise scan the heights an earlier pattern left there (v2 keeps stale
  channels), so mode 2 covers them until the zero pattern of the new length is read, then mode 0 returns.
* **Recovery by the sync check and the 2 s timeout.**  Zeros that complete any command in progress on
  either version, the safe tail (count 0, mode 0, sense 0), then 0xF4: its one-byte reply (the count, 0)
  proves a command boundary and every byte before it read.  No reply means a command was pending (its
  2 s timeout may have discarded the probe): wait until every byte has arrived plus the 2 s timeout, then
  the whole probe again.  Still silent: the board does not answer as v2 must —
  :class:`~tactdeform_hw.device.driver.firmware_probe.FirmwareMismatchError`, after bytes that stop current
  on both
  versions.  Then the electrode count is written and proved by the sync reply's value before any pattern.
* **Pacing for the 1024-byte queue**, once the board has answered the sync check (until then the pacer
  keeps v1.2's 256 bytes: a board that turns out to run v1.2 still reads every byte of the probe).

The interlock (:class:`~tactdeform_hw.device.safety.interlock.WireInterlock`, ``firmware = V2``) reads every
write with the v2 table and checks each channel's own height
(:class:`~tactdeform_hw.device.safety.readings.V2Reading`).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import replace
from typing import TYPE_CHECKING

from tactdeform_hw.device.driver.config import POLARITY_CODE, StimConfig
from tactdeform_hw.device.driver.dialect import (
    DriverState,
    Pace,
    PaceFor,
    Plan,
    PlanBuilder,
    Prove,
    Step,
    Write,
    begin_recovery,
    rehearsal_in_flight,
    timing_before_count,
)
from tactdeform_hw.device.driver.firmware_probe import PROBE, SYNC_CHECK, FirmwareMismatchError
from tactdeform_hw.device.driver.pacing import SCAN_GAP_MIN_US
from tactdeform_hw.device.links.recovery import REPLY_POLL_S, LinkState
from tactdeform_hw.errors import LimitError, ShortReplyError
from tactdeform_hw.protocol.commands import V2_COMMANDS as c2
from tactdeform_hw.protocol.constants import CURRENT_STEP_UA, PATTERN_BIPHASIC, PATTERN_MONOPHASIC
from tactdeform_hw.protocol.firmware import V2
from tactdeform_hw.protocol.firmware_math import estimate_scan_us, firmware_period_us
from tactdeform_hw.protocol.state import BoardState

if TYPE_CHECKING:
    from tactdeform_hw.device.driver.dialect import LinkOps, PaceInForce, PlanContext
    from tactdeform_hw.device.participant.mapping import ChannelMapping
    from tactdeform_hw.device.safety.guard import SafetyGuard
    from tactdeform_hw.protocol.units import CurrentTransfer

#: Margin past the firmware's 2 s command timeout before a pending command is taken as discarded.
TIMEOUT_MARGIN_S = 0.1
#: The firmware's command timeout (v2 discards a command not complete this long after its byte was read).
COMMAND_TIMEOUT_S = (V2.command_timeout_us or 0) / 1e6
_EPS = 1e-6
_ACTIVE = (PATTERN_MONOPHASIC, PATTERN_BIPHASIC)


def mode_for(levels: Sequence[int]) -> int | None:
    """The stimulation mode a frame of levels needs (None: no active electrode)."""
    active = {v for v in levels if v in _ACTIVE}
    if not active:
        return None
    return c2.STIM_MODE_BIPHASIC if PATTERN_BIPHASIC in active else c2.STIM_MODE_MONOPHASIC


def _critical_write(data: bytes) -> Write:
    return Write(data, critical=True)


def _count_write(data: bytes) -> Write:
    """The electrode count: never padded (v1.2's loss-tolerant echo of a count of 0xF4 would be a sync
    check)."""
    return Write(data, pad=False)


def _recovery_write(data: bytes) -> Write:
    """A write of the recovery itself, never padded (a v1.2 padding byte could be a v2 command)."""
    return Write(data, recovery=True, pad=False)


def covered_pattern(
    codes: Sequence[int], mode: int, *, sense_code: int | None, sense_width_us: int | None = None
) -> list[bytes]:
    """The commands that write the pattern ``codes`` under the cover: mode 2 while the firmware copies it,
    at sense height 0, so a scan that pre-empts the copy delivers no current instead of a torn pattern.

    ``[F9 00]``, ``[F8 00]``, ``FB 02``, ``FE codes``, ``FB mode``, ``[F8 width]``, written as one write
    (:meth:`~tactdeform_hw.device.driver.pacing.Pacer.write_commands`).  v2 reads complete commands back
    to back, so mode 2 lasts from the parser reading ``FB 02`` to its reading ``FB mode``: the copy, plus
    whatever part of the write is still crossing the link.  Every scan snapshots its mode when it starts
    and, in mode 2, gives every channel the sense pulse whatever the pattern holds: a scan that starts in
    that window is one without current (a dropout); any other scan runs the old pattern in the old mode or
    the new pattern in the new one, whole.

    Mode 2 is only ever in force at sense height 0 (``sense_code``: the height in force, None unknown): a
    sense height that is not proved 0 is set to 0 before ``FB 02`` and left at 0 — modes 0 and 1 never
    use it, and a height restored behind ``FB mode`` would be a current on every channel whenever that
    ``FB mode`` does not apply (under the loss-tolerant encoding a byte lost inside the pattern makes the
    pattern take ``FB`` as its last byte: :func:`~tactdeform_hw.device.driver.pacing.paddings`).
    ``sense_width_us`` (given when the mode-2 scan at the configured sense width would be longer than the
    frame's scan, which the pacing and the scan-gap check were computed for) zeroes the sense width and
    restores it after ``FB mode`` (a width alone, at height 0, is no current)."""
    pre: list[bytes] = []
    post: list[bytes] = []
    if sense_code != 0:
        pre.append(c2.encode_sense_height(0))
    if sense_width_us:
        pre.append(c2.encode_sense_width(0))
        post.append(c2.encode_sense_width(sense_width_us))
    return [
        *pre,
        c2.encode_stim_mode(c2.STIM_MODE_IMPEDANCE),
        c2.encode_pattern(codes, electrode_num=len(codes)),
        c2.encode_stim_mode(mode),
        *post,
    ]


def off_packet(electrode_count: int) -> bytes:
    """The guardian's stop on v2: bytes that stop current wherever either firmware's parser stands
    (:data:`~tactdeform_hw.device.driver.firmware_probe.PROBE` without its sync check), then 0xF5 for the
    proof
    the guardian reads (one byte on both versions)."""
    del electrode_count  # the count goes to 0: nothing is scanned at all
    return PROBE[:-1] + c2.HV513_COUNT_REQUEST


class V2Dialect:
    """Firmware v2 (see the module docstring); its registers in force are :class:`DriverState`'s ``mode``,
    ``codes``, ``heights_ua``, ``answered`` and ``covers``."""

    firmware = V2
    signature_proves_count = True

    # --- small helpers --------------------------------------------------------------------------------------

    @staticmethod
    def _rsend(ops: LinkOps, data: bytes) -> int:
        """A write of the recovery itself (allowed before the proof; never padded: a v1.2 padding byte
        could be a v2 command); the written offset just past it."""
        return ops.recovery_send(data, pad=False)

    @staticmethod
    def _scan_us(cfg: StimConfig, mode: int | None) -> float:
        """v1.2's firmware-order estimate of a scan with every channel pulsed in ``mode`` (v2 pulses every
        channel, at height 0 when off; its discharge is shorter, so the estimate errs long)."""
        level = PATTERN_BIPHASIC if mode in (None, c2.STIM_MODE_BIPHASIC) else PATTERN_MONOPHASIC
        return estimate_scan_us(
            [level] * cfg.electrode_count, cfg.pulse_width_us, cfg.discharge_us, cfg.sense_width_us
        )

    @staticmethod
    def _app_count(mapping: ChannelMapping | None, n: int) -> int:
        return mapping.electrodes if mapping is not None else n

    def _sync(self, ops: LinkOps, expected: int) -> bool:
        """0xF4 alone at a proved boundary; True when answered with ``expected`` (the count) and nothing
        more (a second answer is a request the board read that the host did not send)."""
        ops.discard_input()
        mark = self._rsend(ops, SYNC_CHECK)
        reply = ops.await_reply(1, whole=True)
        if reply == bytes((expected & 0xFF,)):
            ops.proved(mark)
            ops.guard.note_in_step(expected)  # the reply is the count in force
            return True
        return False

    def _zero_pattern(
        self, b: PlanBuilder, n: int, mapping: ChannelMapping | None, scan_s: float | None
    ) -> None:
        st = b.st
        data = c2.encode_pattern([0] * n, electrode_num=n)
        if st.codes is not None and len(st.codes) == n and not any(st.codes):
            b.add(Write(data, critical=True))  # the same zeros again: no scan can mix two patterns
        else:
            mode = st.mode if st.mode in (c2.STIM_MODE_MONOPHASIC, c2.STIM_MODE_BIPHASIC) else 0
            self._write_covered(b, [0] * n, mode, scan_s)
        st.codes = [0] * n
        st.heights_ua = [0] * self._app_count(mapping, n)
        st.current_ua = 0
        st.last_pattern = bytes(n)

    def _raise_count(
        self,
        b: PlanBuilder,
        n: int,
        write: Callable[[bytes], Write],
        write_count: Callable[[bytes], Write],
        before_count: Sequence[bytes] = (),
    ) -> None:
        """Electrode count ``n`` with no stale channel scanned: sense height 0, mode 2 (every pulse at the
        sense height, 0), sense width 0, the count, its zero pattern, mode 0.  Mode 2 comes right after the
        sense height: from there on no pattern height is scanned at all, so every later command is safe
        whatever the interlock could not know of the registers (after a write it reads as a resync, such
        as the firmware check's zeros, the heights and the mode are unknown to it).  ``write_count`` plans
        the count: never v1.2's loss-tolerant echo of it (a count of 0xF4 would echo a sync check)."""
        st = b.st
        b.add(write(c2.encode_sense_height(0)))
        st.sense_byte = 0
        b.add(write(c2.encode_stim_mode(c2.STIM_MODE_IMPEDANCE)))
        b.add(write(c2.encode_sense_width(0)))
        for data in before_count:  # (a configuration's new rate and widths: no pattern height is scanned)
            b.add(write(data))
        b.add(write_count(c2.encode_electrode_num(n)))
        b.add(write(c2.encode_pattern([0] * n, electrode_num=n)))
        b.add(write(c2.encode_stim_mode(c2.STIM_MODE_MONOPHASIC)))
        st.mode = c2.STIM_MODE_MONOPHASIC
        st.codes = [0] * n
        st.last_pattern = bytes(n)
        st.current_ua = 0

    def _write_covered(self, b: PlanBuilder, codes: Sequence[int], mode: int, scan_s: float | None) -> None:
        """``codes`` and then ``mode`` in force, written under the cover of :func:`covered_pattern` (the
        frame path's only way of changing a pattern that may differ from the one in force); ``scan_s`` is
        the scan the pacer paces for."""
        st = b.st
        cfg = st.config
        wide: int | None = None
        if cfg is not None and cfg.sense_width_us:
            n = len(codes)
            sense_scan = estimate_scan_us(bytes(n), cfg.pulse_width_us, cfg.discharge_us, cfg.sense_width_us)
            if sense_scan > (scan_s or 0.0) * 1e6:
                wide = cfg.sense_width_us  # a sense pulse longer than the frame's: mode 2 at width 0
        cover = covered_pattern(codes, mode, sense_code=st.sense_byte, sense_width_us=wide)
        b.add(Write(commands=tuple(cover), critical=True))
        st.sense_byte = 0  # never restored (see covered_pattern)
        st.codes = list(codes)
        st.mode = mode
        st.covers += 1

    def guardian_stop(self, electrode_count: int) -> bytes:
        return off_packet(electrode_count)

    def guardian_open_stop(self) -> bytes | None:
        # v1.2's stop (a few zeros, then 0xFB 00 00 …) would complete a v2 pattern in progress with 0xFB as
        # a height's high byte (4095): the guardian stops a v2 board with the probe's bytes
        return off_packet(0)

    # --- recovery -------------------------------------------------------------------------------------------

    def frame_commands(self, n: int) -> list[bytes]:
        """More than the longest frame (:meth:`frame`, :meth:`off`): a zero pattern, then a pattern under
        a cover that also zeroes and restores the sense height and width (an upper bound for the bytes a
        frame can leave in flight)."""
        return [
            c2.encode_pattern([0] * n, electrode_num=n),
            # any sense height and width other than 0: the cover zeroes and restores both (the most bytes)
            *covered_pattern([0] * n, c2.STIM_MODE_BIPHASIC, sense_code=1, sense_width_us=1),
        ]

    def resync_bound_now_s(self, ops: LinkOps, st: DriverState) -> float:
        """The longest a failing v2 resync waits at the configuration in force before the reset line (or the
        refusal), computed like v1.2's on a simulated clock with a scratch pacer: behind a frame still in
        flight (a zero pattern, a mode change, a pattern), the probe and its sync reply's deadline, then
        the wait until every byte has arrived plus the firmware's 2 s command timeout and the margin, then
        the probe and its deadline again.  A probe answered in between proves count 0, mode 0 and sense 0
        in force (no current), so no slower failing path leaves the board stimulating longer."""
        _n, clock, scratch = rehearsal_in_flight(ops, st, self.frame_commands, pad=False)

        def written(data: bytes) -> None:
            scratch.write(lambda _chunk: None, data, pad=False)

        def await_reply() -> None:
            period = scratch.period_s if scratch.period_s is not None else ops.unknown_reply_s
            deadline = scratch.drained_by() + 0.003 + scratch.policy.byte_s + period
            clock.advance(max(0.0, deadline - clock.now()) + REPLY_POLL_S)

        written(PROBE)
        await_reply()
        clock.advance(max(0.0, scratch.arrived_by() + COMMAND_TIMEOUT_S + TIMEOUT_MARGIN_S - clock.now()))
        written(PROBE)
        await_reply()
        return clock.now()

    def _probe_until_answered(self, ops: LinkOps, st: DriverState) -> int:
        """SYNCING (→ FLUSHING after the 2 s timeout): the probe until the sync check answers 00; the
        mark of the answered probe.  Silence twice: FAILED, then the reset line (a board that answered as
        v2 before) or the refusal; another answer: FAILED and the refusal."""
        pacer = ops.pacer()
        ops.discard_input()
        ops.enter(LinkState.SYNCING, "zeros, the safe tail and the sync check")
        mark = self._rsend(ops, PROBE)
        reply = ops.await_reply(1)
        if not reply:
            ops.enter(LinkState.FLUSHING, "no sync reply: a command was pending (2 s timeout)")
            pacer.wait_until(pacer.arrived_by() + COMMAND_TIMEOUT_S + TIMEOUT_MARGIN_S)
            ops.discard_input()
            mark = self._rsend(ops, PROBE)  # nothing is pending now; the whole probe again, as at first
            reply = ops.await_reply(1)
            if not reply:
                ops.enter(LinkState.FAILED, "the sync check unanswered after the 2 s timeout")
                ops.guard.mark_unknown()
                if st.answered and ops.can_reset() and not ops.resetting():
                    # a board that answered as v2 before and is silent now is hung (perhaps still
                    # stimulating): the reset line, as on v1.2 (``Device._recover``)
                    raise ShortReplyError(
                        "sync check after the 2 s timeout (parser hung: reset the board)", 1, b""
                    )
                if st.answered:
                    # silent even after the reset line (or with none to pulse): not another firmware — the
                    # board that answered as v2 in this session no longer answers at all
                    raise ShortReplyError(
                        "sync check after the 2 s timeout (the board answered as v2 before and is silent "
                        "now: hung or unplugged)",
                        1,
                        b"",
                    )
                raise FirmwareMismatchError(
                    "the board does not answer the sync check 0xF4 as firmware v2 must (twice, the "
                    "second time more than 2 s after any command could have started): it runs v1.2, or "
                    "its parser is hung; only bytes that stop current on both versions were sent"
                )
        if reply != b"\x00":
            ops.enter(LinkState.FAILED, f"sync check answered {reply.hex()}, not 00")
            raise FirmwareMismatchError(
                f"the sync check after electrode count 0 was answered {reply.hex()}, not 00: the board "
                "did not read the bytes as firmware v2 does"
            )
        return mark

    def flush_parser(self, ops: LinkOps, st: DriverState) -> None:
        """SUSPECT → SYNCING (→ FLUSHING after the 2 s timeout) → SAFE → VERIFYING → IN_STEP, on v2."""
        cfg, n = begin_recovery(ops, st, self.resync_bound_now_s)
        pacer = ops.pacer()
        st.mode = st.codes = None
        for attempt in (1, 2):
            if ops.link_state() is not LinkState.SUSPECT:
                ops.enter(LinkState.SUSPECT, f"recovery attempt {attempt}")
            mark = self._probe_until_answered(ops, st)
            ops.proved(mark)
            ops.guard.note_in_step(0)
            st.answered = True
            # v2 answered: from now on pace for its parser and 1024-byte queue (until then, for v1.2's
            # 256 bytes and tick per command: a board that turns out to run v1.2 must read the whole probe)
            pacer.policy = replace(pacer.policy, firmware=V2, queue_bytes=V2.rx_queue_bytes)
            ops.enter(LinkState.SAFE, "sync answered 00: command boundary, count 0, mode 0, sense 0")
            st.current_ua = 0
            st.sense_byte = 0
            st.last_pattern = None
            st.mode = c2.STIM_MODE_MONOPHASIC
            st.codes = []
            if cfg is None:
                ops.enter(LinkState.IN_STEP, "count 0; no electrode count to prove")
                return
            b = PlanBuilder(st)
            self._raise_count(b, n, _recovery_write, _recovery_write)
            ops.run(b.done(), st)
            ops.enter(LinkState.VERIFYING, f"electrode count {n} written")
            if self._sync(ops, n):
                ops.enter(LinkState.IN_STEP, f"sync check answered the count {n}")
                break
            if attempt == 2:
                ops.enter(LinkState.FAILED, f"sync check did not answer the count {n}")
                raise ShortReplyError("sync check after resync", 1, b"")
            ops.enter(LinkState.SUSPECT, f"sync check did not answer the count {n}")
        assert cfg is not None
        st.heights_ua = [0] * self._app_count(ops.mapping, n)
        st.scan_us = self._scan_us(cfg, st.mode)
        pacer.set_timing(firmware_period_us(cfg.rate_hz) / 1e6, st.scan_us / 1e6)

    def prove(self, ops: LinkOps, electrodes: int) -> None:
        """In step: the sync check; its reply must be the count (one byte): every byte before it read."""
        if not self._sync(ops, electrodes):
            ops.suspect("the sync check did not answer the count")
            raise ShortReplyError("sync check (proof that the queue was read)", 1, b"")

    # --- configuration --------------------------------------------------------------------------------------

    def validated(self, config: StimConfig, transfer: CurrentTransfer) -> StimConfig:
        """v1.2's checks, except the sense current: v2 stores 0xF9 unshifted, so any DAC code up to 255."""
        checked = replace(config, sense_current_ua=0).validated(transfer)
        code = transfer.to_code(config.sense_current_ua, "sense_current_ua")
        top = V2.value_max("sense_pulse_height")
        if code > top:
            raise LimitError(
                "sense_current_ua",
                config.sense_current_ua,
                f"a DAC code of at most {top} on firmware v2 (0xF9 is stored unshifted; this one is {code})",
            )
        return replace(checked, sense_current_ua=transfer.check_current(config.sense_current_ua))

    def check_idle_scan(self, guard: SafetyGuard, config: StimConfig) -> None:
        """v2 checks its scan once the caller's frame is superseded (:meth:`check_configuration`)."""

    def check_configuration(self, guard: SafetyGuard, config: StimConfig) -> None:
        """v2 pulses every channel in every scan (an off one at height 0): a configuration whose
        monophasic scan fills the period starves the parser whatever the pattern, so it is refused before
        any byte."""
        guard.check_scan(
            self._scan_us(config, c2.STIM_MODE_MONOPHASIC),
            firmware_period_us(config.rate_hz),
            SCAN_GAP_MIN_US,
        )

    def configure(self, ctx: PlanContext, st: DriverState, config: StimConfig, pace: PaceInForce) -> Plan:
        """Everything off first (zero pattern), the count raised without stale channels, mode 0, polarity
        while all is off, widths and rate, then a proof by the sync check.  A count that rises goes after
        the rate, polarity and widths (:func:`~.dialect.timing_before_count`): its longer scan never meets
        the old period."""
        old = st.config
        new_period = firmware_period_us(config.rate_hz)
        timings = [(new_period, self._scan_us(config, None))]
        if old is not None:
            timings.append((firmware_period_us(old.rate_hz), self._scan_us(old, None)))
        elif pace.period_s is not None and pace.scan_s is not None:
            timings.append((pace.period_s * 1e6, pace.scan_s * 1e6))
        b = PlanBuilder(st)
        st = b.st
        b.add(PaceFor(tuple(timings)))
        in_force = old.electrode_count if old is not None else (len(st.codes) if st.codes is not None else 0)
        if in_force and any(st.codes or [1]):
            mode = st.mode if st.mode in (c2.STIM_MODE_MONOPHASIC, c2.STIM_MODE_BIPHASIC) else 0
            self._write_covered(b, [0] * in_force, mode, pace.slowest(timings)[1] / 1e6)
            b.add(Prove(in_force))  # a long pattern: proved read before the next one
        n = config.electrode_count
        timing_first = timing_before_count(old, config)
        # a rising count: rate and widths before it, once mode 2 holds every pulse at sense height 0
        timing = self._rate_and_widths(config, old, after_count=False) if timing_first else []
        self._raise_count(b, n, Write, _count_write, timing)
        b.add(Prove(n))
        if timing_first:
            b.add(Write(c2.encode_polarity(POLARITY_CODE[config.polarity])))  # all is off: mode 0, zeros
            b.add(Write(c2.encode_sense_width(config.sense_width_us)))  # the count's raise set it to 0
        else:
            for data in self._rate_and_widths(config, old, after_count=True):
                b.add(Write(data))
        sense = ctx.transfer.to_code(config.sense_current_ua, "sense_current_ua")
        b.add(Write(c2.encode_sense_height(sense)))  # used only in mode 2, which never runs with heights
        st.sense_byte = sense
        st.config = config
        st.target_ua = config.current_ua
        st.current_ua = 0
        st.heights_ua = [0] * self._app_count(ctx.mapping, n)
        st.requested = None
        st.suspended = False
        st.scan_us = self._scan_us(config, None)
        b.add(Pace((timings[-1][0] / 1e6, max(t[1] for t in timings) / 1e6)))
        b.add(Prove(n))
        b.add(Pace((new_period / 1e6, st.scan_us / 1e6)))
        return b.done()

    @staticmethod
    def _rate_and_widths(config: StimConfig, old: StimConfig | None, *, after_count: bool) -> list[bytes]:
        """Rate (a longer period first, a shorter one last), polarity and widths.  Written after the count,
        except when the count rises (:func:`~.dialect.timing_before_count`): then rate, pulse width and
        discharge go before it, under mode 2, so the longer scan meets the new period rather than the old;
        polarity (no scan's length depends on it) and the sense width (the raise holds it at 0) follow the
        count, once the zero pattern and mode 0 are in force."""
        new_period = firmware_period_us(config.rate_hz)
        longer = old is None or new_period >= firmware_period_us(old.rate_hz)
        out = [c2.encode_frequency(config.rate_hz)] if longer else []
        if after_count:
            out.append(c2.encode_polarity(POLARITY_CODE[config.polarity]))
        out.append(c2.encode_pulse_width(config.pulse_width_us))  # >= 1: a width of 0 would still pulse
        if after_count:
            out.append(c2.encode_sense_width(config.sense_width_us))
        out.append(c2.encode_discharge(config.discharge_us))
        if not longer:
            out.append(c2.encode_frequency(config.rate_hz))
        return out

    # --- frames ---------------------------------------------------------------------------------------------

    def heights_in_force(self, st: DriverState, mapping: ChannelMapping | None) -> list[int] | None:
        """The DAC codes in force in application order (None: unknown)."""
        if st.codes is None:
            return None
        if mapping is None:
            return list(st.codes)
        return [st.codes[ch] if ch < len(st.codes) else 0 for ch in mapping.app_to_hw]

    def check_levels(self, levels: Sequence[int]) -> None:
        active = {v for v in levels if v in _ACTIVE}
        if len(active) > 1:
            raise LimitError(
                "pattern",
                list(levels),
                "one waveform per frame on firmware v2 (its mode is global): every active electrode 1 "
                "(monophasic) or every one 2 (biphasic)",
            )

    def heights_for(self, ctx: PlanContext, st: DriverState, levels: Sequence[int]) -> list[int]:
        """Each application electrode's height (µA): the target lowered to its own limit and ramp."""
        cfg = st.config
        assert cfg is not None
        guard = ctx.guard
        n = len(levels)
        active = [v in _ACTIVE for v in levels]
        if any(active) and guard.positions_matter:
            guard.require_positions(n)
        base = guard.base_limit_ua(cfg.pulse_width_us)
        limits = guard.electrode_limits(n)
        prev = st.heights_ua if len(st.heights_ua) == n else [0] * n
        target = st.target_ua
        ramp = guard.ramp_ua_per_frame
        robust = ctx.robust
        out: list[int] = []
        clipped: list[tuple[int, int]] = []
        ramped: list[tuple[int, int]] = []
        for i in range(n):
            if not active[i]:
                out.append(0)
                continue
            h = min(target, base, limits[i])
            h -= h % CURRENT_STEP_UA
            if h < target:
                clipped.append((i, h))
            if ramp is not None and h > prev[i] + ramp:
                h = prev[i] + ramp
                ramped.append((i, h))
            if robust:
                while h > 0 and (ctx.transfer.to_code(h) & 0xFF) >= V2.command_byte_min:
                    h -= CURRENT_STEP_UA
            out.append(max(0, h))
        for rule, rows, why in (
            ("electrode_limit", clipped, "their own limits"),
            ("ramp", ramped, f"the ramp of {ramp} µA per frame"),
        ):
            if rows:
                guard.note_electrode_clips(
                    rule,
                    f"{len(rows)} electrode(s) lowered from {target} µA to {why} "
                    f"({', '.join(f'{i}: {h}' for i, h in rows[:8])}{' …' if len(rows) > 8 else ''} µA)",
                    requested_ua=target,
                    sent_ua=max(h for _, h in rows),
                    electrodes=[i for i, _ in rows],
                )
        return out

    def frame(self, ctx: PlanContext, st: DriverState, levels: Sequence[int], *, force_pattern: bool) -> Plan:
        """A pattern that may differ from the one in force under the cover (:func:`covered_pattern`), the
        same heights again when ``force_pattern``.  A change of mode restarts the ramp from 0, and that
        holds even when the guard then refuses the frame."""
        cfg = st.config
        assert cfg is not None
        self.check_levels(levels)
        b = PlanBuilder(st)
        st = b.st
        want = mode_for(levels)
        mode = st.mode if want is None and st.mode in (0, 1) else (want if want is not None else 0)
        if mode != st.mode:
            st.heights_ua = []  # after a mode change the ramp starts from 0
        try:
            heights = self.heights_for(ctx, st, levels)
            n = cfg.electrode_count
            codes = [0] * n
            app_to_hw = ctx.mapping.app_to_hw if ctx.mapping is not None else range(n)
            for i, ch in enumerate(app_to_hw):
                if ch < n:
                    codes[ch] = ctx.transfer.to_code(heights[i])
            period = firmware_period_us(cfg.rate_hz)
            scan = self._scan_us(cfg, mode)
            ctx.guard.check_scan(scan, period, SCAN_GAP_MIN_US)
        except Exception as refusal:
            return b.refused(refusal)
        before = st.scan_us if st.scan_us is not None else self._scan_us(cfg, None)
        paced = (period / 1e6, max(before, scan) / 1e6)
        if mode != st.mode or codes != st.codes:
            # a scan that pre-empts the copy would mix the two patterns (or run the new heights in the old
            # mode): mode 2 at sense height 0 covers the copy, and the new mode follows it
            self._write_covered(b, codes, mode, paced[1])
            st.frames_sent += 1
        elif force_pattern:
            if ctx.robust and any(codes):
                # a byte lost from a pattern written alone would shift its heights into the mode in force
                self._write_covered(b, codes, mode, paced[1])
            else:
                b.add(Write(c2.encode_pattern(codes, electrode_num=n), critical=True))  # the same heights
            st.frames_sent += 1
        st.heights_ua = heights
        st.last_pattern = ctx.mapping.to_hardware(levels) if ctx.mapping is not None else bytes(levels)
        st.current_ua = max(heights, default=0)
        st.suspended = False
        st.scan_us = scan
        plan = b.done((period / 1e6, scan / 1e6))
        plan.pace_before = paced
        return plan

    def off(self, st: DriverState, mapping: ChannelMapping | None, scan_s: float | None) -> Plan:
        """Every height 0 (mode 0 or 1 stays: a zero pattern there is no current)."""
        cfg = st.config
        assert cfg is not None
        n = cfg.electrode_count
        b = PlanBuilder(st)
        if b.st.mode not in (c2.STIM_MODE_MONOPHASIC, c2.STIM_MODE_BIPHASIC):
            b.add(Write(c2.encode_electrode_num(0), critical=True))  # mode unknown: nothing scanned at all
            b.add(Write(c2.encode_stim_mode(c2.STIM_MODE_MONOPHASIC), critical=True))
            b.st.mode = c2.STIM_MODE_MONOPHASIC
            self._raise_count(b, n, _critical_write, _count_write)
        self._zero_pattern(b, n, mapping, scan_s)
        b.st.scan_us = self._scan_us(cfg, b.st.mode)
        return b.done((firmware_period_us(cfg.rate_hz) / 1e6, b.st.scan_us / 1e6))

    def prove_stopped(self, ops: LinkOps, st: DriverState) -> None:
        """``close``'s proof on v2: electrode count 0, then the sync check must answer 00.  The sync reply
        to the count in force proves only that every byte was read — a corrupted pattern command byte
        turns the all-off into unknown bytes and the old heights go on — while the value 00 proves that
        nothing is scanned at all, whatever became of the pattern."""
        self._rsend(ops, c2.encode_electrode_num(0))
        if not self._sync(ops, 0):
            ops.suspect("the sync check did not answer count 0 after the all-off")
            raise ShortReplyError("sync check after the close's electrode count 0", 1, b"")
        st.codes = []

    def refresh(self, ctx: PlanContext, st: DriverState, *, sense: bool) -> Plan:
        """The mode and the pattern of heights again (``sense`` has no meaning here: v2 uses the sense
        height only in mode 2).  Under the loss-tolerant encoding heights in force go under the cover
        (:func:`covered_pattern`, twice): a byte lost from a pattern written alone would shift its heights
        into the mode in force."""
        cfg = st.config
        assert cfg is not None
        n = cfg.electrode_count
        codes = st.codes if st.codes is not None and len(st.codes) == n else [0] * n
        if ctx.robust and any(codes) and st.mode in (c2.STIM_MODE_MONOPHASIC, c2.STIM_MODE_BIPHASIC):
            b = PlanBuilder(st)
            self._write_covered(b, codes, st.mode, st.scan_us / 1e6 if st.scan_us is not None else None)
            return b.done()
        # the mode again (a mode byte mis-read as 2 gives every channel the sense pulse, whatever the
        # pattern) and the pattern again.  Zeros go first: the board's pattern may not be the one the host
        # believes (a byte lost inside a covered pattern leaves its shifted heights under mode 2, and the
        # cover's closing mode unapplied), and a mode 0 or 1 read before the zeros would deliver them.
        mode: list[Step] = [Write(c2.encode_stim_mode(st.mode))] if st.mode is not None else []
        pattern: list[Step] = [Write(c2.encode_pattern(codes, electrode_num=n))]
        return Plan(pattern + mode if not any(codes) else mode + pattern)

    def set_current(self, ctx: PlanContext, st: DriverState, levels: list[int] | None) -> Plan:
        """The target changed: the frame in force follows (each electrode to its own limit and ramp)."""
        if levels is None:
            return Plan()
        return self.frame(ctx, st, levels, force_pattern=False)


def buffer_levels(state: BoardState) -> list[int]:
    """The levels a board's pattern buffer stands for, from its register snapshot: v1.2 holds the levels
    themselves; v2 (a state with ``stim_mode``) holds heights, read back as 0 (no current) or the
    waveform its mode gives every other channel (1 monophasic, 2 biphasic)."""
    pattern = [int(v) for v in state.stim_pattern]
    mode = state.stim_mode
    if mode is None:
        return pattern
    level = PATTERN_BIPHASIC if mode == c2.STIM_MODE_BIPHASIC else PATTERN_MONOPHASIC
    return [level if v else 0 for v in pattern]
