"""The controller and its stacked switching boards, as far as the firmware can see them."""

from __future__ import annotations

from dataclasses import dataclass

from tactdeform_hw.errors import ConfigurationError
from tactdeform_hw.protocol import firmware_math as fm

BOARD_KINDS = ("compact", "large")

#: The controller's pins as the firmware names them (configuration.h, both versions): the HV513 chain's
#: BL, LE, POL, CLK and DIN, and the chip selects of the ADC and the DAC.
BL, LE, POL, CLK, DIN, AD_CS, DA_CS = 1, 2, 3, 4, 5, 43, 44


@dataclass
class Board:
    """Board kind and stack.  ``stack_reading`` overrides the averaged analog reading the firmware uses to
    count boards (e.g. a loose connector); by default it is the reading the stack really produces."""

    kind: str = "compact"
    switching_boards: int = 1
    stack_reading: float | None = None

    def __post_init__(self) -> None:
        if self.kind not in BOARD_KINDS:
            raise ConfigurationError(f"board={self.kind!r} is not one of {', '.join(BOARD_KINDS)}")
        if (
            isinstance(self.switching_boards, bool)
            or not isinstance(self.switching_boards, int)
            or not 0 <= self.switching_boards <= 16
        ):
            raise ConfigurationError(f"switching_boards={self.switching_boards!r} is out of range: 0 to 16")

    def reading(self) -> float:
        if self.stack_reading is not None:
            return self.stack_reading
        return fm.reading_for_stack(self.switching_boards + 1)  # the controller counts as one board

    def detect_hv513(self) -> int:
        """What the firmware's detection returns: HV513 chips by board kind and the sensed stack."""
        return fm.hv513_count(self.kind, fm.stack_count_from_reading(self.reading()))
