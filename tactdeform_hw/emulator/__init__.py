"""The eTactileKit firmware and board, emulated byte for byte (and, in ``timed``, microsecond for
microsecond)."""

from tactdeform_hw.emulator.firmware.board import Board
from tactdeform_hw.emulator.firmware.hazards import Hazard, HazardKind
from tactdeform_hw.emulator.firmware.parser import CallResult, Parser
from tactdeform_hw.emulator.firmware.registers import Registers

from .core import Emulator

__all__ = ["Board", "CallResult", "Emulator", "Hazard", "HazardKind", "Parser", "Registers"]
