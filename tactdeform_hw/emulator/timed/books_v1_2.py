"""The v1.2 timed model's books: what each command did and when it was felt, what was lost, the scans'
records and hazards.

:class:`~.model_v1_2.TimedEmulator` runs the firmware (deliveries, the main loop's calls, the scans);
these mixins keep its books from what it runs: :class:`CommandBooks` follows each command from the
host's bytes to its first felt pulse and every loss to the command read next, :class:`ScanBooks`
records scan runs, stretches of repeated hazards and torn patterns, and forgets old records.  They are
mixins of the one model (the same object), split out so that neither file is the whole model.
"""

from __future__ import annotations

from bisect import bisect_right
from dataclasses import dataclass, field
from operator import attrgetter
from typing import Any

from tactdeform_hw.emulator.firmware.hazards import Hazard, HazardKind
from tactdeform_hw.emulator.firmware.parser import Parser
from tactdeform_hw.emulator.firmware.registers import Registers
from tactdeform_hw.emulator.firmware.scan import PulseKind, ScanConfig, ScanTemplate
from tactdeform_hw.emulator.records.reports import (
    ChannelLatency,
    CommandReport,
    LossReport,
    ScanRun,
    TornInfo,
)
from tactdeform_hw.emulator.timed.link import ReceiveQueue, Scheduled
from tactdeform_hw.protocol.constants import Opcode
from tactdeform_hw.protocol.decoder import StreamDecoder

_PATTERN = int(Opcode.PATTERN)

#: a u16 completed this long after the main loop began spinning on its first byte is reported
U16_LATE_US = 2000.0
# which pulses a command affects (None: any pulse)
AFFECTS: dict[int, tuple[int, ...] | None] = {
    Opcode.PULSE_HEIGHT: (PulseKind.MONO, PulseKind.BI_ANODIC, PulseKind.BI_CATHODIC),
    Opcode.PULSE_WIDTH: (PulseKind.MONO, PulseKind.BI_ANODIC, PulseKind.BI_CATHODIC),
    Opcode.SENSE_HEIGHT: (PulseKind.SENSE,),
    Opcode.SENSE_WIDTH: (PulseKind.SENSE,),
    Opcode.POLARITY: None,
    Opcode.DISCHARGE: None,
    Opcode.ELECTRODE_NUM: None,
    Opcode.FREQUENCY: None,
    Opcode.HV513_COUNT: None,
}


@dataclass
class PendingEffect:
    """A command whose first affected pulse is still to come."""

    report: CommandReport
    kinds: tuple[int, ...] | None
    after_ns: int
    channels: dict[int, ChannelLatency] | None = None  # patterns: unresolved channels


@dataclass
class MainLoop:
    """The firmware's main loop and timer bookkeeping, as the board holds it (reset at every boot)."""

    parser_base: int = 0  # device-stream offset of the parser's byte 0 since the last boot
    booting_until: int = 0  # bytes arriving before this are lost
    tick_base: int = 0  # RTOS tick 0
    last_reload: int = 0  # when the timer last reloaded
    main_next: float | None = None  # when the main loop next calls the parser
    main_wait: str | None = None  # what it waits for otherwise (_WAIT_*)
    call: tuple[int, int] | None = None  # (cpu ns spent, bytes read) of an interrupted call
    held: bytes = b""  # an interrupted call's bytes: read (out of the queue), not yet stored or acted on
    init_edges: int | None = None  # an interrupted hv513Init(): the CLK rising edges it has made so far
    call_lead: bool = True  # the interrupted call began by reading a command byte (see call_reads_ns)
    checking: bool = False  # ``call`` goes on at its payload loop's next Serial.available() check
    # a scan pre-empted a call's last Serial.available() check: this much of the check is left when the loop
    # resumes, then vTaskDelay(1) (its tick counted from there, after the scan)
    check_left_ns: int | None = None
    # when the firmware's read of each byte the last parser call took from the queue begins (ns, ascending):
    # the model takes a call's bytes at its start, the firmware reads them one at a time, so a byte arriving
    # up to its read still finds it in the receive queue
    read_starts: list[int] = field(default_factory=list)
    ticks_before_call: int = 0  # the alarm register when the call being fed began
    # 0xF6's new alarm when the scan its call let in came before setPeriodUs(): written once the loop resumes
    period_pending: int | None = None
    busy_from: int = -1  # the scan in progress: the main loop does not run inside it
    busy_until: int = -1
    stuck_reported: bool = False  # spinning on a half u16: reported once, from stuck_at
    stuck_at: int | None = None
    # the spin on a half u16: when its first Serial.available() began, and the scans' time since (the
    # spin runs in the main loop's time, one check after another)
    spin_from: int = 0
    spin_scanned_ns: int = 0
    call_end_ns: int = 0  # when the call being fed ends, and the device offset of its last byte
    call_dev_last: int = 0


