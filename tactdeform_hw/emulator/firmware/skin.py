"""A small electrode–skin model, so measure replies carry plausible, repeatable voltages.

The firmware stores, for each channel, the ADC reading the SPI exchange returns as the pulse ends
(``raw >> 2``).  On a real fingertip that reading depends on the electrode's contact, which no host can
know in advance; the emulator therefore needs *a* model, and this one is chosen to be simple, documented
and deterministic rather than faithful to any one participant:

* **Impedance** — each electrode is the classic three-element skin circuit: a series resistance
  ``R_s`` (electrode, stratum corneum access) in series with ``R_p ‖ C_p`` (the skin's capacitive
  layer).  Under a constant current ``I`` the electrode voltage rises as
  ``V(t) = I · (R_s + R_p · (1 - exp(-t / (R_p C_p))))``.
* **Per-electrode spread** — every electrode's contact differs by a factor ``k`` in
  ``[1 - spread, 1 + spread]`` drawn from a fixed integer hash of the electrode index (different per
  electrode, identical on every run and every machine), read as 1 / relative contact area: both
  resistances are multiplied by ``k`` and the capacitance divided by it.  ``impedances`` overrides single
  electrodes and ``open_electrodes`` lifts electrodes off the skin entirely.
* **Compliance** — the current source cannot drive the electrode above ``compliance_v``.  When the
  voltage the set current needs at the end of the pulse exceeds it, the delivered current is taken as
  ``compliance_v / Z(t_end)`` for the whole pulse (a conservative estimate of the charge: the real source
  delivers the set current until it saturates).  An open electrode (or a channel the HV513 chain does not
  reach) takes no current and reads the compliance voltage.
* **ADC scaling** — the electrode voltage reaches the ADC through a divider: ``adc_full_scale_v`` reads
  as the 12-bit full scale 4095; the firmware keeps ``raw >> 2``.  Readings are sampled while the pulse
  flows, just before the DAC returns to 0.
* **Biphasic phases** each start from an uncharged skin capacitance (the discharge between phases is not
  modelled).

Nominal values (all labelled assumptions): ``R_s`` 2 kΩ, ``R_p`` 30 kΩ, ``C_p`` 10 nF (τ = 300 µs),
spread ±20 %, compliance 300 V, ADC full scale 330 V.  With them a 1 mA, 200 µs pulse reads about 16 V;
10 mA at 65 ms hits the compliance limit.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from functools import lru_cache

from tactdeform_hw.errors import ConfigurationError
from tactdeform_hw.protocol.units import DEFAULT_TRANSFER, CurrentTransfer

ADC_FULL_SCALE_CODE = 4095
VOLTAGE_SHIFT = 2  # the firmware stores raw >> 2


@dataclass(frozen=True)
class ElectrodeImpedance:
    """One electrode's skin circuit (kΩ, kΩ, nF)."""

    r_series_kohm: float
    r_parallel_kohm: float
    c_parallel_nf: float

    def __post_init__(self) -> None:
        for name in ("r_series_kohm", "r_parallel_kohm", "c_parallel_nf"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v >= 0):
                raise ConfigurationError(f"{name}={v!r} must be a finite number >= 0")

    def impedance_kohm(self, t_us: float) -> float:
        """Apparent impedance ``V(t)/I`` after ``t_us`` of constant current."""
        tau_us = self.r_parallel_kohm * self.c_parallel_nf  # kΩ·nF = µs
        if tau_us <= 0:
            return self.r_series_kohm + self.r_parallel_kohm
        return self.r_series_kohm + self.r_parallel_kohm * (1.0 - math.exp(-max(t_us, 0.0) / tau_us))


@dataclass(frozen=True)
class PulseOutcome:
    """What one pulse delivered and what the firmware reads back."""

    current_ua: float  # delivered (after the compliance limit), unsigned
    voltage_v: float  # electrode voltage at the ADC sample
    compliance_limited: bool
    adc_raw: int  # 12-bit reading
    voltage_code: int  # what the firmware stores: raw >> 2


def _hash01(i: int) -> float:
    """A fixed integer hash (splitmix64) of ``i`` mapped to [0, 1): per-electrode, platform-independent."""
    z = (i + 0x9E3779B97F4A7C15) & 0xFFFFFFFFFFFFFFFF
    z = ((z ^ (z >> 30)) * 0xBF58476D1CE4E5B9) & 0xFFFFFFFFFFFFFFFF
    z = ((z ^ (z >> 27)) * 0x94D049BB133111EB) & 0xFFFFFFFFFFFFFFFF
    z ^= z >> 31
    return (z >> 11) / float(1 << 53)


