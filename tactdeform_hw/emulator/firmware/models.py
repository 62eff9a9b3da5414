"""Which model runs which firmware version: the one place the emulator chooses by version.

Every firmware version the emulator runs has one :class:`ModelEntry` in :data:`MODELS`, keyed by its
:class:`~tactdeform_hw.protocol.firmware.FirmwareSpec`: its registers and parser (both keep the
:class:`~.contract.FirmwareParser` contract), its scan engine and its timed model.  The untimed
:class:`~tactdeform_hw.emulator.core.Emulator`, ``timed_emulator``, the real-time server, the emulated
USB device and the ``etactile://`` URL handler all look a version up here (:func:`model_entry`, which
parses a user's words with :func:`~tactdeform_hw.protocol.firmware.get_firmware`), so none of them
compares version names; what differs between versions is in the entry or in the version's table
(``partial_payload_applied``, ``command_timeout_us``, ``yield_rule``, ``hv513_pauses_timer``).

Adding a version: its table in :mod:`tactdeform_hw.protocol.firmware`, its registers, parser, scan and
timed model, and one entry here.
"""

from __future__ import annotations

import importlib
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from types import MappingProxyType
from typing import TYPE_CHECKING, Any, Protocol, TypeVar

from tactdeform_hw.emulator.firmware.contract import CallOutcome, FirmwareParser
from tactdeform_hw.emulator.firmware.hazards import Hazard
from tactdeform_hw.emulator.firmware.parser import Parser
from tactdeform_hw.emulator.firmware.parser_v2 import ParserV2
from tactdeform_hw.emulator.firmware.registers import Registers, RegistersV2
from tactdeform_hw.protocol.firmware import V1_2, V2, FirmwareSpec, get_firmware
from tactdeform_hw.protocol.state import BoardState

if TYPE_CHECKING:
    from tactdeform_hw.emulator.timed.base import TimedModel, TimedModelBase

#: The registers of any version (their fields differ: v1.2's ``pulse_height``, v2's ``stim_mode``).
BoardRegisters = Registers | RegistersV2

_Part = TypeVar("_Part")


def entry_part(part: object, cls: type[_Part]) -> _Part:
    """``part``, one of an emulator's registers or parser, as ``cls``, the class its version's entry makes.

    The emulator types its parts as any version's; a model of one version reads its own fields (v1.2's
    ``pulse_height``, v2's ``stim_mode``) and states here, once, which class its entry gave it."""
    assert isinstance(part, cls), f"{type(part).__name__} is not the {cls.__name__} of this version's entry"
    return part


class FirmwareModel(Protocol):
    """A firmware version's observable behaviour without time: bytes in, one parser call or every call
    until a time, replies out, a typed state.  :class:`~tactdeform_hw.emulator.core.Emulator` is it for
    every version."""

    firmware: FirmwareSpec
    hazards: list[Hazard]
    received_bytes: int

    def feed(self, data: bytes, at_us: int | None = None) -> bytes: ...

    def call(self) -> CallOutcome: ...

    def advance(self, to_us: int) -> bytes: ...

    def state(self) -> BoardState: ...

    def reset(self) -> None: ...


@dataclass(frozen=True)
class ModelEntry:
    """One firmware version's models.

    ``registers``: the class of its globals; ``parser``: its parser's class (called with the registers,
    the hazard list and the board's stack detection).
    ``parser_owns_queue``: the parser holds the firmware's receive queue (v2: the 1024-byte HWCDC queue,
    whose drops and pending command are part of the board's state); otherwise the queue and its losses
    are the timed model's.  ``scan_module``: the scan engine the timed model runs (its docstring says how
    it is held to the firmware's statements).  ``timed_model``: ``"module:Class"`` of the timed model,
    loaded when first asked for (the timed models import the untimed one, which imports this registry).
    """

    spec: FirmwareSpec
    registers: type[Registers] | type[RegistersV2]
    parser: Callable[[Any, list[Hazard], Callable[[], int]], FirmwareParser]
    parser_owns_queue: bool
    scan_module: str
    timed_model: str

    def parts(
        self, hazards: list[Hazard], detect_hv513: Callable[[], int]
    ) -> tuple[BoardRegisters, FirmwareParser]:
        """The registers at power-on (the stack sensed once) and the parser over them."""
        regs = self.registers(hv513_num=detect_hv513())
        return regs, self.parser(regs, hazards, detect_hv513)

    def timed_class(self) -> type[TimedModelBase]:
        """The timed model's class."""
        module, name = self.timed_model.split(":")
        cls: type[TimedModelBase] = getattr(importlib.import_module(module), name)
        return cls

    def timed(self, board: Any = "compact", switching_boards: int = 1, **kwargs: Any) -> TimedModel:
        """A timed model of this version (keyword arguments: the timed model's own)."""
        cls: Any = self.timed_class()  # a concrete class (TimedModel itself is a Protocol)
        model: TimedModel = cls(board, switching_boards, **kwargs)
        return model


#: Every firmware version the emulator runs, by its table.
MODELS: Mapping[FirmwareSpec, ModelEntry] = MappingProxyType(
    {
        V1_2: ModelEntry(
            spec=V1_2,
            registers=Registers,
            parser=Parser,
            parser_owns_queue=False,
            scan_module="tactdeform_hw.emulator.firmware.scan",
            timed_model="tactdeform_hw.emulator.timed.model_v1_2:TimedEmulator",
        ),
        V2: ModelEntry(
            spec=V2,
            registers=RegistersV2,
            parser=ParserV2,
            parser_owns_queue=True,
            scan_module="tactdeform_hw.emulator.firmware.firmware_scan",
            timed_model="tactdeform_hw.emulator.timed.model_v2:TimedEmulatorV2",
        ),
    }
)


def model_entry(firmware: str | FirmwareSpec, field_name: str = "firmware") -> ModelEntry:
    """The models of ``firmware`` (a version's name as a user writes it, or its table); an unknown
    version is refused naming the value and the choices."""
    return MODELS[get_firmware(firmware, field_name)]


__all__ = ["MODELS", "BoardRegisters", "FirmwareModel", "ModelEntry", "entry_part", "model_entry"]
