"""Firmware v2's scan interrupt, statement by statement, chip-select pins included: v2's scan engine.

This is the conformance walker: it produces the same event log as the firmware's own interrupt code
built on a host (``tests/data/scan_traces_v2.jsonl``), in the same order and with the same values, for
v2 (71adee21): parameters snapshotted at scan start; the pattern is a DAC code per channel and a global
mode picks the waveform (0 mono, 1 biphasic with the first phase at the configured polarity, 2 the sense
pulse on every channel, pattern ignored); the discharge has no exchange; every exchange is wrapped in
chip-select writes, both pins set in one register write.

Two readings the firmware's code leaves open are options of :class:`ScanConventions`:
``cs_writes_costed`` (whether the 6.6 µs exchange excludes the chip-select writes, as the host build
costs them, or includes them) and ``dac_load`` (the DAC output changes 3.3 µs into the exchange, the
firmware comment, or when DA_CS rises, as the converter's datasheet has it).  Times are kept in integer
nanoseconds and reported in µs.

One scan engine per firmware version (:data:`~.models.MODELS` names each version's): the v2 timed model
and ``timing --firmware v2`` run this walker (its scan shapes cached per configuration); v1.2 has its own,
:mod:`.scan`, held to v1.2's firmware traces under the same readings, and this walker refuses v1.2.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

from tactdeform_hw.emulator.firmware.board import AD_CS, BL, CLK, DA_CS, DIN, LE, POL
from tactdeform_hw.emulator.firmware.models import model_entry
from tactdeform_hw.emulator.timed.timing import DAC_LOADS
from tactdeform_hw.errors import ConfigurationError
from tactdeform_hw.protocol import firmware_math as fm
from tactdeform_hw.protocol.constants import OUTPUTS_PER_HV513, POWER_ON_PERIOD_US
from tactdeform_hw.protocol.firmware import FirmwareSpec, get_firmware

__all__ = [
    "AD_CS",
    "BL",
    "CLK",
    "DAC_LOADS",
    "DA_CS",
    "DEFAULT_CONVENTIONS",
    "DIN",
    "HOST_BUILD",
    "LE",
    "MODE_NAMES",
    "POL",
    "FirmwareBudget",
    "FirmwareScanConfig",
    "ScanBudget",
    "ScanConventions",
    "ScanTrace",
    "alarm_ticks_for",
    "beyond_chain_notes",
    "budget",
    "scan_duration_us",
    "trace_scan",
]


@dataclass(frozen=True)
class ScanConventions:
    """The timing conventions of a scan trace.

    The defaults are the host build's ``shim`` except ``cs_writes_costed``: the package reads the
    firmware's "DAAD takes 6.6 µs" as the whole call, chip selects included (7639.05 µs for the
    TactDeform setting on v2); :data:`HOST_BUILD` costs them apart as the host build does (7645.45 µs).
    v1.2's engine takes the same two readings from its timing model."""

    spi_exchange_ns: int = 6600
    dac_change_at_ns: int = 3300
    gpio_write_ns: int = 50
    isr_entry_ns: int = 2000
    timer_tick_ns: int = 500
    cs_writes_costed: bool = False
    dac_load: str = "mid_exchange"

    def __post_init__(self) -> None:
        if self.dac_load not in DAC_LOADS:
            raise ConfigurationError(f"dac_load={self.dac_load!r} is not one of {', '.join(DAC_LOADS)}")

    def describe(self) -> dict[str, Any]:
        return {
            "spi_exchange_us": self.spi_exchange_ns / 1000,
            "dac_change_at_us": self.dac_change_at_ns / 1000,
            "gpio_write_us": self.gpio_write_ns / 1000,
            "isr_entry_us": self.isr_entry_ns / 1000,
            "timer_tick_us": self.timer_tick_ns / 1000,
            "cs_writes_costed": self.cs_writes_costed,
            "dac_load": self.dac_load,
        }


DEFAULT_CONVENTIONS = ScanConventions()
HOST_BUILD = ScanConventions(cs_writes_costed=True)


