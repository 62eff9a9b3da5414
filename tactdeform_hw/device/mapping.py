"""Application electrode order → hardware channel (eTactileKit's ``Mapping_func``).

The renderer numbers electrodes in its own order (row-major from the fingertip); the board's two 16-pin
connectors number them differently.  The mapping lives in the device layer so every caller that sends a
pattern goes through the same translation.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

from ..errors import ConfigurationError, LimitError
from ..protocol.constants import MAX_ELECTRODES


@dataclass(frozen=True)
class ChannelMapping:
    """``app_to_hw[i]`` is the hardware channel of application electrode ``i``; ``hw_channels`` is the
    electrode count the firmware scans (channels no electrode maps to are always sent 0)."""

    app_to_hw: tuple[int, ...]
    hw_channels: int

    def __post_init__(self) -> None:
        if not 1 <= self.hw_channels <= MAX_ELECTRODES:
            raise LimitError("hw_channels", self.hw_channels, f"1 to {MAX_ELECTRODES}")
        seen: set[int] = set()
        for i, ch in enumerate(self.app_to_hw):
            if isinstance(ch, bool) or not isinstance(ch, int) or not 0 <= ch < self.hw_channels:
                raise LimitError(f"mapping[{i}]", ch, f"a hardware channel from 0 to {self.hw_channels - 1}")
            if ch in seen:
                raise ConfigurationError(
                    f"mapping[{i}]={ch} maps a second electrode to hardware channel {ch}"
                )
            seen.add(ch)

    @classmethod
    def identity(cls, n: int) -> ChannelMapping:
        return cls(tuple(range(n)), n)

    @classmethod
    def from_list(cls, app_to_hw: Sequence[int], hw_channels: int | None = None) -> ChannelMapping:
        chans = tuple(int(c) for c in app_to_hw)
        return cls(chans, hw_channels if hw_channels is not None else (max(chans) + 1 if chans else 1))

    @property
    def electrodes(self) -> int:
        return len(self.app_to_hw)

    def to_hardware(self, levels: Sequence[int]) -> bytes:
        """Hardware-order pattern bytes (length ``hw_channels``) from application-order levels."""
        hw = bytearray(self.hw_channels)
        for ch, level in zip(self.app_to_hw, levels):
            hw[ch] = level
        return bytes(hw)

    def to_application(self, hw_values: Sequence[int]) -> list[int]:
        return [hw_values[ch] for ch in self.app_to_hw]
