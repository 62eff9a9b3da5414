"""What each firmware version's registers in force mean for the current a channel receives.

The interlock (:class:`~tactdeform_hw.device.safety.interlock.WireInterlock`) keeps a shadow of the
registers; whether a state breaks a limit depends on the version: v1.2 has one pulse height per scan and a
sense pulse on every channel the pattern has off; v2 has a height per channel and a global mode (mode 2
gives every channel the sense pulse).  :data:`READINGS` holds one reading per firmware spec.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from types import MappingProxyType
from typing import TYPE_CHECKING

from tactdeform_hw.protocol.commands import STIM_MODE_IMPEDANCE
from tactdeform_hw.protocol.constants import PATTERN_BIPHASIC, PATTERN_MONOPHASIC
from tactdeform_hw.protocol.firmware import V1_2, V2, FirmwareSpec
from tactdeform_hw.protocol.units import CurrentTransfer

if TYPE_CHECKING:
    from typing import TypeAlias

    from tactdeform_hw.device.participant.mapping import ChannelMapping
    from tactdeform_hw.device.safety.interlock import Shadow, WireInterlock

    #: The channel mapping a write was built with (None: identity).
    MaybeMapping: TypeAlias = ChannelMapping | None
    #: DAC codes per channel as the interlock knows them (None: unknown), and as a pattern writes them.
    Heights: TypeAlias = Sequence[int | None]
    Codes: TypeAlias = Sequence[int]

ACTIVE = (PATTERN_MONOPHASIC, PATTERN_BIPHASIC)

#: Tolerance of the µA comparisons (a code converted to µA and back).
EPS = 1e-6


class ChannelReading:
    """One firmware version's reading of the registers the interlock follows (each version overrides
    :meth:`verify` and :meth:`current_can_flow`)."""

    def verify(
        self, lock: WireInterlock, sh: Shadow, what: str, mapping: MaybeMapping, transfer: CurrentTransfer
    ) -> None:
        """Refuse (``lock.refuse``) a state in which a scanned channel could exceed its limit."""
        raise NotImplementedError

    def current_can_flow(self, sh: Shadow) -> bool:
        """Whether any channel can receive current in ``sh`` (unknowns count as yes)."""
        raise NotImplementedError

    def check_pattern_ramp(
        self, lock: WireInterlock, before: Heights, after: Codes, at: int, what: str, units: CurrentTransfer
    ) -> None:
        """Refuse a pattern whose values raise a channel's height faster than the ramp allows (v1.2's
        pattern holds levels, not heights: its ramp is the pulse height's, checked there)."""


class V12Reading(ChannelReading):
    """v1.2: one pulse height for every active channel, the sense height on every other one."""

    def verify(
        self, lock: WireInterlock, sh: Shadow, what: str, mapping: MaybeMapping, transfer: CurrentTransfer
    ) -> None:
        lim = lock.limits
        num = sh.electrode_num
        height_ua = transfer.to_ua(sh.height_code) if sh.height_code is not None else math.inf
        if height_ua > lim.cap_ua + EPS:
            raise lock.refuse(
                "interlock", f"{what}: pulse height {height_ua:g} µA above the cap of {lim.cap_ua} µA"
            )
        if height_ua > 0 and sh.height_code is not None:
            width = sh.width_us
            if width is None:
                raise lock.refuse(
                    "interlock", f"{what}: non-zero pulse height while the pulse width is unknown"
                )
            if height_ua * width / 1000.0 > lim.max_charge_nc + EPS:
                raise lock.refuse(
                    "interlock",
                    f"{what}: {height_ua:g} µA × {width} µs exceeds the charge limit of "
                    f"{lim.max_charge_nc:g} nC",
                )
        sense_ua = transfer.to_ua(sh.sense_code) if sh.sense_code is not None else math.inf
        if num is None:
            # any channel may be scanned, at either the pulse height or the sense height
            if height_ua > 0 or sense_ua > 0:
                raise lock.refuse(
                    "interlock", f"{what}: current possible while the electrode count is unknown"
                )
            return
        limits, low = lock.hw_limits(mapping, num)
        # within the lowest channel limit, no channel can be over its own: skip the per-channel search
        within = height_ua <= low + EPS and sense_ua <= low + EPS
        for ch in range(0 if within else num):
            level = sh.pattern[ch]
            # an active (or unknown) level gets the pulse height, an off (or unknown) one the sense height
            for applies, current_ua, received in (
                (level is None or level in ACTIVE, height_ua, "{:g} µA, above its limit of"),
                (level is None or level not in ACTIVE, sense_ua, "a sense current of {:g} µA, above"),
            ):
                if applies and current_ua > limits[ch] + EPS:
                    raise lock.refuse(
                        "interlock",
                        f"{what}: channel {ch} would receive {received.format(current_ua)} {limits[ch]} µA",
                        channel=ch,
                    )
        if sense_ua > 0 and sh.sense_code is not None:
            sw = (
                sh.sense_width_us
                if sh.sense_width_us is not None
                else lock.firmware.value_max("sense_pulse_width")
            )
            if sense_ua * sw / 1000.0 > lim.max_charge_nc + EPS:
                raise lock.refuse("interlock", f"{what}: sense pulse exceeds the charge limit")

    def current_can_flow(self, sh: Shadow) -> bool:
        if sh.sense_code != 0 and sh.electrode_num != 0:
            return True
        if sh.height_code == 0:
            return False
        num = sh.electrode_num
        if num is None:
            return True
        return any(v is None or v in ACTIVE for v in sh.pattern[:num])