@dataclass(frozen=True)
class FirmwareScanConfig:
    """What a v2 scan reads from the firmware's variables, with the golden files' names.

    ``stim_pattern`` holds a DAC code per channel and ``stim_mode`` picks the waveform.  ``frequency_hz``
    None means no 0xF6 ever arrived (power-on period)."""

    electrode_num: int
    stim_pattern: Sequence[int]
    pulse_width: int
    discharge_time: int
    polarity: int = 1
    hv513_num: int = 4
    sense_pulse_height: int = 0
    sense_pulse_width: int = 0
    stim_mode: int = 0
    frequency_hz: int | None = None
    prior_scans: int = 0

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> FirmwareScanConfig:
        names = cls.__dataclass_fields__
        return cls(**{k: v for k, v in d.items() if k in names})


@dataclass
class ScanTrace:
    """One logged scan: events ``[time_us, "GPIO", pin, level]`` / ``[time_us, "DAC", "DAC", code]``."""

    events: list[list[Any]] = field(default_factory=list)
    isr_return_us: float = 0.0
    voltage: list[int] = field(default_factory=list)
    timer_ops: list[list[Any]] = field(default_factory=list)
    alarm_ticks: int = 0
    chain_position: int = 0
    channel_start_us: list[float] = field(default_factory=list)
    clear_start_us: float = 0.0

    @property
    def duration_us(self) -> float:
        return self.isr_return_us


def alarm_ticks_for(frequency_hz: int | None) -> int:
    """The Timer1 alarm v2's parser leaves for 0xF6 (it divides in double; power-on 20000 when never
    set)."""
    if not frequency_hz:
        return fm.alarm_ticks(POWER_ON_PERIOD_US)
    return fm.alarm_ticks(fm.period_us_from_rate_double(frequency_hz))


def _ns_to_us(ns: int) -> float:
    return round(ns / 1000, 3)


class _Walker:
    def __init__(self, spec: FirmwareSpec, conv: ScanConventions, log: bool, times_ns: bool = False) -> None:
        #: a time of the walk (integer ns) as the trace gives it: µs to the ns, or the ns themselves
        self.us: Callable[[int], float] = int if times_ns else _ns_to_us
        self.spec = spec
        self.c = conv
        self.log = log
        self.t = 0
        self.ev: list[list[Any]] = []
        self.dac = 0
        self.pos = 0
        self.marks: list[int] = []  # start of each channel, then of the chain clear

    def gpio(self, *pins_levels: tuple[int, int]) -> None:
        """One register write (several pins: one event each, same time, ascending pin)."""
        self.t += self.c.gpio_write_ns
        if self.log:
            for pin, level in sorted(pins_levels):
                self.ev.append([self.us(self.t), "GPIO", pin, level])

    def _cs(self, level: int) -> None:
        """Both chip selects in one register write."""
        self.gpio((AD_CS, level), (DA_CS, level))

    def _cs_free(self, level: int) -> None:
        """Chip-select events inside the exchange's own time (the other reading)."""
        if self.log:
            for pin in (AD_CS, DA_CS):
                self.ev.append([self.us(self.t), "GPIO", pin, level])

    def exchange(self, code: int) -> int:
        """DAAD(code): returns the ADC reading (the code held when the exchange starts)."""
        c = self.c
        reading = self.dac
        if c.cs_writes_costed:
            self._cs(0)
        else:
            self._cs_free(0)
        t0 = self.t
        self.t = t0 + c.spi_exchange_ns
        if c.dac_load == "mid_exchange" and self.log:
            self.ev.append([self.us(t0 + c.dac_change_at_ns), "DAC", "DAC", code])
        if c.cs_writes_costed:
            self._cs(1)
            if c.dac_load == "cs_rise" and self.log:
                self.ev.append([self.us(self.t), "DAC", "DAC", code])
        else:
            if c.dac_load == "cs_rise" and self.log:
                self.ev.append([self.us(self.t), "DAC", "DAC", code])
            self._cs_free(1)
        self.dac = code
        return reading

    def delay(self, us: int) -> None:
        """``delay_exact_us``: minimum 3, then ``int(us * 2.0 - 5.4)`` ticks of the busy-wait timer."""
        self.t += self.spec.timing.delay_ticks(us) * self.c.timer_tick_ns

    def mono(self, height: int, width: int) -> int:
        self.exchange(height)
        offset = self.spec.timing.pulse_wait_offset_us
        if width >= offset:
            self.delay(width - offset)
        return self.exchange(0)

    def select(self, target: int) -> None:
        self.gpio((LE, 0))
        if target == 0:
            self.gpio((DIN, 1))
            self.gpio((CLK, 1))
            self.gpio((CLK, 0))
            self.pos = 0
        else:
            self.gpio((DIN, 0))
            for _ in range(target - self.pos):
                self.gpio((CLK, 1))
                self.gpio((CLK, 0))
            self.pos = target
        self.gpio((LE, 1))


