"""The stimulation timer interrupt, event for event: HV513 chain, POL, DAC/ADC exchanges, busy-waits, BL.

The firmware's handler, in the protocol reference's exact order, for ``ch`` in ``0 .. electrode_num-1``:

1. select the channel on the HV513 chain — LE low; ``ch == 0``: DIN high and one CLK pulse, position 0;
   otherwise DIN low and ``ch - position`` CLK pulses, position ``ch``; LE high (the outputs latch);
2. POL := the polarity register (high anodic, low cathodic);
3. the pulse: pattern 1 monophasic, 2 biphasic (POL high, monophasic, POL low, monophasic), anything
   else a sense pulse; ``monophasic(h, w)`` = DAC := h (an SPI exchange, the output changing part-way),
   busy-wait ``w - 7`` µs if ``w >= 7``, DAC := 0 (an exchange that returns the ADC reading taken while
   the current still flows — stored as ``voltage[ch] = raw >> 2``);
4. discharge — DAC := 0, POL high, BL low (all outputs off), busy-wait ``d - 7`` µs if ``d > 7``, BL high;

then the chain is cleared by "scanning to position ``8 * hv513_count``" with the same select routine —
which, with an HV513 count of 0, is ``ch == 0``: it loads a 1 and leaves output 0 selected.

This is firmware v1.2's one scan engine (:data:`~.models.MODELS` names each version's): the timed and
untimed models, ``timing`` under every option and the traces all run it.  It times each exchange under
the two readings the firmware's code leaves open, from its :class:`~..timed.timing.TimingModel`: whether
the chip-select writes around an exchange cost GPIO writes of their own (``cs_writes_costed``) and when
the DAC output changes (``dac_load``); :func:`firmware_trace` writes a scan as the firmware's own code
logs it, chip selects included, and ``tests/test_scan_engine_readings.py`` holds it to v1.2's firmware
traces (``tests/data/scan_traces_v12.jsonl``) and to the statement walker's recorded v1.2 outputs under
every reading (``tests/data/scan_walker_v12.jsonl``).  Within this module, two implementations must
agree to the nanosecond:

* the step-through in ``tests/scan_reference.py`` walks the firmware's statements one by one — slow,
  obviously right, the oracle the tests hold this module to;
* :class:`ScanEngine` here builds a :class:`ScanTemplate` per configuration from per-pattern-kind channel
  blocks (numpy), caches it, and reuses it for every scan with the same configuration and chain state,
  shifted in time.  A scan's events depend only on the registers, the chain state at its start, the
  timing model and the skin model — never on the absolute time — so a shifted template *is* the
  step-through; ``tests/test_timing_scan.py`` checks the two event for event over random
  configurations, chain states and whole multi-scan runs.

The HV513 chain is modelled physically: a shift register as long as the outputs really fitted (``8 ×``
the chips on the stack), CLK rising shifts DIN in, LE rising latches.  The firmware's *belief* (its
``position`` variable and ``hv513_num``) can differ from the hardware — a channel beyond the chain has no
electrode behind it, and with a count of 0 and a real chain, ones accumulate and several outputs light
at once.  Both show up in the pulse records (``outputs``).
"""

from __future__ import annotations

from collections import OrderedDict
from dataclasses import dataclass, field
from enum import IntEnum
from functools import lru_cache
from itertools import chain as _chained
from typing import Any, NamedTuple

import numpy as np

from tactdeform_hw.emulator.firmware.board import AD_CS, BL, CLK, DA_CS, DIN, LE, POL
from tactdeform_hw.emulator.firmware.registers import Registers
from tactdeform_hw.emulator.firmware.skin import DEFAULT_SKIN, SkinModel
from tactdeform_hw.emulator.timed.timing import DEFAULT_MODEL, TimingModel
from tactdeform_hw.errors import LimitError
from tactdeform_hw.protocol import firmware_math as fm
from tactdeform_hw.protocol.constants import (
    DAC_MAX_CODE,
    MAX_ELECTRODES,
    OUTPUTS_PER_HV513,
    PATTERN_BIPHASIC,
    PATTERN_MONOPHASIC,
    SENSE_HEIGHT_SHIFT,
    U8_MAX,
    U16_MAX,
)
from tactdeform_hw.protocol.units import check_int


class Signal(IntEnum):
    """Traced signals.  SEL is the lowest latched HV513 output (-1: none); ADC is a stored 12-bit reading."""

    BL = 0
    LE = 1
    POL = 2
    CLK = 3
    DIN = 4
    DAC = 5
    SEL = 6
    ADC = 7