@dataclass(frozen=True)
class SkinModel:
    """Electrode–skin impedance, compliance limit and ADC scaling (see the module text)."""

    r_series_kohm: float = 2.0
    r_parallel_kohm: float = 30.0
    c_parallel_nf: float = 10.0
    spread: float = 0.2
    compliance_v: float = 300.0
    adc_full_scale_v: float = 330.0
    transfer: CurrentTransfer = DEFAULT_TRANSFER
    impedances: Mapping[int, ElectrodeImpedance] | tuple[tuple[int, ElectrodeImpedance], ...] = ()
    open_electrodes: frozenset[int] = frozenset()
    _by_index: dict[int, ElectrodeImpedance] = field(init=False, repr=False, compare=False, hash=False)
    #: the nominal circuits made so far (a pure function of the fields above; a template build asks per pulse)
    _nominal: dict[int, ElectrodeImpedance] = field(init=False, repr=False, compare=False, hash=False)

    def __post_init__(self) -> None:
        for name in ("r_series_kohm", "r_parallel_kohm", "c_parallel_nf", "compliance_v"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v >= 0):
                raise ConfigurationError(f"{name}={v!r} must be a finite number >= 0")
        if not (math.isfinite(self.spread) and 0 <= self.spread < 1):
            raise ConfigurationError(f"spread={self.spread!r} must be in [0, 1)")
        if not (math.isfinite(self.adc_full_scale_v) and self.adc_full_scale_v > 0):
            raise ConfigurationError(f"adc_full_scale_v={self.adc_full_scale_v!r} must be > 0")
        items = dict(self.impedances.items() if isinstance(self.impedances, Mapping) else self.impedances)
        object.__setattr__(self, "impedances", tuple(sorted(items.items())))
        object.__setattr__(self, "open_electrodes", frozenset(self.open_electrodes))
        object.__setattr__(self, "_by_index", items)
        object.__setattr__(self, "_nominal", {})

    def electrode(self, index: int) -> ElectrodeImpedance:
        """Electrode ``index``'s circuit: an override, or the nominal one scaled by its fixed factor."""
        found = self._by_index.get(index)
        if found is not None:
            return found
        found = self._nominal.get(index)
        if found is None:
            k = 1.0 + self.spread * (2.0 * _hash01(index) - 1.0)
            # a smaller contact area: resistances up, capacitance down (k is 1 / relative area)
            found = ElectrodeImpedance(
                self.r_series_kohm * k, self.r_parallel_kohm * k, self.c_parallel_nf / k
            )
            self._nominal[index] = found
        return found

    def pulse(self, outputs: tuple[int, ...], code: int, sample_after_us: float) -> PulseOutcome:
        """One pulse of DAC ``code`` into the electrodes ``outputs`` (the HV513 outputs that are on),
        sampled ``sample_after_us`` after the current started."""
        return _pulse_cached(self, outputs, code, round(sample_after_us, 6))

    def adc_of_voltage(self, voltage_v: float) -> int:
        v = min(max(voltage_v, 0.0), self.adc_full_scale_v)
        return int(round(v / self.adc_full_scale_v * ADC_FULL_SCALE_CODE))


@lru_cache(maxsize=65536)
def _pulse_cached(skin: SkinModel, outputs: tuple[int, ...], code: int, t_us: float) -> PulseOutcome:
    set_ua = abs(skin.transfer.to_ua(code)) if code else 0.0
    live = [o for o in outputs if o not in skin.open_electrodes]
    if not live:
        # no path: the source rises to its compliance and no charge flows (unless nothing is asked)
        v = skin.compliance_v if set_ua > 0 else 0.0
        raw = skin.adc_of_voltage(v)
        return PulseOutcome(0.0, v, set_ua > 0, raw, raw >> VOLTAGE_SHIFT)
    # electrodes in parallel share the current: 1/Z = sum(1/Z_i)
    conductance = 0.0
    for o in live:
        z = skin.electrode(o).impedance_kohm(t_us)
        conductance += math.inf if z <= 0 else 1.0 / z
    z_kohm = 0.0 if math.isinf(conductance) else 1.0 / conductance
    v = set_ua * z_kohm / 1000.0  # µA · kΩ = mV
    limited = v > skin.compliance_v
    current = set_ua
    if limited:
        current = skin.compliance_v * 1000.0 / z_kohm
        v = skin.compliance_v
    raw = skin.adc_of_voltage(v)
    return PulseOutcome(current, v, limited, raw, raw >> VOLTAGE_SHIFT)


DEFAULT_SKIN = SkinModel()