class V2Reading(ChannelReading):
    """v2: every channel its own height in modes 0/1; the sense height on every channel in mode 2."""

    def verify(
        self, lock: WireInterlock, sh: Shadow, what: str, mapping: MaybeMapping, transfer: CurrentTransfer
    ) -> None:
        """Every channel v2 scans receives at most its own limit: in mode 0/1 its own pattern height, in
        mode 2 the sense height (then never above 0); unknown values count as their worst."""
        lim = lock.limits
        num = sh.electrode_num
        mode = sh.stim_mode
        sense_ua = transfer.to_ua(sh.sense_code) if sh.sense_code is not None else math.inf
        if mode is None or mode >= STIM_MODE_IMPEDANCE:
            if sense_ua > 0 and num != 0:
                raise lock.refuse(
                    "interlock",
                    f"{what}: stimulation mode {'unknown' if mode is None else mode} with a sense height "
                    "that may be non-zero (mode 2 gives every channel the sense pulse, a zero pattern does "
                    "not stop it)",
                )
            if mode is not None:
                return
        if num is None:
            if any(v is None or v for v in sh.pattern):
                raise lock.refuse(
                    "interlock", f"{what}: a height possible while the electrode count is unknown"
                )
            return
        limits, _ = lock.hw_limits(mapping, num)
        width = sh.width_us
        for ch in range(num):
            code = sh.pattern[ch]
            ua = transfer.to_ua(code) if code is not None else math.inf
            if ua <= 0:
                continue
            if ua > min(limits[ch], lim.cap_ua) + EPS:
                raise lock.refuse(
                    "interlock",
                    f"{what}: channel {ch} would receive {ua:g} µA, above its limit of {limits[ch]} µA",
                    channel=ch,
                )
            if width is None:
                raise lock.refuse(
                    "interlock", f"{what}: channel {ch} has a height while the pulse width is unknown"
                )
            if ua * max(width, 7) / 1000.0 > lim.max_charge_nc + EPS:
                raise lock.refuse(
                    "interlock",
                    f"{what}: channel {ch}: {ua:g} µA × {width} µs exceeds the charge limit of "
                    f"{lim.max_charge_nc:g} nC",
                    channel=ch,
                )

    def current_can_flow(self, sh: Shadow) -> bool:
        """A height on a scanned channel (modes 0/1), or a sense height (mode 2 or unknown)."""
        if sh.electrode_num == 0:
            return False
        if sh.stim_mode is None or sh.stim_mode >= STIM_MODE_IMPEDANCE:
            if sh.sense_code != 0:
                return True
            if sh.stim_mode is not None:
                return False
        num = sh.electrode_num if sh.electrode_num is not None else len(sh.pattern)
        return any(v is None or v for v in sh.pattern[:num])

    def check_pattern_ramp(
        self, lock: WireInterlock, before: Heights, after: Codes, at: int, what: str, units: CurrentTransfer
    ) -> None:
        """Each channel's height rises by at most the ramp step per pattern (an unknown one counts as 0)."""
        lim = lock.limits
        ramp = lim.ramp_ua_per_frame
        if ramp is None:
            return
        for k, code in enumerate(after):
            old = before[at + k]
            prev = units.to_ua(old) if old is not None else 0.0
            new = units.to_ua(code)
            if new > prev + ramp + EPS:
                raise lock.refuse(
                    "interlock",
                    f"{what}: channel {at + k} rises from {prev:g} to {new:g} µA, more than the ramp of "
                    f"{ramp} µA",
                    channel=at + k,
                )


#: One reading per firmware spec.
READINGS: Mapping[FirmwareSpec, ChannelReading] = MappingProxyType({V1_2: V12Reading(), V2: V2Reading()})

__all__ = ["ACTIVE", "EPS", "READINGS", "ChannelReading", "V12Reading", "V2Reading"]
