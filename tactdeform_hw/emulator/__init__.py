"""The eTactileKit firmware and board, emulated byte for byte (and, in ``timed``, microsecond for
microsecond)."""

from .board import Board
from .core import Emulator
from .hazards import Hazard, HazardKind
from .parser import CallResult, Parser
from .registers import Registers

__all__ = ["Board", "CallResult", "Emulator", "Hazard", "HazardKind", "Parser", "Registers"]
