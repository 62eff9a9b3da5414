"""A per-cycle analytic engine for long runs, and the scenarios both fidelities run on.

The event-exact engine (:class:`~.timed.TimedEmulator`) follows every parser call, byte and scan.  This
engine computes the same quantities from closed forms, one host command and one stretch of identical scans
at a time:

* **scans** — the duration of a configuration's scan is the closed form of :mod:`.scan` (exactly the
  event engine's), the alarms follow the overrun policy, and a stretch of scans is a
  (start, stride, count) triple;
* **commands** — the host's byte stream is decoded as the firmware reads it; each command takes effect at
  the first main-loop wake after its last byte arrives (the next RTOS tick, or at once after a reply),
  pushed past a scan that covers it, plus the call's cost; a scan that lands inside the call delays the
  effect by its duration; effects are applied with the firmware's own parser;
* **first pulses** — the first scan after a pattern's effect, plus each channel's closed-form offset.

What it leaves out, on purpose (these are its errors against the event engine): the receive queue and its
losses, a pattern read across several calls (its byte costs are charged in one call), torn scans, the
interrupt watchdog (reported, not simulated), and the u16 spin.  A third fidelity, ``nominal``, is the
arithmetic a paper does by hand — ``width + discharge`` per channel, commands effective on arrival — kept
to show what the exact models are worth.

:class:`Scenario` is a host's writes over time; :func:`run_event_exact`, :func:`run_analytic` and
:func:`run_nominal` all turn one into a comparable :class:`~.reports.Timeline`.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from tactdeform_hw.emulator.core import Emulator
from tactdeform_hw.emulator.firmware.models import entry_part
from tactdeform_hw.emulator.firmware.registers import Registers
from tactdeform_hw.emulator.firmware.scan import ScanConfig, channel_offsets_ns, scan_duration_ns
from tactdeform_hw.emulator.records.reports import Timeline
from tactdeform_hw.emulator.timed.link import LinkModel, make_link
from tactdeform_hw.emulator.timed.model_v1_2 import TimedEmulator, call_reads_ns
from tactdeform_hw.emulator.timed.timing import DEFAULT_MODEL, TimingModel
from tactdeform_hw.errors import ConfigurationError
from tactdeform_hw.protocol.constants import OUTPUTS_PER_HV513, Opcode
from tactdeform_hw.protocol.decoder import StreamDecoder
from tactdeform_hw.protocol.firmware import V1_2

_SIZE = V1_2.size_table()


@dataclass
class Scenario:
    """Host writes ``(t_us, bytes)`` in time order, run for ``duration_us`` over ``link``."""

    name: str
    writes: list[tuple[float, bytes]]
    duration_us: float
    link: str = "usb"
    board: str = "compact"
    switching_boards: int = 1
    model: TimingModel = field(default_factory=lambda: DEFAULT_MODEL)

    def __post_init__(self) -> None:
        last = -1.0
        for t, _ in self.writes:
            if t < last:
                raise ConfigurationError(
                    f"scenario {self.name!r}: writes must be in time order ({t} after {last})"
                )
            last = t
        if not self.duration_us > 0:
            raise ConfigurationError(f"scenario {self.name!r}: duration_us must be > 0")


def run_event_exact(scenario: Scenario) -> tuple[Timeline, TimedEmulator]:
    """The scenario on the event-exact engine."""
    t0 = time.perf_counter()
    emu = TimedEmulator(scenario.board, scenario.switching_boards, link=scenario.link, model=scenario.model)
    for t, data in scenario.writes:
        if t > emu.now_us:
            emu.advance_to(t)
        emu.write(data, t)
    emu.advance_to(scenario.duration_us)
    wall = time.perf_counter() - t0
    tl = emu.reports.timeline("event-exact")
    tl.wall_s = wall
    return tl, emu


@dataclass
class _Run:
    start: int
    stride: int
    count: int
    duration: int


class _Analytic:
    def __init__(self, scenario: Scenario, nominal: bool) -> None:
        self.sc = scenario
        self.m = scenario.model
        self.nominal = nominal
        self.emu = Emulator(scenario.board, scenario.switching_boards)
        self.runs: list[_Run] = []
        self.position = 0
        self.notes: list[str] = []
        self.firsts: dict[int, dict[int, int]] = {}
        self.pending: list[tuple[int, int]] = []  # (host offset, channels) of patterns not felt yet
        self._reconfigure(first=True)

    # --- the scan schedule ---------------------------------------------------------------------------------

    def _duration(self, cfg: ScanConfig, position: int) -> int:
        if not self.nominal:
            return scan_duration_ns(cfg, self.m, position)
        k = cfg.kinds()
        per = (
            np.array([cfg.pulse_width, 2 * cfg.pulse_width, cfg.sense_pulse_width], dtype=np.int64)
            + cfg.discharge_time
        )
        return int(per[k].sum()) * 1000 if k.size else 0

    def _offsets(self, cfg: ScanConfig) -> np.ndarray:
        if not self.nominal:
            return channel_offsets_ns(cfg, self.m)[1]
        k = cfg.kinds()
        per = (
            np.array([cfg.pulse_width, 2 * cfg.pulse_width, cfg.sense_pulse_width], dtype=np.int64)
            + cfg.discharge_time
        )
        return (
            (np.concatenate(([0], np.cumsum(per[k])[:-1])) * 1000) if k.size else np.zeros(0, dtype=np.int64)
        )

    def _reconfigure(self, first: bool = False) -> None:
        regs = entry_part(self.emu.registers, Registers)  # the analytic model is v1.2's
        self.cfg = ScanConfig.from_registers(regs)
        self.period = self.m.alarm_period_ns(regs.timer_alarm_ticks)
        self.target = OUTPUTS_PER_HV513 * self.cfg.hv513_num
        self.d_steady = self._duration(self.cfg, self.target)
        if first:
            self.last_reload = self.m.timer_start_ns
            self.next_alarm = self.last_reload + self.period
            self.last_end = -1
        wd = self.m.watchdog_ns
        if wd is not None and self.d_steady > wd and "watchdog" not in " ".join(self.notes):
            self.notes.append(
                "a scan exceeds the interrupt watchdog: the analytic engine does not simulate the reboot"
            )

    def _stride(self, d: int) -> int:
        if self.m.overrun_policy == "immediate" or self.period == 0:
            return max(self.period, d)
        return self.period * max(1, -(-d // self.period))

    def _emit(self, start: int, stride: int, count: int, d: int) -> None:
        if self.pending:
            offs = self._offsets(self.cfg)
            for off, nch in self.pending:
                self.firsts[off] = dict(enumerate((start + offs[:nch]).tolist()))
            self.pending.clear()
        runs = self.runs
        if (
            runs
            and runs[-1].stride == stride
            and runs[-1].duration == d
            and runs[-1].start + runs[-1].count * stride == start
        ):
            runs[-1].count += count
        else:
            runs.append(_Run(start, stride, count, d))

    def scans_until(self, t: int) -> None:
        """Emit every scan whose alarm is at or before ``t``."""
        while self.next_alarm <= t:
            d = self._duration(self.cfg, self.position) if self.cfg.electrode_num == 0 else self.d_steady
            stride = self._stride(d)
            if self.cfg.electrode_num == 0 and self.position != self.target:
                count = 1
            else:
                count = (t - self.next_alarm) // stride + 1
            self._emit(self.next_alarm, stride, count, d)
            last = self.next_alarm + (count - 1) * stride
            self.last_reload = last
            self.last_end = last + d
            self.position = self.target
            self.next_alarm = last + stride

    def place(self, t: int) -> int | None:
        """When a main-loop call wanted at ``t`` really happens (after any scan that covers it)."""
        for _ in range(4):
            self.scans_until(t)
            if t < self.last_end:
                if self.last_end >= self.next_alarm:
                    return None  # back-to-back scans: the main loop never runs
                t = self.last_end
                continue
            return t
        return t

    # --- ticks ---------------------------------------------------------------------------------------------

    def tick_at_or_after(self, t: int) -> int:
        base = self.m.tick_phase_ns
        tick = self.m.rtos_tick_ns
        if t <= base:
            return base
        return base + -(-(t - base) // tick) * tick

    def _idle_poll(self, first: int, a: int, ready: int) -> int:
        """The idle loop's poll that reads a command whose first byte arrives at ``first`` and last at
        ``a``: the first tick at or after ``a``, or the end of the scan under way at ``first`` when a tick
        the loop polls at (from ``ready``) falls inside that scan -- the poll runs as the scan returns
        (``TimedEmulator``'s idle wait) and its call reads the bytes as they arrive."""
        self.scans_until(first)
        start, end = self.last_reload, self.last_end
        if start <= first <= end and self.tick_at_or_after(max(start, ready)) < end:
            return max(end, a - self.m.call_ns)  # (a call cannot read a byte before it arrives)
        return self.tick_at_or_after(a)

    def _last_check(self, eff: int) -> int:
        """When the loop next reads after a command that took effect at ``eff``: the payload loop's last
        ``Serial.available()`` check, then ``vTaskDelay(1)`` to the next tick -- after the scan whose alarm
        falls inside that check, with the rest of the check (``TimedEmulator._last_check``)."""
        check_end = eff + self.m.call_ns
        alarm = self.next_alarm
        if alarm > check_end:
            return self.tick_at_or_after(check_end + 1)
        self.scans_until(alarm)
        return self.tick_at_or_after(self.last_end + check_end - alarm + 1)

    # --- the run --------------------------------------------------------------------------------------------

    def run(self) -> Timeline:
        sc, m = self.sc, self.m
        link: LinkModel = make_link(sc.link)
        dec = StreamDecoder(0)
        effects: dict[int, int | None] = {}
        ready: int | None = 0
        host_off = 0
        duration = int(round(sc.duration_us * 1000))
        for t_us, data in sc.writes:
            t_w = int(round(t_us * 1000))
            arrivals = link.arrival_times(data, t_w)
            base = host_off
            host_off += len(data)
            for c in dec.feed(data):
                if c.opcode is None:
                    continue  # unknown bytes: read and ignored at once
                last = c.offset + len(c.raw) - 1 - base
                if last >= arrivals.size:  # pragma: no cover - decode only returns complete commands
                    continue
                a = int(arrivals[last])
                if self.nominal:
                    eff: int | None = a
                else:
                    if ready is None:
                        effects[c.offset] = None
                        continue
                    first = int(arrivals[max(0, c.offset - base)])
                    call = ready if a <= ready else self._idle_poll(first, a, ready)
                    placed = self.place(call)
                    if placed is None:
                        ready = None
                        effects[c.offset] = None
                        self.notes.append("scans run back to back: later commands are never read")
                        continue
                    unit = 2 if _SIZE.get(int(c.opcode)) == 2 else 1  # a u16's bytes are read together
                    cost = call_reads_ns(m, True, unit, len(c.raw))[-1] + (
                        m.hv513_detect_ns if c.opcode == Opcode.HV513_COUNT else 0
                    )
                    eff = placed + cost
                    if self.next_alarm < eff:
                        self.scans_until(self.next_alarm)
                        eff += self.runs[-1].duration
                if eff is None or eff > duration:
                    effects[c.offset] = None if eff is None or eff > duration else eff
                    continue
                self.scans_until(eff - 1)  # a scan whose alarm is the effect's instant sees the new value
                self.emu.feed(c.raw)
                self._reconfigure()
                if c.opcode == Opcode.FREQUENCY and c.value:
                    self.next_alarm = (
                        eff if eff - self.last_reload >= self.period else self.last_reload + self.period
                    )
                effects[c.offset] = eff
                if c.opcode == Opcode.PATTERN:
                    # felt at the next scan, whatever configuration it runs (an older pattern is overwritten)
                    self.pending = [(c.offset, len(c.raw) - 1)]
                if not self.nominal:
                    ready = eff if c.opcode in (Opcode.MEASURE, Opcode.HV513_COUNT) else self._last_check(eff)
        self.scans_until(duration)
        return self._timeline(duration, effects)

    def _timeline(self, duration: int, effects: dict[int, int | None]) -> Timeline:
        """The scans that started by ``duration`` and the effects, as a :class:`Timeline`."""
        # keep only scans that started by the end of the run
        starts, durs = [], []
        for r in self.runs:
            s = r.start + r.stride * np.arange(r.count, dtype=np.int64)
            keep = s <= duration
            starts.append(s[keep])
            durs.append(np.full(int(keep.sum()), r.duration, dtype=np.int64))
        st = np.concatenate(starts) if starts else np.zeros(0, dtype=np.int64)
        du = np.concatenate(durs) if durs else np.zeros(0, dtype=np.int64)
        return Timeline(
            "nominal" if self.nominal else "analytic",
            st,
            du,
            effects,
            self.firsts,
            duration,
            notes=sorted(set(self.notes)),
        )


def run_analytic(scenario: Scenario) -> Timeline:
    """The scenario on the analytic per-cycle engine."""
    t0 = time.perf_counter()
    tl = _Analytic(scenario, nominal=False).run()
    tl.wall_s = time.perf_counter() - t0
    return tl


def run_nominal(scenario: Scenario) -> Timeline:
    """The scenario as back-of-the-envelope arithmetic (``width + discharge`` per channel)."""
    t0 = time.perf_counter()
    tl = _Analytic(scenario, nominal=True).run()
    tl.wall_s = time.perf_counter() - t0
    return tl