@dataclass
class HostLedger:
    """What the host wrote and what reached the device: the books that map device bytes back to the
    host's stream and its send times (not firmware state: a reboot keeps them)."""

    decoder: StreamDecoder
    offset: int = 0  # bytes the host has written
    last_write_ns: int = 0
    writes: list[tuple[int, int, int]] = field(default_factory=list)  # (host offset, length, sent ns)
    write_starts: list[int] = field(default_factory=list)
    intended: dict[int, tuple[int, int]] = field(default_factory=dict)  # host offset -> (opcode, end offset)
    intended_starts: list[int] = field(default_factory=list)
    deliveries: list[tuple[int, int, Scheduled]] = field(default_factory=list)  # heap: bytes on their way in
    seq: int = 0
    # heap: replies on their way out
    tx_deliveries: list[tuple[int, int, Scheduled]] = field(default_factory=list)
    rx: bytearray = field(default_factory=bytearray)  # replies that reached the host, unread
    dev_total: int = 0  # device stream: accepted bytes, session-wide offsets
    seg_dev: list[int] = field(default_factory=list)
    # (dev start, host start, length, delivered ns)
    segments: list[tuple[int, int, int, int]] = field(default_factory=list)


@dataclass
class Records:
    """What the reports are made of: scan runs, command and loss reports, the reply log, trace sinks."""

    runs: list[ScanRun] = field(default_factory=list)
    commands: list[CommandReport] = field(default_factory=list)
    losses: list[LossReport] = field(default_factory=list)
    open_losses: list[LossReport] = field(default_factory=list)  # not followed by a command in step yet
    awaiting: list[PendingEffect] = field(default_factory=list)
    sinks: list[Any] = field(default_factory=list)
    tx_log: list[tuple[float, bytes]] = field(default_factory=list)  # (device write µs, bytes)
    scan_index: int = 0
    sense_key: tuple[Any, ...] | None = None
    # per stretch kind: (index in hazards, what must stay the same) of the record a stretch extends
    stretch: dict[HazardKind, tuple[int, tuple[Any, ...]]] = field(default_factory=dict)
    reboots: int = 0
    interrupted_calls: int = 0  # parser calls an alarm interrupted mid-read
    cur: CommandReport | None = None  # the command being read, and for a pattern its channels' times
    cur_written: dict[int, int] = field(default_factory=dict)
    cur_first: dict[int, int] = field(default_factory=dict)  # channels a scan used while still being read
    cur_old: bytes = b""
    last_rep: CommandReport | None = None


_channel_of = attrgetter("channel")


def ns_of(us: float) -> int:
    return int(round(us * 1000.0))


def us_of(ns: int | None) -> float | None:
    return None if ns is None else ns / 1000.0


class _ModelState:
    """What the books read of the model they belong to (set by :class:`~.model_v1_2.TimedEmulator`)."""

    fw: MainLoop
    hazards: list[Hazard]
    host: HostLedger
    queue: ReceiveQueue
    rec: Records
    next_alarm: float
    now_ns: int

    @property
    def registers(self) -> Registers:
        raise NotImplementedError

    @property
    def parser(self) -> Parser:
        raise NotImplementedError

    def parser_status(self) -> str:
        raise NotImplementedError

    def _retime_alarm(self, t: int, by_call: bool = False) -> None:
        raise NotImplementedError

    def _mark(self, t: int, kind: str, detail: dict[str, Any]) -> None:
        raise NotImplementedError