#: Bit widths for waveform viewers.
SIGNAL_BITS: dict[Signal, int] = {
    Signal.BL: 1,
    Signal.LE: 1,
    Signal.POL: 1,
    Signal.CLK: 1,
    Signal.DIN: 1,
    Signal.DAC: 12,
    Signal.SEL: 9,
    Signal.ADC: 12,
}

#: Signal levels at power-on (assumption: BL and LE idle high as after a scan, POL high, chain clear).
POWER_ON_LEVELS: dict[Signal, int] = {
    Signal.BL: 1,
    Signal.LE: 1,
    Signal.POL: 1,
    Signal.CLK: 0,
    Signal.DIN: 0,
    Signal.DAC: 0,
    Signal.SEL: -1,
    Signal.ADC: 0,
}


class PulseKind(IntEnum):
    MONO = 0  # pattern 1
    BI_ANODIC = 1  # pattern 2, first phase (POL high)
    BI_CATHODIC = 2  # pattern 2, second phase (POL low)
    SENSE = 3  # any other pattern value: sense_pulse_height / sense_pulse_width


class ChannelKind(IntEnum):
    """What a channel's scan step delivers.  v2's stimulation mode takes these values, for every channel."""

    MONO = 0
    BIPHASIC = 1
    SENSE = 2


def channel_kind(pattern_value: int) -> ChannelKind:
    """The kind of a v1.2 channel whose pattern byte is ``pattern_value``: 1 monophasic, 2 biphasic, any
    other value the sense pulse."""
    if pattern_value == PATTERN_MONOPHASIC:
        return ChannelKind.MONO
    if pattern_value == PATTERN_BIPHASIC:
        return ChannelKind.BIPHASIC
    return ChannelKind.SENSE


def pulse_kind_of(kind: int, polarity: int) -> PulseKind:
    """The kind of a pulse delivered on a channel of kind ``kind`` (a :class:`ChannelKind`, or v2's
    stimulation mode) with the POL pin at ``polarity``: a biphasic phase is told by its POL level, and any
    value but monophasic or biphasic is a sense pulse, as the scans read the mode."""
    if kind == ChannelKind.MONO:
        return PulseKind.MONO
    if kind == ChannelKind.BIPHASIC:
        return PulseKind.BI_ANODIC if polarity else PulseKind.BI_CATHODIC
    return PulseKind.SENSE


#: :func:`channel_kind` of every pattern byte, for a whole pattern at once.
_KIND_OF_VALUE = np.array([channel_kind(v) for v in range(256)], dtype=np.int64)


# --- the scan's inputs -------------------------------------------------------------------------------------


@dataclass(frozen=True)
class ChainState:
    """The HV513 chain: the firmware's ``position`` variable and the hardware's shift register / latches
    (bit ``k`` = output ``k``)."""

    position: int = 0
    bits: int = 0
    latched: int = 0
    #: CLK left high by the code the interrupt pre-empted (0xF5's hv513Init() between a CLK high and its CLK
    #: low): the scan's first CLK high is then no rising edge and shifts nothing in
    clk_high: bool = False


POWER_ON_CHAIN = ChainState()


