"""The firmware's global variables, with their power-on values."""

from __future__ import annotations

from typing import Any

from tactdeform_hw.protocol import firmware_math as fm
from tactdeform_hw.protocol.constants import PATTERN_BUFFER_SIZE, POWER_ON_PERIOD_US, POWER_ON_POLARITY


def _snapshot(regs: Registers | RegistersV2) -> dict[str, Any]:
    """Every register but the voltages (read only by a measure request), the pattern as a copy."""
    out = {name: getattr(regs, name) for name in regs.__slots__ if name != "voltage"}
    out["stim_pattern"] = list(regs.stim_pattern)
    return out


class Registers:
    """Plain attributes (the parser's hot loop touches them); ``snapshot`` hands out copies."""

    __slots__ = (
        "electrode_num",
        "polarity",
        "pulse_height",
        "pulse_width",
        "sense_pulse_height",
        "sense_pulse_width",
        "discharge_time",
        "period_us",
        "timer_alarm_ticks",
        "hv513_num",
        "stim_pattern",
        "voltage",
    )

    def __init__(self, hv513_num: int = 0) -> None:
        self.electrode_num = 0
        self.polarity = POWER_ON_POLARITY
        self.pulse_height = 0
        self.pulse_width = 0
        self.sense_pulse_height = 0
        self.sense_pulse_width = 0
        self.discharge_time = 0
        self.period_us = POWER_ON_PERIOD_US
        self.timer_alarm_ticks = fm.alarm_ticks(POWER_ON_PERIOD_US)
        self.hv513_num = hv513_num
        self.stim_pattern = bytearray(PATTERN_BUFFER_SIZE)
        # voltage[ch] holds the ADC reading (raw >> 2) of the channel's last pulse; 0 until a scan runs.
        self.voltage = [0] * PATTERN_BUFFER_SIZE

    def snapshot(self) -> dict[str, Any]:
        return _snapshot(self)


#: The v2 registers a scan reads once, at its start (``etk.cpp:110-116``): what the timed model snapshots
#: per scan, and the parameters a v2 golden vector's ``expect`` names first.
V2_SCAN_REGISTERS = (
    "electrode_num",
    "polarity",
    "stim_mode",
    "pulse_width",
    "sense_pulse_height",
    "sense_pulse_width",
    "discharge_time",
)


class RegistersV2:
    """The v2 firmware's globals (``etk.cpp:3-22``): per-electrode u16 heights, a stimulation mode and
    no global pulse height."""

    __slots__ = (
        *V2_SCAN_REGISTERS,
        "period_us",
        "timer_alarm_ticks",
        "hv513_num",
        "stim_pattern",
        "voltage",
    )

    def __init__(self, hv513_num: int = 0) -> None:
        self.electrode_num = 0
        self.polarity = POWER_ON_POLARITY
        self.stim_mode = 0
        self.pulse_width = 0
        self.sense_pulse_height = 0
        self.sense_pulse_width = 0
        self.discharge_time = 0
        self.period_us = POWER_ON_PERIOD_US
        self.timer_alarm_ticks = fm.alarm_ticks(POWER_ON_PERIOD_US)
        self.hv513_num = hv513_num
        self.stim_pattern = [0] * PATTERN_BUFFER_SIZE
        # voltage[ch]: the u16 the scan stored for the channel (the second phase's reading when biphasic).
        self.voltage = [0] * PATTERN_BUFFER_SIZE

    def snapshot(self) -> dict[str, Any]:
        return _snapshot(self)