class CommandBooks(_ModelState):
    """Each command from the host's bytes to its first felt pulse; each loss to what the parser read
    next."""

    def arrival_us(self, host_offset: int) -> float | None:
        """When the host's byte at ``host_offset`` reached the receive queue (``None``: lost, or not yet
        arrived) — whether or not the parser ever reads it."""
        for _, host, length, t in reversed(self.host.segments):
            if host >= 0 and host <= host_offset < host + length:
                return t / 1000
        return None

    def intended_offsets(self) -> list[int]:
        """Host offsets of the commands the host's byte stream holds (decoded the way the firmware reads)."""
        return list(self.host.intended_starts)

    def _loss(self, t: int, data: bytes, host_offset: int, reason: str) -> None:
        state = self.parser_status()
        rep = LossReport(
            t / 1000,
            host_offset,
            len(data),
            bytes(data),
            reason,
            len(self.queue),
            state,
            self._cut_command(host_offset),
        )
        self.rec.losses.append(rep)
        if reason == "queue_full":
            self.hazards.append(
                Hazard(
                    HazardKind.QUEUE_OVERFLOW,
                    self.host.dev_total - self.fw.parser_base,
                    {"bytes_lost": len(data), "host_offset": host_offset, "parser": state},
                    t / 1000,
                )
            )
            self.rec.open_losses.append(rep)
        self._mark(t, "loss", {"bytes": len(data), "host_offset": host_offset, "reason": reason})

    def _cut_command(self, host_offset: int) -> dict[str, Any] | None:
        if host_offset < 0:
            return None
        i = bisect_right(self.host.intended_starts, host_offset) - 1
        if i < 0:
            return None
        start = self.host.intended_starts[i]
        op, end = self.host.intended[start]
        if host_offset >= end or host_offset == start:
            return (
                None
                if host_offset >= end
                else {
                    "name": Opcode(op).name,
                    "host_offset": start,
                    "bytes_before_loss": 0,
                    "length": end - start,
                }
            )
        return {
            "name": Opcode(op).name,
            "host_offset": start,
            "bytes_before_loss": host_offset - start,
            "length": end - start,
        }

    def _meant_as_command(self, parser_offset: int) -> bool:
        """Whether the host wrote a command byte at this parser offset (a byte that did not come from the
        host counts as meant: nothing says otherwise)."""
        host = self._host_of(self.fw.parser_base + parser_offset)
        return host < 0 or host in self.host.intended

    def _host_of(self, dev_offset: int) -> int:
        """Host-stream offset of a device-stream byte (-1 if it did not come from the host)."""
        i = bisect_right(self.host.seg_dev, dev_offset) - 1
        if i < 0:
            return -1
        start, host, length, _ = self.host.segments[i]
        if host < 0 or dev_offset >= start + length:
            return -1
        return host + dev_offset - start

    def _delivered_at(self, dev_offset: int) -> int | None:
        i = bisect_right(self.host.seg_dev, dev_offset) - 1
        return None if i < 0 else self.host.segments[i][3]

    def _sent_at(self, host_offset: int) -> int | None:
        if host_offset < 0:
            return None
        i = bisect_right(self.host.write_starts, host_offset) - 1
        return None if i < 0 else self.host.writes[i][2]

    def _on_command(self, op: int, value: object, offset: int) -> None:
        t = self.fw.call_end_ns
        rep = self.rec.cur
        if rep is None or rep.opcode != op:  # pragma: no cover - every completion was started by _feed
            host = self._host_of(self.fw.parser_base + offset)
            rep = CommandReport(self.fw.parser_base + offset, host, op, Opcode(op).name)
        self.rec.cur = None
        self.rec.last_rep = rep
        rep.effect_us = t / 1000
        if op == _PATTERN:
            rep.value = bytes(self.registers.stim_pattern[: len(self.rec.cur_written)])
        else:
            rep.value = value
        last_dev = self.fw.call_dev_last
        # the last byte's segment, once for both questions (:meth:`_delivered_at`, :meth:`_host_of`)
        i = bisect_right(self.host.seg_dev, last_dev) - 1
        if i < 0:
            rep.arrival_us = us_of(None)
            last_host = -1
        else:
            start, host, length, arr = self.host.segments[i]
            rep.arrival_us = us_of(arr)
            last_host = -1 if host < 0 or last_dev >= start + length else host + last_dev - start
        # in step with the host?  same opcode at the same host offset, ending where the host's ended
        intended = self.host.intended.get(rep.host_offset)
        rep.host_end = last_host + 1 if last_host >= 0 else -1
        rep.in_sync = bool(intended and intended[0] == op and intended[1] == last_host + 1)
        self.rec.commands.append(rep)
        if self.fw.stuck_at is not None:
            self._late_u16(op, t)
        if self.rec.sinks:  # (the marker's detail is made only for a sink to receive)
            self._mark(
                t,
                "command",
                {
                    "name": rep.name,
                    "value": list(rep.value) if isinstance(rep.value, bytes) else rep.value,
                    "host_offset": rep.host_offset,
                    "in_sync": rep.in_sync,
                },
            )
        self._follow_losses(rep)
        if op == Opcode.FREQUENCY and value:
            self._retime_alarm(t, by_call=True)
        if op == _PATTERN:
            chans = {ch: ChannelLatency(ch, wt / 1000) for ch, wt in self.rec.cur_written.items()}
            cur_first = self.rec.cur_first
            felt = {ch: chans.pop(ch) for ch in list(chans) if ch in cur_first} if cur_first else {}
            for ch, cl in felt.items():
                cl.first_pulse_us = self.rec.cur_first[ch] / 1000
            self.rec.cur_first = {}
            # an older pattern still waiting for these channels will never be felt there
            for pend in self.rec.awaiting:
                if pend.channels:
                    for ch in chans:
                        if ch in pend.channels:
                            pend.channels.pop(ch).note = "overwritten before its next pulse"
            rep.channels = sorted([*chans.values(), *felt.values()], key=_channel_of)
            if felt:
                rep.first_pulse_us = min(
                    cl.first_pulse_us for cl in felt.values() if cl.first_pulse_us is not None
                )
            self.rec.awaiting.append(PendingEffect(rep, None, t, chans))
        elif op in AFFECTS:
            for pend in self.rec.awaiting:
                if pend.channels is None and pend.report.opcode == op:
                    pend.report.note = "superseded before it was felt"
            self.rec.awaiting = [
                a for a in self.rec.awaiting if not (a.channels is None and a.report.opcode == op)
            ]
            self.rec.awaiting.append(PendingEffect(rep, AFFECTS[op], t))
        self.rec.cur_written = {}

    def _late_u16(self, op: int, t: int) -> None:
        """A u16 whose first byte waited longer than ``U16_LATE_US`` for its second: whatever the host
        meant, the main loop spun meanwhile and the value is made of bytes written far apart."""
        gap = t - self.fw.stuck_at if self.fw.stuck_at is not None else 0
        self.fw.stuck_at = None
        if gap <= ns_of(U16_LATE_US):
            return
        from tactdeform_hw.emulator.firmware.parser import register_after

        field, stored = register_after(op, self.registers)
        rep = self.rec.last_rep
        self.hazards.append(
            Hazard(
                HazardKind.U16_COMPLETED_LATE,
                rep.device_offset - self.fw.parser_base if rep else -1,
                {
                    "command": Opcode(op).name,
                    "value": rep.value if rep else None,
                    "gap_us": gap / 1000,
                    "register": field,
                    "stored": stored,
                },
                t / 1000,
            )
        )

    def _follow_losses(self, rep: CommandReport) -> None:
        if not self.rec.open_losses:
            return
        entry = {
            "name": rep.name,
            "value": list(rep.value) if isinstance(rep.value, bytes) else rep.value,
            "host_offset": rep.host_offset,
            "in_sync": rep.in_sync,
            "time_us": rep.effect_us,
        }
        still = []
        for lo in self.rec.open_losses:
            if lo.host_offset >= 0 and 0 <= rep.host_end <= lo.host_offset:
                still.append(lo)  # read from bytes sent before the loss: not a consequence of it
                continue
            if rep.in_sync and rep.host_offset >= lo.host_offset + lo.count:
                lo.resync_host_offset = rep.host_offset
                lo.resync_us = rep.effect_us
                continue
            lo.followed.append(entry)
            if len(lo.followed) < 16:
                still.append(lo)
        self.rec.open_losses = still

    def _resolve(self, ta: int, tmpl: ScanTemplate, cut: int | None = None) -> None:
        """First pulses: every command waiting to be felt that this scan makes felt (and the channels of a
        pattern still being read that this scan already uses)."""
        n = tmpl.config.electrode_num
        onsets: list[int] = []  # each channel's first onset, as ints when a channel asks
        if self.rec.cur_written and self.rec.cur is not None and self.rec.cur.opcode == _PATTERN:
            onsets = tmpl.first_pulse_ns.tolist()
            for ch in self.rec.cur_written:
                if ch < n and ch not in self.rec.cur_first:
                    t = onsets[ch]
                    if cut is None or t < cut:
                        self.rec.cur_first[ch] = ta + t
        if not self.rec.awaiting:
            return
        keep: list[PendingEffect] = []
        for pend in self.rec.awaiting:
            if pend.after_ns > ta:
                keep.append(pend)
                continue
            if pend.channels is not None:
                done = []
                if pend.channels and not onsets:
                    onsets = tmpl.first_pulse_ns.tolist()
                for ch, cl in pend.channels.items():
                    if ch < n:
                        t = onsets[ch]
                        if cut is None or t < cut:
                            cl.first_pulse_us = (ta + t) / 1000
                            done.append(ch)
                for ch in done:
                    del pend.channels[ch]
                firsts = [c.first_pulse_us for c in pend.report.channels if c.first_pulse_us is not None]
                if firsts:
                    pend.report.first_pulse_us = min(firsts)
                if pend.channels:
                    keep.append(pend)
            else:
                first = tmpl.first_of(pend.kinds)
                if first is not None and (cut is None or first < cut):
                    pend.report.first_pulse_us = (ta + first) / 1000
                elif (
                    pend.report.opcode in (Opcode.FREQUENCY, Opcode.ELECTRODE_NUM, Opcode.HV513_COUNT)
                    and first is None
                ):
                    pend.report.first_pulse_us = None
                    pend.report.note = pend.report.note or f"first scan at {ta / 1000:.1f} us has no pulse"
                else:
                    keep.append(pend)
        self.rec.awaiting = keep


