"""One stimulating session, built in the order that keeps "nothing was sent" true: the participant's
profile, the safety guard made from it, the array's wiring (which channel drives each electrode, where each
electrode sits), the delivery log, the device, the renderer.

Every step that can refuse runs before the device is opened: a malformed profile, a calibration profile
whose mapping disagrees with the wiring, a current above the cap.  The command line's stimulating commands
and the study runner build their sessions here, so a rule added to one step holds for all of them.  A
command takes only the steps it needs (``replay-log`` reads a profile and opens no device; ``calibrate``
brings its own guard).
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

from tactdeform_hw.device.participant.regions import RegionMap, region_map_from_positions

from .delivery import DeliveryLog, session_region_map

if TYPE_CHECKING:
    from tactdeform_hw.clock import Clock
    from tactdeform_hw.device.driver.audit import AuditLog
    from tactdeform_hw.device.driver.serial_driver import EtactileKitDevice
    from tactdeform_hw.device.safety.guard import SafetyGuard
    from tactdeform_hw.render.array import ElectrodeArray
    from tactdeform_hw.render.pipeline import Renderer

#: Where a session's regions come from: a map of electrode positions, one region per electrode, or
#: nothing (the TactDeform array's regions).
RegionSource = RegionMap | Sequence[int] | None


@dataclass(frozen=True)
class Wiring:
    """Which hardware channel drives each electrode and where the electrodes sit.

    ``mapping`` is the channel mapping the device is opened with (None: electrode i on channel i);
    ``region_of`` gives the safety guard its regions (a :class:`RegionMap` of positions, one region per
    electrode, or None for the TactDeform array's); ``positions`` is what the delivery log's session line
    records, so ``replay-log`` judges the session by the same positions; ``against`` names the mapping in a
    calibration profile's refusal; ``channel_offset`` is an on-board array's first hardware channel;
    ``array`` is the array the renderer draws on, when there is one."""

    mapping: Any = None
    region_of: RegionSource = None
    positions: RegionMap | None = None
    against: str | None = None
    channel_offset: int = 0
    array: ElectrodeArray | None = None

    @classmethod
    def tactdeform(cls) -> Wiring:
        """The TactDeform finger-pad array the renderer draws on: its channel mapping, and regional limits
        that follow its electrodes' positions."""
        from tactdeform_hw.render.array import ElectrodeArray

        array = ElectrodeArray.tactdeform()
        region_map = region_map_from_positions(array.positions_mm.tolist(), f"the {array.name} array")
        return cls(
            mapping=array.channel_mapping(),
            region_of=region_map,
            positions=region_map,
            against=f"the {array.name} array's channel mapping",
            array=array,
        )

    @classmethod
    def for_array_file(cls, array_file: Any, mapping: Any, electrodes: int) -> Wiring:
        """A pattern's wiring: an electrode-array file's positions and ``Mapping_func`` (an on-board array
        counts from hardware channel 24), or without one ``electrodes`` on channels 0 upwards (the
        TactDeform array's positions for 32 of them)."""
        if array_file is None:
            return cls(mapping=mapping, positions=session_region_map(None, electrodes))
        region_map = array_file.region_map()
        return cls(
            mapping=mapping,
            region_of=region_map,
            positions=region_map,
            against=f"--array {array_file.source}'s Mapping_func",
            channel_offset=array_file.pattern_offset,
        )


def regions_by_electrode(region_of: RegionSource) -> Sequence[int]:
    """One region per electrode: a map of positions resolved, else the TactDeform array's regions."""
    if isinstance(region_of, RegionMap):
        return region_of.resolve(None)
    if region_of is None:
        from tactdeform_hw.render.array import ElectrodeArray

        return tuple(int(r) for r in ElectrodeArray.tactdeform().regions)
    return region_of


def read_participant(path: str | os.PathLike[str] | None, region_of: RegionSource = None) -> tuple[Any, Any]:
    """The participant profile in ``path`` and, for an eTactileKit calibration profile, the calibration
    profile itself ((None, None) without a path); a calibration profile's intensities are read as regions
    through ``region_of``.  Raises :class:`~tactdeform_hw.errors.ProfileError` naming the field."""
    if not path:
        return None, None
    from tactdeform_hw.formats.calibration_profile import read_participant_file

    return read_participant_file(path, regions_by_electrode(region_of))


def guard_for(profile: Any, calibration: Any, wiring: Wiring) -> SafetyGuard:
    """The safety guard of a session: the participant's limits with a profile, the 10 mA hardware ceiling
    without.  An eTactileKit calibration profile's intensities bind the hardware channels its mapping
    names, and one whose mapping disagrees with ``wiring.mapping`` is refused here, before any device is
    opened."""
    from tactdeform_hw.device.safety.guard import SafetyGuard
    from tactdeform_hw.formats.calibration_profile import calibration_guard

    if profile is None:
        return SafetyGuard()
    if calibration is None:
        return SafetyGuard.from_profile(profile, region_of=wiring.region_of)
    against = wiring.against
    if against is None:
        against = (
            "the identity mapping (electrode i on channel i; no --array)"
            if wiring.mapping is None
            else "the device's channel mapping"
        )
    guard: SafetyGuard = calibration_guard(
        calibration,
        regions_by_electrode(wiring.region_of),
        region_map=wiring.region_of,
        mapping=wiring.mapping,
        against=against,
        channel_offset=wiring.channel_offset,
    )
    return guard


class Session:
    """The steps of one session, each taken when the command asks for it.

    Made with the participant file, the profile is read at once and the guard built from it (a bad file
    is refused before anything else); ``guard_now=False`` leaves the guard to the first use of
    :attr:`guard`, for a command that checks its own options in between.  ``guard`` replaces the
    participant's (``calibrate`` runs under the cap it is calibrating to).  :meth:`delivery_log` makes the
    audit log the device writes to, :meth:`open_device` opens the device under the guard and that log,
    :meth:`renderer` puts a renderer on it."""

    def __init__(
        self,
        *,
        device: str = "emulator",
        timeout_s: float = 0.5,
        firmware: str = "auto",
        robust_encoding: bool | None = None,
        participant_file: str | None = None,
        audit_path: str | os.PathLike[str] | None = None,
        wiring: Wiring | None = None,
        guard: SafetyGuard | None = None,
        profile: Any = None,
        log: AuditLog | None = None,
        guard_now: bool = True,
    ) -> None:
        self.device = device
        self.timeout_s = timeout_s
        self.firmware = firmware
        self.robust_encoding = robust_encoding
        self.participant_file = participant_file
        self.audit_path = audit_path
        self.wiring = wiring if wiring is not None else Wiring()
        self.calibration: Any = None
        if participant_file:
            profile, self.calibration = read_participant(participant_file, self.wiring.region_of)
        self.profile = profile
        self._guard = guard
        self.log: AuditLog | None = log
        if guard_now:
            self.guard  # noqa: B018 - built now: a profile that disagrees with the wiring is refused here

    @property
    def guard(self) -> SafetyGuard:
        """The session's safety guard (built from the profile on first use)."""
        if self._guard is None:
            self._guard = guard_for(self.profile, self.calibration, self.wiring)
        return self._guard

    @property
    def participant(self) -> str | None:
        """The participant's name in the profile (None without one)."""
        return self.profile.participant if self.profile is not None else None

    def header(self, command: str, **extra: Any) -> dict[str, Any]:
        """The delivery log's usual session line: the command, the device, the participant file and the
        participant's name, then ``extra``."""
        return {
            "command": command,
            "device": self.device,
            "participant_file": self.participant_file,
            "participant": self.participant,
            **extra,
        }

    def delivery_log(
        self, header: dict[str, Any], *, requested_ua: int | None = None, guard_regions: bool = True
    ) -> DeliveryLog:
        """The session's audit log (written to ``audit_path`` when given), keeping what the console reports;
        the device opened after it writes to it.  ``header`` is its session line's fields, in order;
        ``guard_regions`` names the guard's regions in the report (else the positions' own)."""
        log = DeliveryLog(
            self.audit_path,
            requested_ua=requested_ua,
            mapping=self.wiring.mapping,
            region_map=self.wiring.positions,
            region_of=self.guard.region_of if guard_regions else None,
            **header,
        )
        self.log = log
        return log

    def open_device(self, *, offline_clock: Clock | None = None) -> EtactileKitDevice:
        """The device under the session's guard, wiring and delivery log.  ``offline_clock``: the clock an
        instant port (the in-process emulator) paces on, so an offline run keeps session time."""
        from tactdeform_hw.device import open_device

        return open_device(
            self.device,
            timeout=self.timeout_s,
            firmware=self.firmware,
            robust_encoding=self.robust_encoding,
            mapping=self.wiring.mapping,
            guard=self.guard,
            audit=self.log,
            offline_clock=offline_clock,
        )

    def readback(self, device: Any) -> Any:
        """What the renderer compares each sent frame with: the pattern the board holds, read in application
        order (None when the port cannot show it)."""
        from tactdeform_hw.device.driver.readback import pattern_readback

        return pattern_readback(device, self.wiring.mapping)

    def renderer(self, scene: Any, device: Any, **options: Any) -> Renderer:
        """A renderer drawing ``scene`` on the session's array and sending to ``device``; ``options`` are the
        renderer's (approach, contact mode, current, stimulation config, readback)."""
        from tactdeform_hw.render.pipeline import Renderer

        return Renderer(scene, device, array=self.wiring.array, **options)
