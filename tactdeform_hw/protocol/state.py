"""What an emulated board holds, as one typed value: the firmware's registers and its receive queue.

An emulated board can show its registers and a real one cannot; the driver's read-back, the CLI, the
study and the tests read them.  They used to read a ``dict`` by key, so a misspelt or version-specific
name failed only when that line ran.  :class:`BoardState` names every register once, with its unit where
it has one; a register a firmware version lacks is ``None`` (v1.2 has no stimulation mode, v2 no global
pulse height), so a reader says which version it expects by the field it reads.

The golden vectors' ``expect`` objects and the JSON the tools write use the firmware's own variable
names (``pulse_width``, ``discharge_time``): :meth:`BoardState.as_dict` gives exactly those keys, and only
the ones the version has.

This module sits in ``protocol/`` because the device layer reads board states and the emulator makes
them, and neither may import the other.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

from ..errors import ConfigurationError
from .firmware import FirmwareSpec

#: BoardState field -> the firmware variable's name (the golden vectors' ``expect`` key), in the order the
#: firmware declares them; fields not listed keep their name.
_WIRE_NAMES = {
    "pulse_width_us": "pulse_width",
    "sense_pulse_width_us": "sense_pulse_width",
    "discharge_time_us": "discharge_time",
}

#: The fields that are the firmware's variables.
_REGISTERS = (
    "electrode_num",
    "polarity",
    "stim_mode",
    "pulse_height",
    "pulse_width_us",
    "sense_pulse_height",
    "sense_pulse_width_us",
    "discharge_time_us",
    "period_us",
    "timer_alarm_ticks",
    "hv513_num",
    "stim_pattern",
)

#: The registers one version lacks (``None`` there): v1.2's stimulation mode, v2's global pulse height.
_VERSION_REGISTERS = ("stim_mode", "pulse_height")

_ORDER = (*_REGISTERS, "rx_pending", "rx_dropped", "command_in_progress")

#: The firmware variables (by the firmware's names) every version's board state is read from: what
#: :meth:`BoardState.from_variables` needs, and what a host build's state map must name.
STATE_VARIABLES: tuple[str, ...] = tuple(
    _WIRE_NAMES.get(name, name) for name in _REGISTERS if name not in _VERSION_REGISTERS
)


@dataclass(frozen=True)
class BoardState:
    """The firmware's variables at one moment, and its receive queue.

    ``pulse_height`` (v1.2's global DAC code, 0-4095) and ``stim_mode`` (v2's waveform: 0 monophasic,
    1 biphasic, 2 impedance only) are ``None`` on the version that lacks them.  ``stim_pattern`` is the
    whole pattern buffer (v1.2: one pattern byte per channel; v2: one DAC code per channel), of which the
    first ``electrode_num`` are scanned.  ``sense_pulse_height`` is the stored DAC code (v1.2 stores the
    payload shifted left by 2).  ``rx_pending``: bytes waiting in the receive queue.  ``rx_dropped`` and
    ``command_in_progress`` are part of the state where the parser owns the receive queue (v2: its
    1024-byte queue drops, its 2 s timeout discards a pending command); ``None`` where they are not.
    """

    firmware: FirmwareSpec
    electrode_num: int
    polarity: int
    stim_mode: int | None
    pulse_height: int | None
    pulse_width_us: int
    sense_pulse_height: int
    sense_pulse_width_us: int
    discharge_time_us: int
    period_us: float
    timer_alarm_ticks: int
    hv513_num: int
    stim_pattern: tuple[int, ...]
    rx_pending: int
    rx_dropped: int | None = None
    command_in_progress: bool | None = None

    def __repr__(self) -> str:
        regs = self.as_dict()
        regs["stim_pattern"] = self.scanned_pattern
        return f"BoardState({self.firmware.name}: " + ", ".join(f"{k}={v!r}" for k, v in regs.items()) + ")"

    @property
    def scanned_pattern(self) -> tuple[int, ...]:
        """The pattern entries the scan reads: the first ``electrode_num``."""
        return self.stim_pattern[: self.electrode_num]

    @classmethod
    def from_variables(
        cls,
        firmware: FirmwareSpec,
        variables: Mapping[str, Any],
        *,
        rx_pending: int,
        rx_dropped: int | None = None,
        command_in_progress: bool | None = None,
    ) -> BoardState:
        """The state of a board whose firmware holds ``variables`` (by the firmware's own names, the keys
        :meth:`as_dict` gives; any other name is not read), with its receive queue: a model whose
        registers carry the firmware's names hands them over as they are, and the names are mapped to
        fields here, beside :meth:`as_dict` that maps them back.  A register the version lacks
        (``stim_mode``, ``pulse_height``) is absent and becomes ``None``; any other absent is refused,
        naming it."""
        missing = [name for name in STATE_VARIABLES if name not in variables]
        if missing:
            raise ConfigurationError(
                f"variables: {', '.join(missing)} missing, a {firmware.name} board state needs them"
            )
        regs: dict[str, Any] = {name: variables.get(_WIRE_NAMES.get(name, name)) for name in _REGISTERS}
        regs["stim_pattern"] = tuple(regs["stim_pattern"])
        return cls(
            firmware=firmware,
            **regs,
            rx_pending=rx_pending,
            rx_dropped=rx_dropped,
            command_in_progress=command_in_progress,
        )

    def as_dict(self) -> dict[str, Any]:
        """The firmware's variable names (the golden vectors' ``expect`` keys) to their values; registers
        the version lacks are left out, the pattern is a list (for JSON)."""
        out: dict[str, Any] = {}
        for name in _ORDER:
            value = getattr(self, name)
            if value is None:
                continue
            out[_WIRE_NAMES.get(name, name)] = list(value) if name == "stim_pattern" else value
        return out


__all__ = ["BoardState"]
