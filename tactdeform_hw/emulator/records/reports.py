"""What the timed emulator tells its user: per scan cycle, per pulse, per host command, per lost byte,
per torn cycle — and the static scan budget of a configuration.

Times in reports are µs since the emulated device's first power-on (``*_us`` floats); the emulator
itself counts integer nanoseconds.  Long runs are stored compactly as :class:`ScanRun` s (one scan
template repeated at a fixed stride) and expanded here only when asked: ``cycles()`` and ``pulses()``
build objects, ``pulse_table()`` builds numpy columns for millions of pulses.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np

from tactdeform_hw.emulator.firmware.firmware_scan import (
    FirmwareBudget,
    ScanBudget,
    ScanTrace,
    beyond_chain_notes,
)
from tactdeform_hw.emulator.firmware.scan import (
    ChannelKind,
    PulseArrays,
    PulseKind,
    ScanConfig,
    ScanTemplate,
    channel_costs,
    channel_offsets_ns,
    clear_clk_pulses,
    scan_duration_ns,
)
from tactdeform_hw.emulator.timed.timing import DEFAULT_MODEL, TimingModel
from tactdeform_hw.protocol.constants import OUTPUTS_PER_HV513, Opcode
from tactdeform_hw.protocol.firmware import V1_2
from tactdeform_hw.protocol.units import DEFAULT_TRANSFER, CurrentTransfer

if TYPE_CHECKING:
    from tactdeform_hw.emulator.timed.model_v1_2 import TimedEmulator

PULSE_KIND_NAMES = {
    PulseKind.MONO: "monophasic",
    PulseKind.BI_ANODIC: "biphasic-anodic",
    PulseKind.BI_CATHODIC: "biphasic-cathodic",
    PulseKind.SENSE: "sense",
}


def _us(ns: int | None) -> float | None:
    return None if ns is None else ns / 1000.0


# --- raw records kept by the emulator -----------------------------------------------------------------------


@dataclass(frozen=True)
class TornInfo:
    """A scan started while a pattern command was half-written: channels below ``new_channels`` came from
    the new pattern, the rest from before it."""

    command_device_offset: int
    command_host_offset: int
    new_channels: int
    electrode_num: int
    changed_channels: int  # of the new ones, how many differ from the value they replaced


@dataclass(frozen=True)
class ScanRun:
    """``count`` scans of one template, alarms ``stride_ns`` apart, the first at ``start_ns``."""

    first_index: int
    start_ns: int
    stride_ns: int
    count: int
    template: ScanTemplate
    period_ns: int
    overrun: bool
    starved: bool  # back to back: the main loop cannot run between these scans
    torn: TornInfo | None = None
    cut_ns: int | None = None  # the watchdog stopped the handler this long after the alarm

    @property
    def duration_ns(self) -> int:
        return self.template.duration_ns if self.cut_ns is None else self.cut_ns

    @property
    def end_ns(self) -> int:
        return self.start_ns + (self.count - 1) * self.stride_ns + self.duration_ns

    def starts_ns(self) -> np.ndarray:
        return self.start_ns + self.stride_ns * np.arange(self.count, dtype=np.int64)


@dataclass(frozen=True)
class EventRun:
    """One scan given by its own signal events, for trace sinks: firmware v2's timed model keeps no
    :class:`~.scan.ScanTemplate` (its scans are walked statement by statement), so it hands the walk's
    events over directly.  ``events`` are (time ns after ``start_ns``, Signal, value) columns."""

    start_ns: int
    duration_ns: int
    events: tuple[np.ndarray, np.ndarray, np.ndarray]

    @property
    def end_ns(self) -> int:
        return self.start_ns + self.duration_ns


@dataclass
class ChannelLatency:
    """When a pattern command's byte for one channel was written, and when that channel's next pulse
    (the first with the new value) started.  ``note`` says why there is none."""

    channel: int
    written_us: float
    first_pulse_us: float | None = None
    note: str = ""


#: The pulse table's columns, in its order.
_PULSE_COLUMNS = (
    "cycle",
    "channel",
    "kind",
    "code",
    "pol",
    "current_ua",
    "charge_nc",
    "voltage_code",
    "n_outputs",
    "output",
    "limited",
    "start_us",
    "width_us",
)


@dataclass
class CommandReport:
    """One command the device's parser completed: when it was sent, arrived, took effect and was first
    felt.  ``latency_us = wire_us + loop_wait_us + scan_wait_us``."""

    device_offset: int
    host_offset: int
    opcode: int
    name: str
    value: Any = None
    host_end: int = -1  # host offset just past its last byte (-1: not from the host)
    sent_us: float | None = None  # host wrote the command byte
    arrival_us: float | None = None  # its last byte reached the receive queue
    effect_us: float | None = None  # the parser stored it (or wrote the reply)
    first_pulse_us: float | None = None  # first pulse it affected
    reply_us: float | None = None  # the reply's last byte reached the host (0xFF, 0xF5)
    in_sync: bool = True  # the parser read exactly the command the host meant at this offset
    channels: list[ChannelLatency] = field(default_factory=list)
    note: str = ""

    @property
    def wire_us(self) -> float | None:
        if self.sent_us is None or self.arrival_us is None:
            return None
        return self.arrival_us - self.sent_us

    @property
    def loop_wait_us(self) -> float | None:
        if self.arrival_us is None or self.effect_us is None:
            return None
        return self.effect_us - self.arrival_us

    @property
    def scan_wait_us(self) -> float | None:
        if self.effect_us is None or self.first_pulse_us is None:
            return None
        return self.first_pulse_us - self.effect_us

    @property
    def latency_us(self) -> float | None:
        if self.sent_us is None or self.first_pulse_us is None:
            return None
        return self.first_pulse_us - self.sent_us

    @property
    def last_channel_us(self) -> float | None:
        """For a pattern: when the last of its channels got its first new pulse."""
        times = [c.first_pulse_us for c in self.channels if c.first_pulse_us is not None]
        return max(times) if times else None

    def to_dict(self) -> dict[str, Any]:
        d = asdict(self)
        if isinstance(self.value, (bytes, bytearray)):
            d["value"] = list(self.value)
        d.update(
            wire_us=self.wire_us,
            loop_wait_us=self.loop_wait_us,
            scan_wait_us=self.scan_wait_us,
            latency_us=self.latency_us,
        )
        return d


@dataclass
class LossReport:
    """Bytes that never reached the parser.

    ``reason``: ``queue_full`` (the rest of a packet discarded), ``rebooting`` (arrived while the device
    restarted) or ``reboot`` (waiting in the queue when the device restarted).  ``parser_state`` is what
    the parser was doing; ``followed`` lists what it made of the bytes that came next — each command it
    completed after the loss, with whether that was the command the host meant at that offset — until it
    read a command in step with the host again (``resync_host_offset``)."""

    time_us: float
    host_offset: int
    count: int
    data: bytes
    reason: str
    queue_bytes: int
    parser_state: str
    cut_command: dict[str, Any] | None = None  # the host's command the first lost byte belonged to
    followed: list[dict[str, Any]] = field(default_factory=list)
    resync_host_offset: int | None = None
    resync_us: float | None = None
    parser_now: str = ""  # while no command in step has been read since: what the parser is doing now

    def to_dict(self) -> dict[str, Any]:
        d = asdict(self)
        d["data"] = self.data.hex()
        return d

    def describe(self) -> str:
        head = (
            f"t={self.time_us:.1f}us lost {self.count} byte(s) at host offset {self.host_offset} "
            f"({self.reason}; queue {self.queue_bytes} B; parser {self.parser_state})"
        )
        lines = [head]
        cc = self.cut_command
        if cc is not None:
            lines.append(
                f"  first lost byte is byte {cc['bytes_before_loss']} of the {cc['length']}-byte "
                f"{cc['name']} sent at host offset {cc['host_offset']}"
            )
        for f in self.followed:
            mark = "ok " if f["in_sync"] else "BAD"
            lines.append(f"  {mark} host@{f['host_offset']} {f['name']} {f['value']}")
        if self.resync_host_offset is not None:
            lines.append(
                f"  back in step at host offset {self.resync_host_offset} (t={self.resync_us:.1f}us)"
            )
        elif self.parser_now:
            lines.append(f"  not back in step yet; parser now {self.parser_now}")
        return "\n".join(lines)


@dataclass(frozen=True)
class CycleReport:
    index: int
    start_us: float
    duration_us: float
    end_us: float
    period_us: float
    overrun: bool
    interval_us: float | None  # to the next scan's alarm
    actual_rate_hz: float | None
    electrode_num: int
    pulses: int
    torn: bool
    watchdog: bool
    starved: bool


@dataclass(frozen=True)
class PulseReport:
    cycle: int
    channel: int
    kind: str
    start_us: float
    width_us: float
    height_code: int
    current_ua: float
    charge_nc: float
    polarity: str
    voltage_code: int
    outputs: tuple[int, ...]
    compliance_limited: bool


@dataclass(frozen=True)
class TornReport:
    cycle: int
    time_us: float
    command_host_offset: int
    new_channels: int
    old_channels: int
    changed_channels: int


# --- the budget ------------------------------------------------------------------------------------------


_KIND_LABEL = {
    ChannelKind.MONO: "monophasic (pattern 1)",
    ChannelKind.BIPHASIC: "biphasic (pattern 2)",
    ChannelKind.SENSE: "sense (other values)",
}


def _budget_notes(
    cfg: ScanConfig, model: TimingModel, scan: int, period: int, stride: int, counts: np.ndarray
) -> list[str]:
    """What a scan budget means for the device, in words: a watchdog reboot, an overrun, a starved or
    slowed parser, sense pulses on channels off in the pattern, channels beyond the HV513 chips."""
    watchdog = model.watchdog_ns is not None and scan > model.watchdog_ns
    overrun = scan > period
    starved = stride <= scan
    notes: list[str] = []
    # The main loop runs only between scans: ``free`` ns in every ``stride``.  Under the skip policy an
    # overrunning scan makes the stride a whole number of periods, with most of the last one free.
    free = stride - scan
    periods = stride // period if period else 1
    if watchdog:
        notes.append(
            f"the scan ({scan / 1000:.1f} µs) exceeds the {model.watchdog_us:.0f} µs interrupt watchdog: "
            "the device reboots to its power-on state part-way through the first scan"
        )
    elif overrun:
        notes.append(
            f"overrun by {(scan - period) / 1000:.2f} µs: the next scan follows at once"
            if model.overrun_policy == "immediate"
            else f"overrun by {(scan - period) / 1000:.2f} µs: the missed alarm is skipped, so a scan "
            f"starts every {periods} periods and leaves {free / 1000:.2f} µs to the main loop"
        )
    if starved and not watchdog:
        notes.append("scans run back to back: the main loop never runs, so no later command is read")
    elif not watchdog and free < model.rtos_tick_ns:
        notes.append(
            f"only {free / 1000:.1f} µs per period outside the scan: the parser reads at most one "
            "command with a payload per period"
            if periods == 1
            else f"only {free / 1000:.1f} µs outside the scan every {periods} periods: the parser reads "
            f"at most one command with a payload per {periods} periods"
        )
    if counts[ChannelKind.SENSE] and cfg.sense_pulse_height:
        notes.append(
            f"{int(counts[ChannelKind.SENSE])} channel(s) off in the pattern still get a sense pulse "
            f"of code {cfg.sense_pulse_height}"
        )
    notes.extend(beyond_chain_notes(cfg.electrode_num, cfg.hv513_num))
    if cfg.hv513_num == 0 and cfg.electrode_num:
        notes.append("HV513 count 0: the clear loads a 1 and leaves output 0 selected")
    return notes


@dataclass(frozen=True)
class BudgetRow:
    kind: str
    channels: int
    select_pol_us: float
    pulse_us: float
    discharge_us: float
    per_channel_us: float
    subtotal_us: float


@dataclass(frozen=True)
class Budget(ScanBudget):
    """A configuration's scan cost against its timer period, from the closed-form costs."""

    electrodes: int
    rows: list[BudgetRow]
    isr_us: float
    clear_clk_pulses: int
    parser_starved: bool
    actual_rate_hz: float
    requested_rate_hz: float | None
    effective_width_us: float
    overrun_policy: str
    notes: list[str]

    @classmethod
    def of(
        cls, cfg: ScanConfig, model: TimingModel = DEFAULT_MODEL, requested_rate_hz: float | None = None
    ) -> Budget:
        costs = channel_costs(cfg, model)
        kinds = cfg.kinds()
        counts = np.bincount(kinds, minlength=3) if kinds.size else np.zeros(3, dtype=np.int64)
        rows = []
        for k in ChannelKind:
            if counts[k] == 0:
                continue
            per = costs.channel_ns(k)
            rows.append(
                BudgetRow(
                    _KIND_LABEL[k],
                    int(counts[k]),
                    (costs.select_ns + costs.pol_ns) / 1000,
                    costs.pulse_ns[k] / 1000,
                    costs.discharge_ns / 1000,
                    per / 1000,
                    int(counts[k]) * per / 1000,
                )
            )
        pos = cfg.electrode_num - 1 if cfg.electrode_num else OUTPUTS_PER_HV513 * cfg.hv513_num
        clk = clear_clk_pulses(cfg, pos)
        scan = scan_duration_ns(cfg, model, pos)
        period = model.alarm_period_ns(cfg.alarm_ticks)
        wd = model.watchdog_ns
        watchdog = wd is not None and scan > wd
        overrun = scan > period
        if model.overrun_policy == "immediate":
            stride = max(scan, period)
        else:
            stride = period * max(1, -(-scan // period)) if period else scan
        starved = stride <= scan
        rate = 0.0 if watchdog or stride == 0 else 1e9 / stride
        notes = _budget_notes(cfg, model, scan, period, stride, counts)
        return cls(
            electrodes=cfg.electrode_num,
            rows=rows,
            isr_us=(costs.entry_ns + costs.exit_ns) / 1000,
            clear_clk_pulses=clk,
            clear_us=costs.clear_ns(clk) / 1000,
            scan_us=scan / 1000,
            period_us=period / 1000,
            alarm_ticks=cfg.alarm_ticks,
            margin_us=(period - scan) / 1000,
            overrun=overrun,
            watchdog_reset=watchdog,
            parser_starved=starved and not watchdog,
            actual_rate_hz=rate,
            requested_rate_hz=requested_rate_hz,
            effective_width_us=model.pulse_width_ns(cfg.pulse_width) / 1000,
            overrun_policy=model.overrun_policy,
            notes=notes,
        )

    def to_dict(self) -> dict[str, Any]:
        d = asdict(self)
        d["verdict"] = self.verdict
        return d

    def table(self) -> str:
        rate = f"{self.requested_rate_hz:g} Hz, " if self.requested_rate_hz is not None else ""
        lines = [
            f"Scan budget: {self.electrodes} electrodes, {rate}timer alarm {self.alarm_ticks} ticks = "
            f"{self.period_us:.2f} µs, overrun policy {self.overrun_policy}",
            f"{'kind':<24}{'channels':>9}{'select+POL':>12}{'pulse':>11}{'discharge':>11}"
            f"{'per channel':>13}{'subtotal':>12}",
        ]
        for r in self.rows:
            lines.append(
                f"{r.kind:<24}{r.channels:>9}{r.select_pol_us:>12.2f}{r.pulse_us:>11.2f}"
                f"{r.discharge_us:>11.2f}{r.per_channel_us:>13.2f}{r.subtotal_us:>12.2f}"
            )
        w = 24 + 9 + 12 + 11 + 11 + 13
        lines += [
            f"{'interrupt entry + exit':<{w}}{self.isr_us:>12.2f}",
            f"{f'chain clear ({self.clear_clk_pulses} CLK)':<{w}}{self.clear_us:>12.2f}",
            f"{'scan':<{w}}{self.scan_us:>12.2f}",
            f"{'period':<{w}}{self.period_us:>12.2f}",
            f"{'margin':<{w}}{self.margin_us:>12.2f}",
            f"verdict: {self.verdict.upper()}; actual rate {self.actual_rate_hz:.2f} Hz; "
            f"effective pulse width {self.effective_width_us:.2f} µs (all times in µs)",
        ]
        lines += [f"note: {n}" for n in self.notes]
        return "\n".join(lines)


def firmware_budget(cfg: ScanConfig, model: TimingModel = DEFAULT_MODEL) -> FirmwareBudget:
    """One scan of ``cfg`` from power-on against its timer period, in the terms of the firmware's own
    scan logs (what ``timing --cs-writes`` / ``--dac-load`` print, on either version): the cost of each
    channel, entry, chain clear, scan, margin and verdict, and the exchange's readings it was timed under.
    The times are the v1.2 scan engine's closed-form costs, each rounded to the ns as a logged µs is.
    """
    costs = channel_costs(cfg, model)
    starts, _ = channel_offsets_ns(cfg, model)
    end = scan_duration_ns(cfg, model, 0)  # a fresh process's chain: the firmware's position 0
    clear_start = costs.entry_ns + sum(costs.channel_ns(k) for k in cfg.kinds().tolist())
    scan = ScanTrace(
        isr_return_us=_us3(end),
        timer_ops=[[_us3(model.isr_entry_ns), 1, "alarm_disable", 0], [_us3(end), 1, "alarm_enable", 0]],
        alarm_ticks=cfg.alarm_ticks,
        channel_start_us=[_us3(t) for t in starts.tolist()],
        clear_start_us=_us3(clear_start),
    )
    cs_extra = model.chip_select_writes * model.cs_write_ns / 1000
    readings = model.readings()
    return FirmwareBudget.of_scan(
        scan,
        firmware=V1_2.name,
        stim_mode=None,
        hv513_num=cfg.hv513_num,
        period_us=cfg.alarm_ticks * model.tick_ns / 1000,
        watchdog_us=model.watchdog_us,
        effective_width_us=round(
            model.spi_ns / 1000 + cs_extra + model.pulse_wait_ns(cfg.pulse_width) / 1000, 3
        ),
        conventions={
            "spi_exchange_us": model.spi_ns / 1000,
            "dac_change_at_us": model.dac_at_ns / 1000,
            "gpio_write_us": model.gpio_ns / 1000,
            "isr_entry_us": model.isr_entry_ns / 1000,
            "timer_tick_us": model.tick_ns / 1000,
            "cs_writes_costed": readings["cs_writes_costed"],
            "dac_load": readings["dac_load"],
        },
    )


def _us3(ns: int) -> float:
    """A time in ns as a scan log writes it: µs to the ns."""
    return round(ns / 1000, 3)


# --- the comparable outcome of a run (for fidelity comparisons) -------------------------------------------


@dataclass
class Timeline:
    """What two engines can be compared on: scan alarms and durations, command effect times and the
    first pulse per channel of each pattern command (keys: host offsets of the command bytes)."""

    engine: str
    scan_start_ns: np.ndarray
    scan_duration_ns: np.ndarray
    effects_ns: dict[int, int | None]
    first_pulses_ns: dict[int, dict[int, int]]
    device_ns: int
    wall_s: float = 0.0
    notes: list[str] = field(default_factory=list)

    def compare(self, reference: Timeline) -> dict[str, Any]:
        """Errors of this timeline against ``reference`` (µs, absolute, max and mean)."""
        n = min(self.scan_start_ns.size, reference.scan_start_ns.size)
        ds = np.abs(self.scan_start_ns[:n] - reference.scan_start_ns[:n]) / 1000.0
        dd = np.abs(self.scan_duration_ns[:n] - reference.scan_duration_ns[:n]) / 1000.0
        eff = []
        missing = 0
        for off, t in reference.effects_ns.items():
            mine = self.effects_ns.get(off)
            if t is None and mine is None:
                continue
            if t is None or mine is None:
                missing += 1
                continue
            eff.append(abs(mine - t) / 1000.0)
        fp = []
        for off, chans in reference.first_pulses_ns.items():
            mine_ch = self.first_pulses_ns.get(off, {})
            for ch, t in chans.items():
                if ch in mine_ch:
                    fp.append(abs(mine_ch[ch] - t) / 1000.0)
                else:
                    missing += 1

        def stats(a: Any) -> tuple[float, float]:
            a = np.asarray(a, dtype=float)
            return (float(a.max()), float(a.mean())) if a.size else (0.0, 0.0)

        return {
            "scans": int(self.scan_start_ns.size),
            "reference_scans": int(reference.scan_start_ns.size),
            "scan_start_max_us": stats(ds)[0],
            "scan_start_mean_us": stats(ds)[1],
            "scan_duration_max_us": stats(dd)[0],
            "effect_max_us": stats(eff)[0],
            "effect_mean_us": stats(eff)[1],
            "first_pulse_max_us": stats(fp)[0],
            "first_pulse_mean_us": stats(fp)[1],
            "unmatched": missing,
        }


def _run_rows(
    r: ScanRun, lo: int | None, hi: int | None
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None:
    """The rows a run keeps in ``[lo, hi)`` ns (None: unbounded) as (cycle, start ns, width ns, index of
    the template's pulse behind each row); None when it keeps none.  A run kept whole needs no mask: a
    single scan (most runs) is its template's rows shifted to its start."""
    p = r.template.pulses
    size = p.channel.size
    whole = lo is None and hi is None and r.cut_ns is None
    if whole and r.count == 1:
        return (
            np.full(size, r.first_index, dtype=np.int64),
            p.start_ns + r.start_ns,
            p.width_ns,
            np.arange(size),
        )
    starts = r.starts_ns()
    reps = starts.size
    width = p.width_ns
    if whole:
        if reps == 0:
            return None
        sel = np.arange(size)
        abs_start = (starts[:, None] + p.start_ns[None, :]).ravel()
    else:
        keep = np.ones(size, dtype=bool)
        if r.cut_ns is not None:
            keep = p.start_ns < r.cut_ns
            width = np.minimum(p.width_ns, r.cut_ns - p.start_ns)
        sel = np.nonzero(keep)[0]
        abs_start = (starts[:, None] + p.start_ns[sel][None, :]).ravel()
        mask = np.ones(abs_start.size, dtype=bool)
        if lo is not None:
            mask &= abs_start >= lo
        if hi is not None:
            mask &= abs_start < hi
        if not mask.any():
            return None
    cycle = np.repeat(r.first_index + np.arange(reps), sel.size)
    # the template's pulse behind each row kept (its pulses once per repetition)
    idx = np.tile(sel, reps) if reps > 1 else sel
    if lo is not None or hi is not None:
        idx, cycle, abs_start = idx[mask], cycle[mask], abs_start[mask]
    return cycle, abs_start, width[idx], idx


# --- the view the emulator hands out ----------------------------------------------------------------------


class RowPulseTable:
    """The delivered pulses as the campaigns read them, for the models that record them row by row (the
    v2 model, a host build): a subclass lists the rows (:meth:`_rows`, the columns :attr:`row_columns`),
    and the columns every reader needs past them (``current_ua``, the DAC code through ``transfer`` as the
    Python models give it, and ``charge_nc``, current × width) are made here, by one rule for both."""

    #: The columns of a row, in order; ``code`` and ``width_us`` among them.
    row_columns: tuple[str, ...] = ()

    def __init__(self, owner: Any) -> None:
        self._owner = owner

    def _rows(self, t0_us: float | None, t1_us: float | None) -> list[tuple[float, ...]]:
        """The rows of the pulses that start within ``[t0_us, t1_us)`` (a bound of None: no bound)."""
        raise NotImplementedError

    def pulse_table(
        self,
        t0_us: float | None = None,
        t1_us: float | None = None,
        transfer: CurrentTransfer = DEFAULT_TRANSFER,
    ) -> dict[str, np.ndarray]:
        """Every pulse (the subclass says which) as numpy columns: :attr:`row_columns`, then ``current_ua``
        and ``charge_nc``, optionally starting within ``[t0_us, t1_us)``."""
        rows = self._rows(t0_us, t1_us)
        cols = list(zip(*rows)) if rows else [()] * len(self.row_columns)
        out: dict[str, np.ndarray] = {
            name: np.asarray(col, dtype=np.float64 if name.endswith("_us") else np.int64)
            for name, col in zip(self.row_columns, cols, strict=True)
        }
        current = np.asarray([transfer.to_ua(int(c)) for c in out["code"]], dtype=np.float64)
        out["current_ua"] = current
        out["charge_nc"] = current * out["width_us"] / 1e3
        return out


class TimingReports:
    """Reports over everything a :class:`~tactdeform_hw.emulator.timed.model_v1_2.TimedEmulator` has
    simulated."""

    def __init__(self, emu: TimedEmulator) -> None:
        self._emu = emu

    @property
    def runs(self) -> list[ScanRun]:
        return self._emu.runs

    @property
    def commands(self) -> list[CommandReport]:
        return self._emu.commands

    @property
    def losses(self) -> list[LossReport]:
        return self._emu.losses

    def scan_count(self) -> int:
        return sum(r.count for r in self.runs)

    def _starts(self) -> np.ndarray:
        if not self.runs:
            return np.zeros(0, dtype=np.int64)
        return np.concatenate([r.starts_ns() for r in self.runs])

    def cycles(self, first: int = 0, last: int | None = None) -> list[CycleReport]:
        """Cycle reports ``first`` .. ``last - 1`` (all by default)."""
        starts = self._starts()
        nxt = np.r_[starts[1:], -1] if starts.size else starts
        out: list[CycleReport] = []
        last = starts.size if last is None else min(last, starts.size)
        i = 0
        for r in self.runs:
            for _ in range(r.count):
                if first <= i < last:
                    s = int(starts[i])
                    interval = int(nxt[i]) - s if nxt[i] >= 0 else None
                    cut = r.cut_ns is not None
                    out.append(
                        CycleReport(
                            i,
                            s / 1000,
                            r.duration_ns / 1000,
                            (s + r.duration_ns) / 1000,
                            r.period_ns / 1000,
                            r.overrun,
                            None if interval is None else interval / 1000,
                            None if not interval else 1e9 / interval,
                            r.template.config.electrode_num,
                            int(r.template.pulses.channel.size)
                            if not cut
                            else int(np.sum(r.template.pulses.start_ns < r.cut_ns)),
                            r.torn is not None,
                            cut,
                            r.starved,
                        )
                    )
                i += 1
                if i >= last:
                    return out
        return out

    def pulse_table(self, t0_us: float | None = None, t1_us: float | None = None) -> dict[str, np.ndarray]:
        """Every pulse as numpy columns (``cycle, channel, kind, start_us, width_us, code, pol, current_ua,
        charge_nc, voltage_code, n_outputs, output, limited``), optionally within ``[t0_us, t1_us)``.

        Each run gives the rows of its template's pulses it keeps (as indices into the columns of every
        template met, laid end to end); each column is gathered once at the end."""
        lo = None if t0_us is None else int(round(t0_us * 1000))
        hi = None if t1_us is None else int(round(t1_us * 1000))
        templates: dict[int, int] = {}  # id of a template's pulses -> where its rows start end to end
        met: list[PulseArrays] = []
        rows = 0
        cycles: list[np.ndarray] = []
        starts_ns: list[np.ndarray] = []
        widths: list[np.ndarray] = []
        picks: list[np.ndarray] = []
        for r in self.runs:
            p = r.template.pulses
            if p.channel.size == 0:
                continue
            kept = _run_rows(r, lo, hi)
            if kept is None:
                continue
            cycle, abs_start, width, idx = kept
            at = templates.get(id(p))
            if at is None:
                at = templates[id(p)] = rows
                met.append(p)
                rows += p.channel.size
            cycles.append(cycle)
            starts_ns.append(abs_start)
            widths.append(width)
            picks.append(idx + at)
        if not picks:
            return {k: np.zeros(0) / 1000.0 if k.endswith("_us") else np.zeros(0) for k in _PULSE_COLUMNS}
        pick = np.concatenate(picks)
        w = np.concatenate(widths)
        out = {"cycle": np.concatenate(cycles)}
        for name in _PULSE_COLUMNS[1:-2]:
            if name == "charge_nc":
                out[name] = out["current_ua"] * w / 1e6
                continue
            col = np.concatenate([getattr(p, name) for p in met]) if len(met) > 1 else getattr(met[0], name)
            out[name] = col[pick]
        out["start_us"] = np.concatenate(starts_ns) / 1000.0
        out["width_us"] = w / 1000.0
        return out

    def pulses(
        self, t0_us: float | None = None, t1_us: float | None = None, limit: int | None = None
    ) -> list[PulseReport]:
        t = self.pulse_table(t0_us, t1_us)
        n = t["channel"].size if limit is None else min(limit, t["channel"].size)
        outputs_of = self.outputs_lookup()
        kind_name = {int(k): v for k, v in PULSE_KIND_NAMES.items()}
        col = {k: t[k][:n].tolist() for k in t}  # one conversion per column, not one per value
        rows = zip(
            col["cycle"],
            col["channel"],
            col["kind"],
            col["start_us"],
            col["width_us"],
            col["code"],
            col["current_ua"],
            col["charge_nc"],
            col["pol"],
            col["voltage_code"],
            col["output"],
            col["n_outputs"],
            col["limited"],
        )
        return [
            PulseReport(
                int(cyc),
                int(ch),
                kind_name[int(kind)],
                float(start),
                float(width),
                int(code),
                float(ua),
                float(nc),
                "anodic" if pol else "cathodic",
                int(volt),
                outputs_of(int(cyc), int(ch), int(out), int(n_out)),
                bool(limited),
            )
            for cyc, ch, kind, start, width, code, ua, nc, pol, volt, out, n_out, limited in rows
        ]

    def outputs_lookup(self) -> Any:
        """The outputs of a :meth:`pulse_table` row, as ``lookup(cycle, channel, output, n_outputs)``: the
        table keeps one output and a count; a pulse through several outputs is looked up in its run."""
        runs = self.runs

        def lookup(cycle: int, channel: int, low: int, n: int) -> tuple[int, ...]:
            if n <= 1:
                return (low,) if n == 1 else ()
            for r in runs:
                if r.first_index <= cycle < r.first_index + r.count:
                    idx = np.nonzero(r.template.pulses.channel == channel)[0]
                    return r.template.pulse_outputs[int(idx[0])]
            return ()

        return lookup

    def torn(self) -> list[TornReport]:
        out = []
        for r in self.runs:
            if r.torn is None:
                continue
            for j in range(r.count):
                t = r.torn
                out.append(
                    TornReport(
                        r.first_index + j,
                        (r.start_ns + j * r.stride_ns) / 1000,
                        t.command_host_offset,
                        t.new_channels,
                        t.electrode_num - t.new_channels,
                        t.changed_channels,
                    )
                )
        return out

    def overruns(self) -> list[CycleReport]:
        return [c for c in self.cycles() if c.overrun]

    def summary(self) -> dict[str, Any]:
        starts = self._starts()
        n = int(starts.size)
        over = sum(r.count for r in self.runs if r.overrun)
        pulses = sum(
            r.count * int(r.template.pulses.channel.size)
            if r.cut_ns is None
            else int(np.sum(r.template.pulses.start_ns < r.cut_ns))
            for r in self.runs
        )
        durations = (
            np.concatenate([np.full(r.count, r.duration_ns) for r in self.runs]) if self.runs else np.zeros(0)
        )
        lat = [c.latency_us for c in self.commands if c.latency_us is not None]
        return {
            "now_us": self._emu.now_us,
            "scans": n,
            "pulses": pulses,
            "overruns": over,
            "torn_scans": sum(r.count for r in self.runs if r.torn is not None),
            "watchdog_resets": sum(1 for r in self.runs if r.cut_ns is not None),
            "scan_us_max": float(durations.max() / 1000) if n else None,
            "mean_rate_hz": float((n - 1) * 1e9 / (starts[-1] - starts[0]))
            if n > 1 and starts[-1] > starts[0]
            else None,
            "commands": len(self.commands),
            "commands_out_of_step": sum(1 for c in self.commands if not c.in_sync),
            "bytes_lost": sum(lo.count for lo in self.losses),
            "losses": len(self.losses),
            "latency_us_max": max(lat) if lat else None,
            "queue_high_water": self._emu.queue.high_water,
            "model_assumptions": self._emu.model.assumptions(),
        }

    def timeline(self, engine: str = "event-exact") -> Timeline:
        starts = self._starts()
        durs = (
            np.concatenate([np.full(r.count, r.duration_ns, dtype=np.int64) for r in self.runs])
            if self.runs
            else np.zeros(0, dtype=np.int64)
        )
        # every command the host meant, None until the device applied it in step
        effects: dict[int, int | None] = {off: None for off in self._emu.intended_offsets()}
        firsts: dict[int, dict[int, int]] = {}
        for c in self.commands:
            if c.host_offset < 0 or not c.in_sync:
                continue
            effects[c.host_offset] = None if c.effect_us is None else int(round(c.effect_us * 1000))
            if c.opcode == Opcode.PATTERN:
                firsts[c.host_offset] = {
                    ch.channel: int(round(ch.first_pulse_us * 1000))
                    for ch in c.channels
                    if ch.first_pulse_us is not None
                }
        return Timeline(engine, starts, durs, effects, firsts, self._emu.now_ns)

    def to_dict(self, pulses_limit: int = 0) -> dict[str, Any]:
        d: dict[str, Any] = {
            "summary": self.summary(),
            "commands": [c.to_dict() for c in self.commands],
            "losses": [lo.to_dict() for lo in self.losses],
            "torn": [asdict(t) for t in self.torn()],
            "cycles": [asdict(c) for c in self.cycles()],
        }
        if pulses_limit:
            d["pulses"] = [asdict(p) for p in self.pulses(limit=pulses_limit)]
        return d