@dataclass(frozen=True)
class ScanConfig:
    """Everything a scan reads from the firmware's registers (the pattern cut to ``electrode_num``)."""

    electrode_num: int = 0
    polarity: int = 1
    pulse_height: int = 0
    pulse_width: int = 0
    sense_pulse_height: int = 0
    sense_pulse_width: int = 0
    discharge_time: int = 0
    alarm_ticks: int = 20_000
    hv513_num: int = 4
    pattern: bytes = b""

    @classmethod
    def from_registers(cls, regs: Registers) -> ScanConfig:
        n = regs.electrode_num
        return cls(
            n,
            regs.polarity,
            regs.pulse_height,
            regs.pulse_width,
            regs.sense_pulse_height,
            regs.sense_pulse_width,
            regs.discharge_time,
            regs.timer_alarm_ticks,
            regs.hv513_num,
            bytes(regs.stim_pattern[:n]),
        )

    @classmethod
    def make(
        cls,
        electrodes: int = 32,
        pattern: int | bytes | list[int] | tuple[int, ...] = 1,
        *,
        pulse_width_us: int = 200,
        pulse_height: int = 100,
        discharge_us: int = 45,
        rate_hz: int = 125,
        polarity: int = 1,
        sense_height_raw: int = 0,
        sense_width_us: int = 0,
        hv513_num: int = 4,
    ) -> ScanConfig:
        """A configuration as a host would set it, each value checked against what the wire carries.

        ``pattern`` is one value for every channel or one per channel; ``sense_height_raw`` is the value
        sent (the firmware stores ``raw << 2``); ``rate_hz`` goes through the firmware's float32 period.
        """
        n = check_int("electrodes", electrodes, 0, MAX_ELECTRODES)
        if isinstance(pattern, (bytes, bytearray, list, tuple)):
            values = [check_int(f"pattern[{i}]", v, 0, U8_MAX) for i, v in enumerate(pattern)]
            if len(values) != n:
                raise LimitError("pattern length", len(values), f"exactly electrodes = {n}")
        else:
            values = [check_int("pattern", pattern, 0, U8_MAX)] * n
        width = check_int("pulse_width_us", pulse_width_us, 1, U16_MAX, "µs")
        height = check_int("pulse_height", pulse_height, 0, DAC_MAX_CODE)
        discharge = check_int("discharge_us", discharge_us, 0, U8_MAX, "µs")
        rate = check_int("rate_hz", rate_hz, 1, U16_MAX, "Hz")
        pol = check_int("polarity", polarity, 0, 1)
        sense_h = check_int("sense_height_raw", sense_height_raw, 0, U8_MAX)
        sense_w = check_int("sense_width_us", sense_width_us, 0, U8_MAX, "µs")
        hv = check_int("hv513_num", hv513_num, 0, U8_MAX)
        ticks = fm.alarm_ticks(fm.period_us_from_rate(rate))
        return cls(
            n, pol, height, width, sense_h << SENSE_HEIGHT_SHIFT, sense_w, discharge, ticks, hv, bytes(values)
        )

    def kinds(self) -> np.ndarray:
        """Per channel: 0 monophasic, 1 biphasic, 2 sense."""
        return _KIND_OF_VALUE[np.frombuffer(self.pattern, dtype=np.uint8)]


# --- costs in closed form (shared by the template builder, the analytic engine and the budget) -----------


@dataclass(frozen=True)
class ChannelCosts:
    """Duration of one channel of each kind and of the fixed parts of a scan, in ns."""

    gpio_ns: int
    select_ns: int  # LE, DIN, one CLK pulse, LE
    pol_ns: int
    pulse_ns: tuple[int, int, int]  # by ChannelKind: the pulse part
    discharge_ns: int
    entry_ns: int
    exit_ns: int

    def channel_ns(self, kind: int) -> int:
        return self.select_ns + self.pol_ns + self.pulse_ns[kind] + self.discharge_ns

    def clear_ns(self, clk_pulses: int) -> int:
        """LE, DIN, the CLK pulses, LE."""
        return (3 + 2 * clk_pulses) * self.gpio_ns


def channel_costs(cfg: ScanConfig, model: TimingModel = DEFAULT_MODEL) -> ChannelCosts:
    return _channel_costs(model, cfg.pulse_width, cfg.sense_pulse_width, cfg.discharge_time)


@lru_cache(maxsize=4096)
def _channel_costs(model: TimingModel, pulse_width: int, sense_width: int, discharge: int) -> ChannelCosts:
    g, s = model.gpio_ns, model.exchange_ns
    mono = 2 * s + model.pulse_wait_ns(pulse_width)
    sense = 2 * s + model.pulse_wait_ns(sense_width)
    bi = 2 * g + 2 * mono
    dis = s + 2 * g + model.discharge_wait_ns(discharge) + g
    return ChannelCosts(g, 5 * g, g, (mono, bi, sense), dis, model.isr_entry_ns, model.isr_exit_ns)


def clear_clk_pulses(cfg: ScanConfig, position_before: int) -> int:
    """CLK pulses of the chain clear: "scan to ``8 * hv513``" from ``position_before``.

    Target 0 takes the ``ch == 0`` branch (DIN high, one pulse).  A target below the position gives no
    pulse (the firmware's loop count ``target - position`` is a signed int — assumption) and the
    position still becomes the target."""
    target = OUTPUTS_PER_HV513 * cfg.hv513_num
    if target == 0:
        return 1
    return max(0, target - position_before)


def scan_duration_ns(
    cfg: ScanConfig, model: TimingModel = DEFAULT_MODEL, position_before: int | None = None
) -> int:
    """From the alarm to the handler's return, in closed form (identical to the step-through)."""
    costs = channel_costs(cfg, model)
    n = cfg.electrode_num
    if n:
        p = cfg.pattern
        c_mono = p.count(PATTERN_MONOPHASIC)
        c_bi = p.count(PATTERN_BIPHASIC)
        body = (
            c_mono * costs.channel_ns(0)
            + c_bi * costs.channel_ns(1)
            + (n - c_mono - c_bi) * costs.channel_ns(2)
        )
    else:
        body = 0
    pos = (n - 1) if n else (position_before or 0)
    return costs.entry_ns + body + costs.clear_ns(clear_clk_pulses(cfg, pos)) + costs.exit_ns