def trace_scan(
    cfg: FirmwareScanConfig,
    firmware: str | FirmwareSpec = "v2",
    conventions: ScanConventions = DEFAULT_CONVENTIONS,
    *,
    log: bool = True,
    times_ns: bool = False,
) -> ScanTrace:
    """One v2 interrupt (after ``cfg.prior_scans`` unlogged ones), from a fresh process's chain state.

    ``firmware`` must be one this walker is the scan engine of (v2; v1.2's is :mod:`.scan`).
    ``times_ns``: every time in the trace (events, return, channel starts) as the integer ns the walk
    keeps, not in µs (each µs value is that ns / 1000 to the ns, so nothing else differs) -- for a model
    that works in ns and would only multiply back."""
    spec = _walked(firmware)
    w = _Walker(spec, conventions, log=False, times_ns=times_ns)
    volts: list[int] = []
    for k in range(cfg.prior_scans + 1):
        w.log = log and k == cfg.prior_scans
        w.ev = []
        w.t = conventions.isr_entry_ns
        volts = _isr(w, cfg, spec)
    end = w.t
    return ScanTrace(
        events=w.ev,
        isr_return_us=w.us(end),
        voltage=volts,
        timer_ops=[
            [w.us(conventions.isr_entry_ns), 1, "alarm_disable", 0],
            [w.us(end), 1, "alarm_enable", 0],
        ],
        alarm_ticks=alarm_ticks_for(cfg.frequency_hz),
        chain_position=w.pos,
        channel_start_us=[w.us(t) for t in w.marks[:-1]],
        clear_start_us=w.us(w.marks[-1]),
    )


def _walked(firmware: str | FirmwareSpec) -> FirmwareSpec:
    """The version's table, if this walker is its scan engine (the registry says which engine is)."""
    spec = get_firmware(firmware)
    engine = model_entry(spec).scan_module
    if engine != __name__:
        raise ConfigurationError(
            f"firmware {spec.name}: its scan engine is {engine}; the statement walker scans v2 only"
        )
    return spec


def _isr(w: _Walker, cfg: FirmwareScanConfig, spec: FirmwareSpec) -> list[int]:
    """The handler: the global mode picks each channel's waveform; the pattern holds its DAC code."""
    n = cfg.electrode_num
    volts = [0] * n
    pol = cfg.polarity
    w.marks = []
    for ch in range(n):
        w.marks.append(w.t)
        w.select(ch)
        w.gpio((POL, 1 if pol else 0))
        value = cfg.stim_pattern[ch]
        if cfg.stim_mode == 0:
            ad = w.mono(value, cfg.pulse_width)
        elif cfg.stim_mode == 1:
            w.mono(value, cfg.pulse_width)
            w.gpio((POL, 1 if pol == 0 else 0))
            ad = w.mono(value, cfg.pulse_width)
        else:
            ad = w.mono(cfg.sense_pulse_height, cfg.sense_pulse_width)
        volts[ch] = ad
        w.gpio((POL, 1))
        w.gpio((BL, 0))
        if cfg.discharge_time > spec.timing.discharge_wait_offset_us:
            w.delay(cfg.discharge_time - spec.timing.discharge_wait_offset_us)
        w.gpio((BL, 1))
    w.marks.append(w.t)
    w.select(OUTPUTS_PER_HV513 * cfg.hv513_num)
    return volts


