"""The firmware's own arithmetic for values the host sets, so host and emulator compute them identically.

The period is held as a 32-bit float and the timer alarm as ``uint32(period) * 2`` ticks of 0.5 µs: a
rate that does not divide 1 000 000 evenly runs slightly faster than asked.  Hosts that budget scan time
must use these numbers, not ``1e6 / rate``.
"""

from __future__ import annotations

import functools
from collections.abc import Sequence

import numpy as np

from .constants import (
    OUTPUTS_PER_HV513,
    PATTERN_BIPHASIC,
    PATTERN_MONOPHASIC,
    STACK_SENSE_NUMERATOR,
    STACK_SENSE_OFFSET,
    TIMER_TICKS_PER_US,
)
from .firmware import DEFAULT_FIRMWARE, FirmwareSpec, FirmwareTiming


def period_us_from_rate(rate_hz: int) -> float:
    """``period_us = 1e6 / v`` stored as float32 (returned as the Python float of that float32)."""
    return float(np.float32(np.float32(1_000_000.0) / np.float32(rate_hz)))


def period_us_from_rate_double(rate_hz: int) -> float:
    """v2's ``StimulationTimePeriod = 1000000.0 / v``: a double division stored into a float32."""
    return float(np.float32(1_000_000.0 / rate_hz))


def alarm_ticks(period_us: float) -> int:
    """``uint32(period_us) * 2``: the truncated period in 0.5 µs timer ticks."""
    return (int(period_us) & 0xFFFFFFFF) * TIMER_TICKS_PER_US


def stack_count_from_reading(reading: float) -> int:
    """``round(9368.8636 / r - 1.51)``: stacked boards (controller included) from the averaged ADC reading."""
    if reading <= 0:
        return 0
    return int(round(STACK_SENSE_NUMERATOR / reading - STACK_SENSE_OFFSET))


def reading_for_stack(stack_count: int) -> float:
    """The averaged analog reading a stack of ``stack_count`` boards produces (the model's inverse)."""
    return float(round(STACK_SENSE_NUMERATOR / (stack_count + STACK_SENSE_OFFSET)))


def hv513_count(board_kind: str, stack_count: int) -> int:
    """HV513 chips the firmware believes it drives, by board kind and detected stack count."""
    if board_kind == "compact":
        return (stack_count - 1) * 4 if stack_count >= 1 else 0
    if board_kind == "large":
        if stack_count >= 2:
            return (stack_count - 1) * 8
        return 1
    raise ValueError(f"board kind {board_kind!r} is not 'compact' or 'large'")


def channels_driven(hv513: int) -> int:
    return hv513 * OUTPUTS_PER_HV513


@functools.lru_cache(maxsize=64)
def firmware_period_us(rate_hz: int) -> float:
    """The alarm period the firmware derives from a rate (float32 division, truncated to whole µs);
    cached, as every frame asks for it."""
    return float(int(period_us_from_rate(rate_hz)))


def monophasic_us(width_us: int, timing: FirmwareTiming = DEFAULT_FIRMWARE.timing) -> float:
    """``monophasic(h, w)``: the DAC exchange, the busy-wait (only for ``w >= 7``), the exchange back to 0."""
    return 2 * timing.spi_exchange_us + timing.pulse_wait_us(width_us)


@functools.lru_cache(maxsize=256)
def _scan_parts(
    t: FirmwareTiming, width_us: int, discharge_us: int, sense_width_us: int, hv513: int
) -> tuple[float, float, float, float]:
    """Interrupt entry and chain clear; and one channel's time at pattern 1, 2 and anything else (select,
    POL, the pulse, the discharge).  Cached: every frame's budget needs them for the same settings."""
    gpio = t.gpio_write_us
    mono = monophasic_us(width_us, t)
    sense = monophasic_us(sense_width_us, t)
    discharge = (
        (t.spi_exchange_us if t.discharge_exchange else 0.0) + 3 * gpio + t.discharge_wait_us(discharge_us)
    )
    select = 5 * gpio  # LE, DIN, CLK, LE; then POL (one more write)
    base = t.isr_entry_us + 2 * gpio * OUTPUTS_PER_HV513 * max(hv513, 1)
    return (
        base,
        select + gpio + mono + discharge,
        select + gpio + (2 * mono + 2 * gpio) + discharge,
        select + gpio + sense + discharge,
    )


def estimate_scan_us(
    levels: Sequence[int],
    width_us: int,
    discharge_us: int,
    sense_width_us: int = 0,
    hv513: int = 4,
    firmware: FirmwareSpec = DEFAULT_FIRMWARE,
) -> float:
    """One scan of ``levels`` (hardware order, one per channel the firmware scans), from the firmware's
    order of operations: select (LE, DIN, CLK), POL, the pulse (1: monophasic, 2: two phases, anything
    else: the sense pulse), the discharge (with its ``DAAD(0)`` exchange where the firmware has one) and
    busy-wait; plus interrupt entry and the chain clear.  Rounded up by 0.5 % + 2 µs so that it errs long.

    This is the host's budget (the device layer paces and refuses frames with it); the emulator's scan
    engine times the same sequence event by event from the same constants."""
    key = levels if type(levels) is bytes else tuple(levels)
    return _estimate_scan_us(key, width_us, discharge_us, sense_width_us, hv513, firmware)


@functools.lru_cache(maxsize=1024)
def _estimate_scan_us(
    levels: bytes | tuple[int, ...],
    width_us: int,
    discharge_us: int,
    sense_width_us: int,
    hv513: int,
    firmware: FirmwareSpec,
) -> float:
    """:func:`estimate_scan_us`, cached: the driver, its guard and a campaign's judge each ask for the
    same frame's scan (the firmware table is keyed by identity; the sum keeps the order of the levels)."""
    base, mono, bi, sense = _scan_parts(firmware.timing, width_us, discharge_us, sense_width_us, hv513)
    total = base
    for v in levels:
        total += mono if v == PATTERN_MONOPHASIC else bi if v == PATTERN_BIPHASIC else sense
    return total * 1.005 + 2.0