def channel_offsets_ns(cfg: ScanConfig, model: TimingModel = DEFAULT_MODEL) -> tuple[np.ndarray, np.ndarray]:
    """(channel start, first current onset) of every channel, relative to the alarm."""
    costs = channel_costs(cfg, model)
    kinds = cfg.kinds()
    per = np.array([costs.channel_ns(k) for k in range(3)], dtype=np.int64)
    if kinds.size == 0:
        empty = np.zeros(0, dtype=np.int64)
        return empty, empty
    cost = per[kinds]
    starts = costs.entry_ns + np.concatenate(([0], np.cumsum(cost)[:-1]))
    lead = (
        costs.select_ns
        + costs.pol_ns
        + model.dac_in_exchange_ns
        + np.where(kinds == ChannelKind.BIPHASIC, model.gpio_ns, 0)
    )
    return starts, starts + lead


# --- one scan's outputs -------------------------------------------------------------------------------------


class PulseArrays(NamedTuple):
    """Columnar pulse records of one scan (times relative to the alarm, ns)."""

    channel: np.ndarray  # int64
    kind: np.ndarray  # PulseKind
    start_ns: np.ndarray  # current onset: the DAC change of the first exchange
    width_ns: np.ndarray  # onset to the DAC change of the closing exchange
    code: np.ndarray  # DAC code
    pol: np.ndarray  # POL level during the pulse: 1 anodic, 0 cathodic
    current_ua: np.ndarray  # delivered (compliance-limited), unsigned
    charge_nc: np.ndarray
    voltage_code: np.ndarray  # raw >> 2 as stored by the firmware
    adc_ns: np.ndarray  # when the ADC sampled
    limited: np.ndarray  # bool: compliance-limited (or no electrode)
    n_outputs: np.ndarray  # HV513 outputs on during the pulse
    output: np.ndarray  # lowest of them, -1 if none


@dataclass
class ScanResult:
    """One scan as the reference step-through produces it."""

    events: list[tuple[int, int, int]]
    # rows in PulseArrays column order (outputs as a tuple in place of n/lowest)
    pulses: list[tuple[Any, ...]]
    duration_ns: int
    chain_end: ChainState
    voltages: dict[int, int]


def physical_outputs(board_kind: str, switching_boards: int) -> int:
    """HV513 outputs the stack really has (what the firmware would detect with a sound connector)."""
    return OUTPUTS_PER_HV513 * fm.hv513_count(board_kind, switching_boards + 1)


def _lowest(bits: int) -> int:
    return (bits & -bits).bit_length() - 1 if bits else -1


def _outputs(bits: int) -> tuple[int, ...]:
    """The positions of the set bits, lowest first (one step per set bit: a chain has one or two)."""
    out = []
    while bits:
        low = bits & -bits
        out.append(low.bit_length() - 1)
        bits ^= low
    return tuple(out)


# --- the fast path: per-configuration templates -------------------------------------------------------------

_PH_DIN, _PH_SEL, _PH_ADC1, _PH_ADC2 = -101, -102, -103, -104


def _block(
    kind: ChannelKind, cfg: ScanConfig, model: TimingModel
) -> tuple[list[tuple[int, int, int]], list[tuple[int, int, int, int, int, int]], int]:
    """One channel's events relative to its start, with placeholders for the per-channel values, its
    pulses as (phase index, kind, onset, width, code, pol, sample time) and its duration."""
    # an exchange (``DAAD``) from its call: its length, its DAC change, its ADC sample
    g, s, a, c = model.gpio_ns, model.exchange_ns, model.dac_in_exchange_ns, model.adc_in_exchange_ns
    pol = 1 if cfg.polarity else 0
    ev: list[tuple[int, int, int]] = []
    pulses: list[Any] = []
    t = 0
    for sig, val in ((Signal.LE, 0), (Signal.DIN, _PH_DIN), (Signal.CLK, 1), (Signal.CLK, 0), (Signal.LE, 1)):
        t += g
        ev.append((t, int(sig), val))
    ev.append((t, int(Signal.SEL), _PH_SEL))
    t += g
    ev.append((t, int(Signal.POL), pol))

    def mono(pkind: PulseKind, code: int, width: int, p: int, ph: int) -> None:
        nonlocal t
        t0 = t
        ev.append((t0 + a, int(Signal.DAC), code))
        t1 = t0 + s + model.pulse_wait_ns(width)
        ev.append((t1 + c, int(Signal.ADC), ph))
        ev.append((t1 + a, int(Signal.DAC), 0))
        pulses.append((int(pkind), t0 + a, t1 - t0, code, p, t1 + c))
        t = t1 + s

    if kind == ChannelKind.MONO:
        mono(PulseKind.MONO, cfg.pulse_height, cfg.pulse_width, pol, _PH_ADC1)
    elif kind == ChannelKind.BIPHASIC:
        t += g
        ev.append((t, int(Signal.POL), 1))
        mono(PulseKind.BI_ANODIC, cfg.pulse_height, cfg.pulse_width, 1, _PH_ADC1)
        t += g
        ev.append((t, int(Signal.POL), 0))
        mono(PulseKind.BI_CATHODIC, cfg.pulse_height, cfg.pulse_width, 0, _PH_ADC2)
    else:
        mono(PulseKind.SENSE, cfg.sense_pulse_height, cfg.sense_pulse_width, pol, _PH_ADC1)
    ev.append((t + a, int(Signal.DAC), 0))
    t += s
    t += g
    ev.append((t, int(Signal.POL), 1))
    t += g
    ev.append((t, int(Signal.BL), 0))
    t += model.discharge_wait_ns(cfg.discharge_time)
    t += g
    ev.append((t, int(Signal.BL), 1))
    return ev, pulses, t