def scan_duration_us(
    cfg: FirmwareScanConfig,
    firmware: str | FirmwareSpec = "v2",
    conventions: ScanConventions = DEFAULT_CONVENTIONS,
) -> float:
    """From the alarm to the handler's return (events not logged)."""
    return trace_scan(cfg, firmware, conventions, log=False).isr_return_us


# --- the budget of one configuration, by firmware version ---------------------------------------------------


def beyond_chain_notes(electrode_num: int, hv513_num: int) -> list[str]:
    """The note of a budget whose electrode count runs past the chips' outputs (``OUTPUTS_PER_HV513``
    each), in the same words for the walker's budget and the closed-form one; [] when every channel has
    an output."""
    driven = OUTPUTS_PER_HV513 * hv513_num
    if electrode_num <= driven:
        return []
    return [f"channels {driven}..{electrode_num - 1} lie beyond the {hv513_num} HV513 chip(s)"]


@dataclass(frozen=True)
class ScanBudget:
    """A scan's cost against its timer period: what every budget states, from the statement walker
    (:class:`FirmwareBudget`) or from the closed-form costs (``reports.Budget``), with one verdict rule
    so the two never name the same outcome differently."""

    clear_us: float
    scan_us: float
    period_us: float
    alarm_ticks: int
    margin_us: float
    overrun: bool
    watchdog_reset: bool

    @property
    def verdict(self) -> str:
        """The outcome in the words the timing command and the reports print: a watchdog reset, the
        graver, is named before an overrun."""
        if self.watchdog_reset:
            return "watchdog reset"
        return "overrun" if self.overrun else "fits"


@dataclass(frozen=True)
class FirmwareBudget(ScanBudget):
    """One scan of a configuration against its timer period, from the statement walker."""

    firmware: str
    electrodes: int
    stim_mode: int | None
    per_channel_us: list[float]
    isr_entry_us: float
    actual_rate_hz: float
    effective_width_us: float
    conventions: dict[str, Any]
    notes: list[str]

    @classmethod
    def of_scan(
        cls,
        scan: ScanTrace,
        *,
        firmware: str,
        stim_mode: int | None,
        hv513_num: int,
        period_us: float,
        watchdog_us: float | None,
        effective_width_us: float,
        conventions: dict[str, Any],
        mode_notes: Sequence[str] = (),
    ) -> FirmwareBudget:
        """The budget of one scan (its return, channel starts and clear start; events need not be logged)
        against its period, by either version's engine: the verdict and the notes in the same words.
        ``mode_notes`` go between the timing note and the chain's."""
        end = scan.isr_return_us
        starts = scan.channel_start_us + [scan.clear_start_us]
        watchdog = watchdog_us is not None and end > watchdog_us
        stride = max(end, period_us)
        notes: list[str] = []
        if watchdog:
            notes.append(f"the scan exceeds the {watchdog_us:.0f} µs interrupt watchdog: the board reboots")
        elif end > period_us:
            notes.append(f"overrun by {end - period_us:.2f} µs: the next scan follows at once")
        notes.extend(mode_notes)
        notes.extend(beyond_chain_notes(len(scan.channel_start_us), hv513_num))
        return cls(
            firmware=firmware,
            electrodes=len(scan.channel_start_us),
            stim_mode=stim_mode,
            per_channel_us=[round(b - a, 3) for a, b in zip(starts, starts[1:], strict=False)],
            isr_entry_us=scan.timer_ops[0][0],
            clear_us=round(end - scan.clear_start_us, 3),
            scan_us=end,
            period_us=period_us,
            alarm_ticks=scan.alarm_ticks,
            margin_us=round(period_us - end, 3),
            overrun=end > period_us,
            watchdog_reset=watchdog,
            actual_rate_hz=0.0 if watchdog or stride == 0 else 1e6 / stride,
            effective_width_us=effective_width_us,
            conventions=conventions,
            notes=notes,
        )

    def to_dict(self) -> dict[str, Any]:
        d = dict(self.__dict__)
        d["verdict"] = self.verdict
        return d

    def table(self) -> str:
        mode = "" if self.stim_mode is None else f", mode {self.stim_mode} ({MODE_NAMES[self.stim_mode]})"
        lines = [
            f"Scan budget, firmware {self.firmware}: {self.electrodes} electrodes{mode}, timer alarm "
            f"{self.alarm_ticks} ticks = {self.period_us:.2f} µs",
        ]
        distinct = sorted(set(self.per_channel_us))
        for cost in distinct:
            count = self.per_channel_us.count(cost)
            lines.append(
                f"{'channels':<24}{count:>9}  "
                f"{'per channel':>12}{cost:>11.2f}{'subtotal':>10}{count * cost:>11.2f}"
            )
        lines += [
            f"{'interrupt entry':<66}{self.isr_entry_us:>11.2f}",
            f"{'chain clear':<66}{self.clear_us:>11.2f}",
            f"{'scan':<66}{self.scan_us:>11.2f}",
            f"{'period':<66}{self.period_us:>11.2f}",
            f"{'margin':<66}{self.margin_us:>11.2f}",
            f"verdict: {self.verdict.upper()}; actual rate {self.actual_rate_hz:.2f} Hz; effective pulse "
            f"width {self.effective_width_us:.2f} µs (all times in µs)",
            "chip-select writes "
            + ("costed apart from" if self.conventions["cs_writes_costed"] else "inside")
            + f" the {self.conventions['spi_exchange_us']} µs exchange; DAC loads "
            + (
                "3.3 µs into the exchange"
                if self.conventions["dac_load"] == "mid_exchange"
                else "when DA_CS rises"
            ),
        ]
        lines += [f"note: {n}" for n in self.notes]
        return "\n".join(lines)


