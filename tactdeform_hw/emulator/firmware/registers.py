"""The firmware's global variables, with their power-on values."""

from __future__ import annotations

from typing import Any, ClassVar

from tactdeform_hw.protocol import firmware_math as fm
from tactdeform_hw.protocol.constants import PATTERN_BUFFER_SIZE, POWER_ON_PERIOD_US, POWER_ON_POLARITY
from tactdeform_hw.protocol.firmware import V1_2, V2, FirmwareSpec
from tactdeform_hw.protocol.state import BoardState


class _RegisterFile:
    """The globals every version has, at their power-on values.  Plain slotted attributes: the parser's
    hot loop touches them."""

    __slots__ = (
        "electrode_num",
        "polarity",
        "pulse_width",
        "sense_pulse_height",
        "sense_pulse_width",
        "discharge_time",
        "period_us",
        "timer_alarm_ticks",
        "hv513_num",
        "voltage",
    )

    #: The version whose globals these are: the board state's version.
    firmware: ClassVar[FirmwareSpec]

    def __init__(self, hv513_num: int) -> None:
        self.electrode_num = 0
        self.polarity = POWER_ON_POLARITY
        self.pulse_width = 0
        self.sense_pulse_height = 0
        self.sense_pulse_width = 0
        self.discharge_time = 0
        self.period_us = POWER_ON_PERIOD_US
        self.timer_alarm_ticks = fm.alarm_ticks(POWER_ON_PERIOD_US)
        self.hv513_num = hv513_num
        self.voltage = [0] * PATTERN_BUFFER_SIZE

    def variables(self) -> dict[str, Any]:
        """Every global by its name in the firmware's source (the attribute names are those names)."""
        return {
            name: getattr(self, name) for cls in type(self).__mro__ for name in getattr(cls, "__slots__", ())
        }

    def board_state(
        self, rx_pending: int, rx_dropped: int | None = None, command_in_progress: bool | None = None
    ) -> BoardState:
        """These registers as a :class:`BoardState`; the register this version lacks (v1.2's stimulation
        mode, v2's global pulse height) is ``None`` there."""
        return BoardState.from_variables(
            self.firmware,
            self.variables(),
            rx_pending=rx_pending,
            rx_dropped=rx_dropped,
            command_in_progress=command_in_progress,
        )


class Registers(_RegisterFile):
    """The v1.2 firmware's globals: one global pulse height, one pattern byte per electrode.
    ``voltage[ch]`` holds the ADC reading (raw >> 2) of the channel's last pulse; 0 until a scan runs."""

    __slots__ = ("pulse_height", "stim_pattern")
    firmware = V1_2

    def __init__(self, hv513_num: int = 0) -> None:
        super().__init__(hv513_num)
        self.pulse_height = 0
        self.stim_pattern = bytearray(PATTERN_BUFFER_SIZE)


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


class RegistersV2(_RegisterFile):
    """The v2 firmware's globals (``etk.cpp:3-22``): per-electrode u16 heights, a stimulation mode and
    no global pulse height.  ``voltage[ch]``: the u16 the scan stored for the channel (the second phase's
    reading when biphasic)."""

    __slots__ = ("stim_mode", "stim_pattern")
    firmware = V2

    def __init__(self, hv513_num: int = 0) -> None:
        super().__init__(hv513_num)
        self.stim_mode = 0
        self.stim_pattern = [0] * PATTERN_BUFFER_SIZE
