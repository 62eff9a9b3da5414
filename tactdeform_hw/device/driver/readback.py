"""Reading back what the board holds, where its port can show it.

An emulated board declares ``board_state()`` (see :mod:`tactdeform_hw.ports`); a real board cannot be
asked for its pattern buffer.  The renderer and the study take the function this module builds as their
``verify`` callback, so neither ever looks for an emulator behind a device.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from tactdeform_hw.device.driver.v2 import buffer_levels
from tactdeform_hw.device.participant.mapping import ChannelMapping
from tactdeform_hw.ports import board_state

PatternReadback = Callable[[], tuple[int, ...]]

#: A measure reading (ADC code, ``raw >> 2``) above this on a channel pulsed at height 0 means current
#: reaches it: the converter's noise stays below.
OFF_READING_CODES = 2


def pattern_readback(device: Any, mapping: ChannelMapping | None = None) -> PatternReadback | None:
    """A function returning the pattern the board behind ``device`` holds, in application order
    (through ``mapping``, default the device's), or None when its port cannot show it."""
    port = getattr(device, "port", None)
    if not callable(getattr(port, "board_state", None)):
        return None
    m = mapping if mapping is not None else getattr(device, "mapping", None)

    def read() -> tuple[int, ...]:
        state = board_state(port)
        assert state is not None  # the port declared board_state()
        pattern = [int(v) for v in buffer_levels(state)]  # v2 holds heights: an active channel reads 1 or 2
        if m is None:
            return tuple(pattern[: state.electrode_num])
        return tuple(m.to_application(pattern[: m.hw_channels]))

    return read


def heights_readback(device: Any, mapping: ChannelMapping | None = None) -> PatternReadback | None:
    """A function returning the pulse height (DAC code) each electrode has in the pattern buffer of a
    firmware-v2 board, in application order; None when the port cannot show its board or the board holds
    levels (v1.2), where :func:`pattern_readback` already shows everything the buffer holds.  On v2 a
    level readback only says which electrodes are on; a wrong height needs the codes themselves."""
    port = getattr(device, "port", None)
    if not callable(getattr(port, "board_state", None)):
        return None
    state = board_state(port)
    if state is None or state.stim_mode is None:
        return None
    m = mapping if mapping is not None else getattr(device, "mapping", None)

    def read() -> tuple[int, ...]:
        now = board_state(port)
        assert now is not None  # the port declared board_state()
        codes = [int(v) for v in now.stim_pattern]
        if m is None:
            return tuple(codes[: now.electrode_num])
        return tuple(m.to_application(codes[: m.hw_channels]))

    return read


__all__ = ["OFF_READING_CODES", "PatternReadback", "heights_readback", "pattern_readback"]