MODE_NAMES = {0: "monophasic", 1: "biphasic", 2: "impedance only"}
WATCHDOG_US = 300_000.0


def budget(
    cfg: FirmwareScanConfig,
    firmware: str | FirmwareSpec = "v2",
    conventions: ScanConventions = DEFAULT_CONVENTIONS,
) -> FirmwareBudget:
    """Scan time, period, margin and verdict of ``cfg`` on ``firmware`` (overruns: the next scan at once);
    v2 only, as :func:`trace_scan` (v1.2's: :func:`~..records.reports.firmware_budget`)."""
    spec = _walked(firmware)
    tr = trace_scan(cfg, spec, conventions, log=False)
    width = cfg.sense_pulse_width if cfg.stim_mode == 2 else cfg.pulse_width
    wait = (
        spec.timing.delay_ticks(width - spec.timing.pulse_wait_offset_us) * conventions.timer_tick_ns / 1000
        if width >= spec.timing.pulse_wait_offset_us
        else 0.0
    )
    cs_extra = (
        spec.timing.chip_select_writes_per_exchange * conventions.gpio_write_ns / 1000
        if conventions.cs_writes_costed
        else 0.0
    )
    notes: list[str] = []
    if cfg.stim_mode == 2 and cfg.electrode_num:
        notes.append(
            f"mode 2: every channel gets the sense pulse (code {cfg.sense_pulse_height}, "
            f"{cfg.sense_pulse_width} µs) whatever the pattern; a zero pattern does not stop current"
        )
    if (
        cfg.stim_mode != 2
        and width < spec.timing.pulse_wait_offset_us
        and any(cfg.stim_pattern[: cfg.electrode_num])
    ):
        notes.append(f"pulse width {width} µs: the pulse is still one SPI exchange long")
    return FirmwareBudget.of_scan(
        tr,
        firmware=spec.name,
        stim_mode=cfg.stim_mode,
        hv513_num=cfg.hv513_num,
        period_us=tr.alarm_ticks * conventions.timer_tick_ns / 1000,
        watchdog_us=spec.timing.watchdog_us,
        effective_width_us=round(conventions.spi_exchange_ns / 1000 + cs_extra + wait, 3),
        conventions=conventions.describe(),
        mode_notes=notes,
    )