class ScanBooks(_ModelState):
    """Scan runs, stretches of repeated hazards, torn patterns and trace markers; forgetting old
    records."""

    def discard_history(self, before_us: float) -> None:
        """Forget records older than ``before_us`` that nothing pending refers to (scan runs, command
        and loss reports, reply log, write and arrival books), so a device served for hours keeps a
        bounded memory.  Reports afterwards cover the time kept."""
        t = ns_of(before_us)
        self.rec.runs = [r for r in self.rec.runs if r.end_ns >= t]
        pending = {id(p.report) for p in self.rec.awaiting}
        self.rec.commands = [
            c for c in self.rec.commands if id(c) in pending or c.effect_us is None or c.effect_us * 1000 >= t
        ]
        self.rec.tx_log = [e for e in self.rec.tx_log if e[0] * 1000 >= t]
        opened = {id(lo) for lo in self.rec.open_losses}
        self.rec.losses = [lo for lo in self.rec.losses if id(lo) in opened or lo.time_us * 1000 >= t]
        p = self.parser
        dev_keep = self.fw.parser_base + (p.cmd_offset if p.cmd is not None else p.offset)
        keep_seg = [
            i for i, seg in enumerate(self.host.segments) if seg[0] + seg[2] > dev_keep or seg[3] >= t
        ]
        if keep_seg and keep_seg[0] > 0:
            first = keep_seg[0]
            self.host.segments = self.host.segments[first:]
            self.host.seg_dev = self.host.seg_dev[first:]
        elif not keep_seg:
            self.host.segments, self.host.seg_dev = [], []
        hosts = [seg[1] for seg in self.host.segments if seg[1] >= 0]
        hosts += [d[2].host_offset for d in self.host.deliveries if d[2].host_offset >= 0]
        hosts += [lo.host_offset for lo in self.rec.open_losses if lo.host_offset >= 0]
        if self.rec.cur is not None and self.rec.cur.host_offset >= 0:
            hosts.append(self.rec.cur.host_offset)
        host_keep = min(hosts, default=self.host.offset)
        i = bisect_right(self.host.intended_starts, host_keep) - 1
        if i > 0:
            for off in self.host.intended_starts[:i]:
                self.host.intended.pop(off, None)
            self.host.intended_starts = self.host.intended_starts[i:]
        j = bisect_right(self.host.write_starts, host_keep) - 1
        if j > 0:
            self.host.writes = self.host.writes[j:]
            self.host.write_starts = self.host.write_starts[j:]

    def attach(self, sink: Any) -> None:
        """Send every scan run and marker from now on to ``sink`` (see :mod:`.trace`)."""
        self.rec.sinks.append(sink)
        if hasattr(sink, "begin"):
            sink.begin(self.now_ns)

    def detach(self, sink: Any) -> None:
        if sink in self.rec.sinks:
            self.rec.sinks.remove(sink)

    def _torn_info(self, n: int) -> TornInfo | None:
        p = self.parser
        if p.cmd != _PATTERN or p.locked or not (0 < p.count < p.needed) or self.rec.cur is None:
            return None
        regs = self.registers
        k = min(p.count, n)
        changed = sum(
            1
            for i in range(k)
            if regs.stim_pattern[i] != (self.rec.cur_old[i] if i < len(self.rec.cur_old) else 0)
        )
        return TornInfo(self.rec.cur.device_offset, self.rec.cur.host_offset, p.count, n, changed)

    def _stretch_hazard(self, hazard: Hazard, same: tuple[Any, ...]) -> None:
        """Record ``hazard`` (its detail has ``first_cycle`` and ``cycles``), or extend the record of the
        same kind it continues: the next cycles, with ``same`` unchanged.  One record per stretch keeps the
        list short when the condition lasts (a starved main loop never ends it)."""
        hz = self.hazards
        last = self.rec.stretch.get(hazard.kind)
        if last is not None and last[0] < len(hz) and last[1] == same:
            prev = hz[last[0]]
            if (
                prev.kind == hazard.kind
                and prev.detail["first_cycle"] + prev.detail["cycles"] == hazard.detail["first_cycle"]
            ):
                hz[last[0]] = Hazard(
                    prev.kind,
                    prev.offset,
                    {**prev.detail, "cycles": prev.detail["cycles"] + hazard.detail["cycles"]},
                    prev.time_us,
                )
                return
        self.rec.stretch[hazard.kind] = (len(hz), same)
        hz.append(hazard)

    def _torn_hazard(self, run: ScanRun) -> None:
        """A ``torn_pattern`` record for a run of torn scans: which channels the scan took from the pattern
        being read, and the values that changed there (``[channel, old, new]``).  The rest kept their old
        values (the new ones have not arrived)."""
        torn = run.torn
        if torn is None or self.rec.cur is None:
            return
        new = self.registers.stim_pattern
        old = self.rec.cur_old
        k = min(torn.new_channels, torn.electrode_num)
        changed = [
            [ch, old[ch] if ch < len(old) else 0, new[ch]]
            for ch in range(k)
            if new[ch] != (old[ch] if ch < len(old) else 0)
        ]
        offset = torn.command_device_offset - self.fw.parser_base
        detail = {
            "first_cycle": run.first_index,
            "cycles": run.count,
            "cycle_start_us": run.start_ns / 1000,
            "command_host_offset": torn.command_host_offset,
            "new_channels": k,
            "old_channels": torn.electrode_num - k,
            "changed": changed,
        }
        self._stretch_hazard(
            Hazard(HazardKind.TORN_PATTERN, offset, detail, run.start_ns / 1000),
            (offset, k, torn.electrode_num),
        )

    def _record(self, run: ScanRun) -> None:
        self.rec.runs.append(run)
        self.rec.scan_index += run.count
        for s in self.rec.sinks:
            s.scan_run(run)

    def _check_sense(self, cfg: ScanConfig) -> None:
        if not cfg.sense_pulse_height or not cfg.electrode_num:
            self.rec.sense_key = None
            return
        chans = tuple(i for i, v in enumerate(cfg.pattern) if v not in (1, 2))
        key = (cfg.sense_pulse_height, cfg.sense_pulse_width, chans)
        if chans and key != self.rec.sense_key:
            self.rec.sense_key = key
            self.hazards.append(
                Hazard(
                    HazardKind.SENSE_CURRENT,
                    self.parser.offset,
                    {
                        "channels": list(chans),
                        "sense_pulse_height": cfg.sense_pulse_height,
                        "sense_pulse_width": cfg.sense_pulse_width,
                    },
                    self.next_alarm / 1000,
                )
            )

    def _mark(self, t: int, kind: str, detail: dict[str, Any]) -> None:
        for s in self.rec.sinks:
            s.marker(t, kind, detail)