@dataclass
class ScanTemplate:
    """One scan of one configuration from one chain state: duration, pulses, voltages, events (lazy).

    Times are ns after the alarm; a scan at alarm time ``T`` is this template shifted by ``T``."""

    config: ScanConfig
    chain_start: ChainState
    chain_end: ChainState
    duration_ns: int
    pulses: PulseArrays
    pulse_outputs: list[tuple[int, ...]]
    first_pulse_ns: np.ndarray  # per channel: its first current onset
    voltages: np.ndarray  # per channel: the value stored (last reading of the channel)
    voltage_at_ns: np.ndarray  # per channel: when that reading was sampled
    #: makes the GPIO/DAC event arrays of this template on first demand (they are rarely needed)
    event_builder: Any = field(repr=False, default=None)
    _events: tuple[np.ndarray, np.ndarray, np.ndarray] | None = field(repr=False, default=None)
    #: :meth:`first_of` answers by kinds asked (a template never changes; the timed model asks per scan)
    _firsts: dict[tuple[int, ...] | None, int | None] = field(repr=False, compare=False, default_factory=dict)

    @property
    def steady(self) -> bool:
        """Whether the next scan of the same configuration starts from the same chain state."""
        return self.chain_end == self.chain_start

    def first_of(self, kinds: tuple[int, ...] | None = None) -> int | None:
        """Earliest onset among pulses of the given PulseKinds (all when None); None if there is none."""
        if kinds in self._firsts:
            return self._firsts[kinds]
        first = self._first_of(kinds)
        self._firsts[kinds] = first
        return first

    def _first_of(self, kinds: tuple[int, ...] | None) -> int | None:
        k = self.pulses.kind
        if k.size == 0:
            return None
        if kinds is None:
            return int(self.pulses.start_ns.min())
        m = np.zeros(k.shape, dtype=bool)
        for kind in kinds:  # (a kind or three: cheaper than np.isin's set machinery on a short array)
            m |= k == kind
        return int(self.pulses.start_ns[m].min()) if m.any() else None

    def events(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(time ns, Signal, value) of every GPIO write, DAC change, latch and stored ADC reading."""
        if self._events is None:
            self._events = self.event_builder(self)
        return self._events


#: template, block and skin-outcome caches shared by the engines of one (model, skin, outputs, cache size)
_SHARED_CACHES: dict[tuple[Any, ...], tuple[OrderedDict[Any, Any], dict[Any, Any], dict[Any, Any]]] = {}
_SHARED_CACHE_MODELS = 8  # distinct models kept at once (a campaign uses one or two)


class ScanEngine:
    """Builds, caches and hands out :class:`ScanTemplate` s (LRU over configuration × chain state)."""

    def __init__(
        self,
        model: TimingModel = DEFAULT_MODEL,
        skin: SkinModel = DEFAULT_SKIN,
        outputs: int = 32,
        cache_size: int = 512,
    ) -> None:
        self.model = model
        self.skin = skin
        self.outputs = outputs
        self.cache_size = cache_size
        # A template is a pure function of (timing model, skin, outputs, configuration, chain state) and is
        # never written to, so engines of equal models share their caches: a campaign that builds a new
        # emulator per session builds each scan once, not once per session.
        shared = _SHARED_CACHES.get((model, skin, outputs, cache_size))
        if shared is None:
            if len(_SHARED_CACHES) >= _SHARED_CACHE_MODELS:
                _SHARED_CACHES.clear()
            shared = (OrderedDict(), {}, {})
            _SHARED_CACHES[(model, skin, outputs, cache_size)] = shared
        self._cache: OrderedDict[tuple[ScanConfig, ChainState], ScanTemplate] = shared[0]
        self._blocks: dict[tuple[Any, ...], Any] = shared[1]
        self._outcomes: dict[tuple[int, int, int], Any] = shared[2]
        self.built = 0  # templates this engine built (misses of the shared cache)

    def template(self, cfg: ScanConfig, chain: ChainState = POWER_ON_CHAIN) -> ScanTemplate:
        key = (cfg, chain)
        t = self._cache.get(key)
        if t is not None:
            self._cache.move_to_end(key)
            return t
        t = self._build(cfg, chain)
        self._cache[key] = t
        if len(self._cache) > self.cache_size:
            self._cache.popitem(last=False)
        return t

    # --- building ---------------------------------------------------------------------------------------

    def _blocks_for(self, cfg: ScanConfig) -> Any:
        key = (
            cfg.polarity,
            cfg.pulse_height,
            cfg.pulse_width,
            cfg.sense_pulse_height,
            cfg.sense_pulse_width,
            cfg.discharge_time,
        )
        b = self._blocks.get(key)
        if b is None:
            b = [_block(ChannelKind(k), cfg, self.model) for k in range(3)]
            if len(self._blocks) > 256:
                self._blocks.clear()
            self._blocks[key] = b
        return b

    def _chain_walk(self, cfg: ScanConfig, chain: ChainState) -> tuple[list[int], ChainState, int]:
        """Latched bits after each channel's select, the end state and the clear's CLK pulses."""
        mask = (1 << self.outputs) - 1
        bits, pos = chain.bits, chain.position
        lost = chain.clk_high  # the first CLK pulse's edge is lost (see ChainState.clk_high)
        latched_after: list[int] = []
        for ch in range(cfg.electrode_num):
            if ch == 0:  # a scan's first select: its first CLK pulse
                bits = bits if lost else ((bits << 1) | 1) & mask
                lost = False
            else:
                bits = (bits << (ch - pos)) & mask if ch > pos else bits
            pos = ch
            latched_after.append(bits)
        clear = clear_clk_pulses(cfg, pos)
        target = OUTPUTS_PER_HV513 * cfg.hv513_num
        if target == 0:
            bits = bits if lost else ((bits << 1) | 1) & mask
            lost = False
        elif clear:
            bits = (bits << (clear - 1 if lost else clear)) & mask
            lost = False
        return latched_after, ChainState(target, bits, bits, lost), clear

    def _build(self, cfg: ScanConfig, chain: ChainState) -> ScanTemplate:
        self.built += 1
        model = self.model
        n = cfg.electrode_num
        blocks = self._blocks_for(cfg)
        kinds = cfg.kinds()
        block_len = np.array([b[2] for b in blocks], dtype=np.int64)
        starts = (
            model.isr_entry_ns + np.concatenate(([0], np.cumsum(block_len[kinds])[:-1]))
            if n
            else np.zeros(0, dtype=np.int64)
        )
        latched, chain_end, clear = self._chain_walk(cfg, chain)
        body_end = model.isr_entry_ns + int(block_len[kinds].sum()) if n else model.isr_entry_ns
        g = model.gpio_ns
        duration = body_end + (3 + 2 * clear) * g + model.isr_exit_ns

        # pulses, channel by channel (n <= 255; the skin outcomes are cached per outputs/code/time)
        rows, flo, outs_list, raws, limited, (voltages, v_at, first) = self._pulse_rows(
            n, latched, kinds, starts, blocks
        )
        pulses, raw = _pulse_arrays(rows, flo, raws, limited)
        return ScanTemplate(
            cfg,
            chain,
            chain_end,
            int(duration),
            pulses,
            outs_list,
            first,
            voltages,
            v_at,
            event_builder=(
                lambda t, _raw=raw, _latched=latched, _starts=starts, _kinds=kinds, _c=clear, _b=blocks: (
                    self._events(t, _raw, _latched, _starts, _kinds, _c, _b)
                )
            ),
        )

    def _pulse_rows(
        self,
        n: int,
        latched: list[int],
        kinds: np.ndarray,
        starts: np.ndarray,
        blocks: list[Any],
    ) -> tuple[
        list[tuple[int, ...]],
        list[float],
        list[tuple[int, ...]],
        list[int],
        list[bool],
        tuple[np.ndarray, np.ndarray, np.ndarray],
    ]:
        """Each pulse of a scan as a row (channel, kind, onset, width, code, polarity, voltage code,
        sample time, outputs), its current, outputs, ADC reading and compliance; per channel the stored
        voltage, when it was sampled and the first onset."""
        skin = self.skin
        cache = self._outcomes
        get = cache.get
        blocks_pulses = [b[1] for b in blocks]
        rows: list[tuple[int, ...]] = []
        flo: list[float] = []
        outs_list: list[tuple[int, ...]] = []
        raws: list[int] = []
        limited: list[bool] = []
        # per channel, as Python ints (one numpy array each at the end: no element write per pulse)
        volt_l = [0] * n
        v_at_l = [0] * n
        first_l = [0] * n
        kinds_l = kinds.tolist()
        starts_l = starts.tolist()
        for ch in range(n):
            st = starts_l[ch]
            bits = latched[ch]
            chan_pulses = blocks_pulses[kinds_l[ch]]
            for pk, on, w, code, pol, sample in chan_pulses:
                key = (bits, code, sample - on)
                o = get(key)
                if o is None:
                    outs = _outputs(bits)
                    o = (outs, skin.pulse(outs, code, (sample - on) / 1000.0))
                    if len(cache) > 65536:
                        cache.clear()
                    cache[key] = o
                outs, oc = o
                rows.append(
                    (
                        ch,
                        pk,
                        st + on,
                        w,
                        code,
                        pol,
                        oc.voltage_code,
                        st + sample,
                        len(outs),
                        outs[0] if outs else -1,
                    )
                )
                flo.append(oc.current_ua)
                outs_list.append(outs)
                raws.append(oc.adc_raw)
                limited.append(oc.compliance_limited)
            if chan_pulses:
                first_l[ch] = st + chan_pulses[0][1]
                volt_l[ch] = oc.voltage_code
                v_at_l[ch] = st + chan_pulses[-1][5]
        voltages = np.array(volt_l, dtype=np.int64)
        v_at = np.array(v_at_l, dtype=np.int64)
        first = np.array(first_l, dtype=np.int64)
        return rows, flo, outs_list, raws, limited, (voltages, v_at, first)

    def _events(
        self,
        tmpl: ScanTemplate,
        raw: np.ndarray,
        latched: list[int],
        starts: np.ndarray,
        kinds: np.ndarray,
        clear: int,
        blocks: Any,
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        cfg, model = tmpl.config, self.model
        n = cfg.electrode_num
        ts: list[np.ndarray] = []
        sigs: list[np.ndarray] = []
        vals: list[np.ndarray] = []
        keys: list[np.ndarray] = []
        p = tmpl.pulses
        for k in range(3):
            chs = np.nonzero(kinds == k)[0]
            if chs.size == 0:
                continue
            ev = blocks[k][0]
            bt = np.array([e[0] for e in ev], dtype=np.int64)
            bs = np.array([e[1] for e in ev], dtype=np.int64)
            bv = np.array([e[2] for e in ev], dtype=np.int64)
            T = starts[chs][:, None] + bt[None, :]
            S = np.broadcast_to(bs, T.shape)
            V = np.broadcast_to(bv, T.shape).copy()
            din = np.where(chs == 0, 1, 0)
            sel = np.array([_lowest(latched[c]) for c in chs], dtype=np.int64)
            V[V == _PH_DIN] = 0
            V[:, bv == _PH_DIN] = din[:, None]
            V[:, bv == _PH_SEL] = sel[:, None]
            rows = np.isin(p.channel, chs)
            adc = raw[rows]
            nph = len(blocks[k][1])
            adc = adc.reshape(chs.size, nph)
            V[:, bv == _PH_ADC1] = adc[:, :1]
            if nph > 1:
                V[:, bv == _PH_ADC2] = adc[:, 1:2]
            ts.append(T.ravel())
            sigs.append(S.ravel())
            vals.append(V.ravel())
            keys.append((chs[:, None] * 64 + np.arange(bt.size)[None, :]).ravel())
        # the clear
        g = model.gpio_ns
        t = model.isr_entry_ns + (int(np.sum([blocks[k][2] for k in kinds])) if n else 0)
        target = OUTPUTS_PER_HV513 * cfg.hv513_num
        clear_ev: list[tuple[int, int, int]] = []
        steps = [(Signal.LE, 0), (Signal.DIN, 1 if target == 0 else 0)]
        steps += [(Signal.CLK, 1), (Signal.CLK, 0)] * clear + [(Signal.LE, 1)]
        for sig, val in steps:
            t += g
            clear_ev.append((t, int(sig), val))
        clear_ev.append((t, int(Signal.SEL), _lowest(tmpl.chain_end.latched)))
        ce = np.array(clear_ev, dtype=np.int64).reshape(-1, 3)
        ts.append(ce[:, 0])
        sigs.append(ce[:, 1])
        vals.append(ce[:, 2])
        keys.append(n * 64 + np.arange(len(clear_ev), dtype=np.int64))
        T = np.concatenate(ts)
        S = np.concatenate(sigs)
        V = np.concatenate(vals)
        order = np.argsort(np.concatenate(keys), kind="stable")
        return T[order], S[order].astype(np.int8), V[order]


#: The engine's pin signals as the firmware's pins (the selected output and the ADC are no pins).
_PIN_OF_SIGNAL = {
    int(Signal.BL): BL,
    int(Signal.LE): LE,
    int(Signal.POL): POL,
    int(Signal.CLK): CLK,
    int(Signal.DIN): DIN,
}


def firmware_trace(tmpl: ScanTemplate, model: TimingModel = DEFAULT_MODEL) -> list[list[Any]]:
    """One scan as the firmware's own code logs it built on a host (``tests/data/scan_traces_v12.jsonl``),
    in the handler's order: ``[t_ns, "GPIO", pin, level]`` for every pin write, the chip selects included,
    and ``[t_ns, "DAC", "DAC", code]`` for every DAC change (ns after the alarm).

    Every exchange changes the DAC once, so each DAC change places its exchange, and the chip selects are
    that exchange's edges: lowered before it and raised after it (DA_CS then AD_CS, one write each, or
    both in one write), each write one GPIO write long when the model costs them and at the exchange's
    own ends when it does not.  The DAC change lies between the raising writes when it loads as DA_CS
    rises (costed), before them otherwise."""
    w = model.cs_write_ns
    edge = [[DA_CS], [AD_CS]] if model.chip_select_writes == 4 else [[AD_CS, DA_CS]]
    out: list[list[Any]] = []

    def chip_selects(at_ns: int, level: int, groups: list[list[int]], first: int = 1) -> None:
        for k, pins in enumerate(groups, first):
            out.extend([at_ns + k * w, "GPIO", pin, level] for pin in pins)

    t, sig, val = tmpl.events()
    for at, signal, value in zip(t.tolist(), sig.tolist(), val.tolist(), strict=True):
        if signal == Signal.DAC:
            call = at - model.dac_in_exchange_ns
            spi_end = call + model.exchange_lead_ns + model.spi_ns
            chip_selects(call, 0, edge)
            if model.dac_load == "cs_rise" and w:
                chip_selects(spi_end, 1, edge[:1])
                out.append([at, "DAC", "DAC", value])
                chip_selects(spi_end, 1, edge[1:], first=2)
            else:
                out.append([at, "DAC", "DAC", value])
                chip_selects(spi_end, 1, edge)
        elif signal in _PIN_OF_SIGNAL:
            out.append([at, "GPIO", _PIN_OF_SIGNAL[signal], value])
    return out


class ScanVoltages:
    """The untimed emulator's ``scan`` seam: before each delivery, store the readings a scan of the
    current registers takes, so measure replies carry the skin model's values
    (``emulator.scan = ScanVoltages()``)."""

    def __init__(self, model: TimingModel = DEFAULT_MODEL, skin: SkinModel = DEFAULT_SKIN) -> None:
        self.model = model
        self.skin = skin
        self._engine: ScanEngine | None = None
        self._chain = POWER_ON_CHAIN

    def __call__(self, emulator: Any) -> None:
        if self._engine is None:
            board = emulator.board
            self._engine = ScanEngine(
                self.model, self.skin, physical_outputs(board.kind, board.switching_boards)
            )
        regs = emulator.registers
        t = self._engine.template(ScanConfig.from_registers(regs), self._chain)
        self._chain = t.chain_end
        regs.voltage[: t.voltages.size] = t.voltages.tolist()


def _pulse_arrays(
    rows: list[tuple[int, ...]], flo: list[float], raws: list[int], limited: list[bool]
) -> tuple[PulseArrays, np.ndarray]:
    """The pulse rows as the columns of :class:`PulseArrays`, and the raw ADC readings."""
    m = len(rows)
    a = np.fromiter(_chained.from_iterable(rows), dtype=np.int64, count=10 * m).reshape(m, 10)
    cur = np.array(flo, dtype=np.float64)
    raw = np.array(raws, dtype=np.int64)
    pulses = PulseArrays(
        a[:, 0],
        a[:, 1],
        a[:, 2],
        a[:, 3],
        a[:, 4],
        a[:, 5],
        cur,
        cur * a[:, 3] / 1e6,
        a[:, 6],
        a[:, 7],
        np.array(limited, dtype=bool),
        a[:, 8],
        a[:, 9],
    )
    return pulses, raw
