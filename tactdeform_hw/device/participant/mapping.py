"""Application electrode order → hardware channel (eTactileKit's ``Mapping_func``).

The renderer numbers electrodes in its own order (row-major from the fingertip); the board's two 16-pin
connectors number them differently.  The mapping lives in the device layer so every caller that sends a
pattern goes through the same translation.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

from tactdeform_hw.errors import ConfigurationError, LimitError, SafetyError
from tactdeform_hw.protocol.constants import MAX_CURRENT_UA, MAX_ELECTRODES


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


@dataclass(frozen=True)
class CalibratedChannels:
    """Per-electrode calibrated limits, bound to the hardware channel each electrode is wired to.

    An eTactileKit calibration profile calibrates electrode ``i`` (its application id) on the hardware
    channel ``app_to_hw[i]``; the current felt there is what was calibrated, so the limit
    ``limits_ua[i]`` belongs to that **channel**, whatever order a pattern lists electrodes in.  A channel
    no calibrated electrode is wired to counts at the lowest calibrated limit: its electrode is unknown,
    and the lowest is the safe direction.  ``source`` names the profile in error messages.
    """

    app_to_hw: tuple[int, ...]
    limits_ua: tuple[int, ...]
    source: str = "the calibration profile"

    def __post_init__(self) -> None:
        n = len(self.app_to_hw)
        if n == 0 or len(self.limits_ua) != n:
            raise ConfigurationError(
                f"{self.source}: {n} electrode(s) but {len(self.limits_ua)} limit(s); one per electrode"
            )
        seen: set[int] = set()
        for i, ch in enumerate(self.app_to_hw):
            if isinstance(ch, bool) or not isinstance(ch, int) or not 0 <= ch < MAX_ELECTRODES or ch in seen:
                raise ConfigurationError(
                    f"{self.source}: electrode {i}'s channel {ch!r} is not a distinct hardware channel "
                    f"from 0 to {MAX_ELECTRODES - 1}"
                )
            seen.add(ch)
        for i, ua in enumerate(self.limits_ua):
            if isinstance(ua, bool) or not isinstance(ua, int) or not 0 <= ua <= MAX_CURRENT_UA:
                raise LimitError(f"limits_ua[{i}]", ua, f"0 to {MAX_CURRENT_UA} µA")
        object.__setattr__(self, "_by_channel", dict(zip(self.app_to_hw, self.limits_ua)))

    @property
    def electrodes(self) -> int:
        return len(self.app_to_hw)

    @property
    def lowest_ua(self) -> int:
        return min(self.limits_ua)

    def channel_limit_ua(self, channel: int) -> int:
        """The limit of one hardware channel: that of the electrode calibrated on it, else the lowest."""
        by_channel: dict[int, int] = self.__dict__["_by_channel"]
        return by_channel.get(channel, self.lowest_ua)

    def application_limits(self, electrodes: int) -> tuple[int, ...]:
        """Each of ``electrodes`` application electrodes' limit (its own calibration); every electrode at
        the lowest limit when the count is not the profile's (which electrode is which is then unknown)."""
        if electrodes != self.electrodes:
            return (self.lowest_ua,) * electrodes
        return self.limits_ua

    def check_wiring(
        self, mapping: ChannelMapping | Sequence[int] | None, against: str | None = None
    ) -> None:
        """Refuse (:class:`~tactdeform_hw.errors.SafetyError`) a device mapping that wires an electrode to
        another channel than the one it was calibrated on: its limit would bind the wrong channel.
        ``mapping`` None is the identity (electrode i on channel i); ``against`` names where the mapping
        comes from (default: the device's channel mapping, or the identity)."""
        if mapping is None:
            chans: tuple[int, ...] = tuple(range(self.electrodes))
            what = against or "the identity mapping (electrode i on channel i; no array file)"
        else:
            chans = tuple(mapping.app_to_hw if isinstance(mapping, ChannelMapping) else mapping)
            what = against or "the device's channel mapping"
        if mapping is not None and len(chans) != self.electrodes:
            raise SafetyError(
                f"{self.source}: calibrates {self.electrodes} electrode(s) but {what} places {len(chans)}: "
                "the profile is for another layout; nothing was sent"
            )
        for eid, (mine, theirs) in enumerate(zip(self.app_to_hw, chans)):
            if mine != theirs:
                raise SafetyError(
                    f"{self.source}: electrode {eid} is calibrated on hardware channel {mine} but {what} "
                    f"wires it to channel {theirs}; its calibrated intensity would limit the wrong channel "
                    "(the profile's mapping must match the array file's Mapping_func); nothing was sent"
                )
