"""The one guard every current passes on its way to the device, and the interlock behind it.

Two layers, both inside :class:`~tactdeform_hw.device.driver.base.Device`, so nothing above the device layer
can
skip them:

1. **The guard** (:meth:`SafetyGuard.check_config`, :meth:`SafetyGuard.request`,
   :meth:`SafetyGuard.frame_height`) decides what current may be sent.  ``configure``, ``set_current``,
   ``send_pattern``, ``keepalive`` and ``resync`` all go through it before any byte is built.
2. **The interlock** (:attr:`SafetyGuard.interlock`, a
   :class:`~tactdeform_hw.device.safety.interlock.WireInterlock`) sees every command the device layer
   writes — it is called from ``Device._send``, the single place bytes leave for the transport — and
   keeps a shadow of the firmware's registers.  It refuses a command whose effect would break a limit
   whatever code path produced it, so a future method that forgets the guard is stopped at the wire.  It
   judges the firmware's reading of the bytes (:mod:`tactdeform_hw.protocol.reader`, from where the
   parser stands), and where the device's queue may be full, every reading a discarded USB packet tail
   could cause.  Only writing to the port object directly (``device.port.write`` or
   ``serial.serial_for_url(...).write``) bypasses it: that is not the driver, it is the raw transport,
   and no Python-level check can stop a caller who opens the port themselves.

Limits (µA unless noted):

* the hardware ceiling, 10 mA (never raised);
* the participant's ``cap_ua``;
* the regional amplitude of every electrode active in the frame.  The firmware has **one pulse height
  per scan** (the 0xFB register applies to every channel whose pattern value is 1 or 2), so a frame's
  height is the **lowest** limit among the electrodes it activates;
* charge per pulse, ``current × width`` in nC (per phase for biphasic pulses: both phases have the same
  height and width), as a current limit ``max_charge_nc × 1000 / width``;
* a ramp limit: the pulse height may rise by at most ``ramp_ua_per_frame`` from one frame to the next
  (counted from 0 after configure, all-off, resync and a watchdog stop, so stimulation always starts soft);
* the sense current: every channel whose pattern value is not 1 or 2 receives the sense pulse, so it must
  be within the *lowest* electrode limit and the charge limit;
* polarity may change only while no current can flow (pulse height 0 or no active channel, and sense 0);
* frames whose scan would fill the stimulation period are refused: the parser runs only between scans,
  and back-to-back scans would leave the host unable to change anything, all-off included; scans that
  could trip the firmware's 300 ms interrupt watchdog are refused at configure time.

**Refuse or clip** — the documented rule:

* *Refused* (:class:`~tactdeform_hw.errors.SafetyError`, nothing written): a requested current above the
  participant's cap (values above the 10 mA ceiling, negative, fractional or not numbers are refused
  earlier as :class:`~tactdeform_hw.errors.LimitError`); a configuration whose charge per pulse, sense
  current, pulse width (wider than calibrated), polarity (other than calibrated) or scan time breaks a
  limit; a polarity change while stimulating; any command the interlock finds unsafe.  These are caller
  errors: a script that asks for more than the participant's cap has a bug, and silently delivering less
  would hide it.
* *Clipped* (logged, the lower height sent): the frame's height is lowered to the lowest regional limit of
  the electrodes it activates, and increases are limited to the ramp step.  These depend on which
  electrodes a frame happens to activate, which the renderer cannot know in advance; the frame still
  renders, at a height that is safe for every electrode in it.

Every refusal and every clip is appended to :attr:`SafetyGuard.log` (the latest 10 000; :attr:`counts`
keeps totals), sent to the ``tactdeform_hw.safety`` logger (refusals at warning level, clips at info) and to
``sink`` (the session's audit log when one is enabled).
"""

from __future__ import annotations

import logging
import math
import time
from collections import deque
from collections.abc import Callable, Sequence
from typing import TYPE_CHECKING, Any

from tactdeform_hw.device.driver.config import POLARITY_CODE, StimConfig
from tactdeform_hw.device.participant.regions import RegionMap, tactdeform_region_map
from tactdeform_hw.device.safety.interlock import Shadow, WireInterlock, WireState
from tactdeform_hw.errors import LimitError, SafetyError
from tactdeform_hw.protocol.constants import (
    CURRENT_STEP_UA,
    MAX_CURRENT_UA,
    PATTERN_BIPHASIC,
    PATTERN_MONOPHASIC,
)
from tactdeform_hw.protocol.firmware import FirmwareSpec
from tactdeform_hw.protocol.firmware_math import estimate_scan_us
from tactdeform_hw.protocol.units import DEFAULT_TRANSFER, CurrentTransfer

if TYPE_CHECKING:
    from tactdeform_hw.device.participant.mapping import CalibratedChannels, ChannelMapping
    from tactdeform_hw.device.participant.profiles import ParticipantProfile

logger = logging.getLogger("tactdeform_hw.safety")

#: 10 mA × 200 µs: the TactDeform hardware's largest pulse at its own pulse width.  Without a profile the
#: guard allows no more charge per pulse than that.
DEFAULT_MAX_CHARGE_NC = MAX_CURRENT_UA * 200 / 1000.0
#: The firmware's interrupt watchdog reboots the chip when one scan runs longer than this.
INTERRUPT_WATCHDOG_US = 300_000.0
#: Scans are refused well before the watchdog: the estimate below leaves this much margin.
SCAN_LIMIT_US = 250_000.0
_ACTIVE = (PATTERN_MONOPHASIC, PATTERN_BIPHASIC)
_EPS = 1e-6
LOG_LIMIT = 10_000


def grid_regions(
    rows: int = 6, cols: int = 6, *, skip_corners: bool = True, region_rows: int = 3, region_cols: int = 3
) -> tuple[int, ...]:
    """Region index of each electrode of a row-major grid (application order), regions row-major too.

    The default is the TactDeform finger-pad array: 6 × 6 minus the corners = 32 electrodes, row 0 at the
    fingertip, grouped 2 × 2 into 3 × 3 regions (the corner regions hold 3 electrodes, the others 4);
    region 4 is the centre.
    """
    out: list[int] = []
    corners = {(0, 0), (0, cols - 1), (rows - 1, 0), (rows - 1, cols - 1)} if skip_corners else set()
    for r in range(rows):
        for c in range(cols):
            if (r, c) in corners:
                continue
            out.append((r * region_rows // rows) * region_cols + (c * region_cols // cols))
    return tuple(out)


#: Region of each of the 32 TactDeform electrodes, application order, from their positions on the pad.
TACTDEFORM_REGION_OF: tuple[int, ...] = tactdeform_region_map().resolve(None)


def worst_scan_us(electrodes: int, width_us: int, discharge_us: int, sense_width_us: int) -> float:
    """One scan with every channel biphasic — the longest a configuration can make — by the pacer's
    firmware-order estimate (which errs long).  Only used to keep scans far from the 300 ms watchdog."""
    return estimate_scan_us(
        [2] * electrodes, width_us, discharge_us, sense_width_us, hv513=max(4, -(-electrodes // 8))
    )


class SafetyGuard:
    """Participant limits, enforced before bytes are built (guard) and as they are written (interlock).

    ``cap_ua`` alone gives the hardware-ceiling guard every device has by default.  A profile adds regional
    amplitudes, its charge limit, its calibrated polarity and pulse width, and optionally a ramp; use
    :meth:`from_profile`.

    Regional limits follow each electrode's **position**.  ``region_of`` is a
    :class:`~tactdeform_hw.device.participant.regions.RegionMap` built from the electrode centres (an array
    file's
    :meth:`~tactdeform_hw.formats.etactilekit.ArrayFile.region_map`), or one region index per application
    electrode already derived from positions.  Without it, 32 application electrodes are the TactDeform
    array in its own order (whose positions are known).  A frame whose electrodes have no known position
    (no map, or a map of another length) is refused while the profile's regions differ, and so is an
    electrode on a border between regions of different amplitude — never a map by index.  (The interlock,
    which only sees hardware channels, still counts an electrode of unknown region at the lowest regional
    amplitude: the safe direction for a backstop.)

    ``channels`` adds per-electrode calibrated limits bound to **hardware channels**
    (:class:`~tactdeform_hw.device.participant.mapping.CalibratedChannels`, from an eTactileKit calibration
    profile's
    ``mapping`` and ``intensity``): the interlock holds every channel to the limit of the electrode
    calibrated on it, whatever the device's mapping, and the guard lowers each application electrode to the
    limit of the channel it was calibrated on.  A device whose mapping wires an electrode elsewhere is
    refused before its port opens (:meth:`check_wiring`).
    """

    def __init__(
        self,
        cap_ua: int = MAX_CURRENT_UA,
        *,
        regions_ua: Sequence[int] | None = None,
        region_of: Sequence[int] | RegionMap | None = None,
        max_charge_nc: float = DEFAULT_MAX_CHARGE_NC,
        ramp_ua_per_frame: int | None = None,
        polarity: str | None = None,
        max_pulse_width_us: int | None = None,
        participant: str | None = None,
        sink: Callable[[dict[str, Any]], None] | None = None,
        channels: CalibratedChannels | None = None,
    ) -> None:
        if isinstance(cap_ua, bool) or not isinstance(cap_ua, int) or not 0 <= cap_ua <= MAX_CURRENT_UA:
            raise SafetyError(f"cap_ua={cap_ua!r} is out of range: 0 to {MAX_CURRENT_UA} µA")
        if not (
            isinstance(max_charge_nc, (int, float)) and math.isfinite(max_charge_nc) and max_charge_nc >= 0
        ):
            raise SafetyError(f"max_charge_nc={max_charge_nc!r} must be a finite number >= 0")
        if ramp_ua_per_frame is not None and (
            isinstance(ramp_ua_per_frame, bool)
            or not isinstance(ramp_ua_per_frame, int)
            or ramp_ua_per_frame < CURRENT_STEP_UA
        ):
            raise SafetyError(
                f"ramp_ua_per_frame={ramp_ua_per_frame!r} must be an integer >= {CURRENT_STEP_UA} µA"
            )
        if polarity is not None and polarity not in POLARITY_CODE:
            raise SafetyError(f"polarity={polarity!r} is not 'anodic' or 'cathodic'")
        self.cap_ua = cap_ua
        self.regions_ua: tuple[int, ...] | None = None
        if regions_ua is not None:
            regs = tuple(regions_ua)
            for i, v in enumerate(regs):
                if isinstance(v, bool) or not isinstance(v, int) or not 0 <= v <= cap_ua:
                    raise SafetyError(f"regions_ua[{i}]={v!r} is out of range: 0 to cap_ua={cap_ua} µA")
            if not regs:
                raise SafetyError("regions_ua is empty")
            self.regions_ua = regs
        self.region_map: RegionMap | None = region_of if isinstance(region_of, RegionMap) else None
        if isinstance(region_of, RegionMap):
            # an electrode on a border between regions of different amplitude has no one limit: refused here,
            # before any port is opened
            region_of = region_of.resolve(self.regions_ua)
        self.region_of: tuple[int, ...] | None = tuple(region_of) if region_of is not None else None
        if self.region_of is not None and self.regions_ua is not None:
            for i, r in enumerate(self.region_of):
                if not 0 <= r < len(self.regions_ua):
                    raise SafetyError(
                        f"region_of[{i}]={r!r} names no region (0 to {len(self.regions_ua) - 1})"
                    )
        self.max_charge_nc = float(max_charge_nc)
        self.ramp_ua_per_frame = ramp_ua_per_frame
        self.polarity = polarity
        self.max_pulse_width_us = max_pulse_width_us
        self.participant = participant
        self.sink = sink
        #: Per-electrode calibrated limits by hardware channel (None: regional limits only).
        self.channels = channels
        #: The most recent refusals and clips (bounded: a long session clips every frame of some patterns);
        #: :attr:`counts` keeps the totals and the audit log keeps every one.
        self.log: deque[dict[str, Any]] = deque(maxlen=LOG_LIMIT)
        self.counts: dict[str, int] = {}
        self._limits_cache: tuple[Any, ...] | None = None
        #: The wire layer: every command as the firmware reads it, against these limits.
        self.interlock = WireInterlock(self)

    @classmethod
    def from_profile(
        cls,
        profile: ParticipantProfile,
        *,
        region_of: Sequence[int] | RegionMap | None = None,
        sink: Callable[[dict[str, Any]], None] | None = None,
        channels: CalibratedChannels | None = None,
        regional: bool = True,
    ) -> SafetyGuard:
        """The guard of a participant profile: its cap, charge limit, ramp, polarity and pulse width.
        ``regional=False`` leaves out the profile's regional limits, for a guard whose ``channels`` hold
        every electrode's own calibrated current (the regional view would hold most of them lower)."""
        return cls(
            profile.cap_ua,
            regions_ua=profile.regions_ua if regional else None,
            region_of=region_of,
            max_charge_nc=min(profile.charge_limit_nc, DEFAULT_MAX_CHARGE_NC),
            ramp_ua_per_frame=profile.ramp_ua_per_frame,
            polarity=profile.polarity,
            max_pulse_width_us=profile.pulse_width_us,
            participant=profile.participant,
            sink=sink,
            channels=channels,
        )

    def check_wiring(self, mapping: ChannelMapping | None, against: str | None = None) -> None:
        """Refuse a device mapping (None: the identity) that wires an electrode to another hardware channel
        than the one its calibrated limit belongs to; nothing to check without calibrated channels.  The
        device layer calls it before a port is opened."""
        if self.channels is not None:
            self.channels.check_wiring(mapping, against)

    # --- logging --------------------------------------------------------------------------------------------

    def _record(self, event: str, rule: str, message: str, **detail: Any) -> dict[str, Any]:
        entry: dict[str, Any] = {"t": time.time(), "event": event, "rule": rule, "message": message, **detail}
        if self.participant:
            entry["participant"] = self.participant
        self.log.append(entry)
        key = f"{event}:{rule}"
        self.counts[key] = self.counts.get(key, 0) + 1
        # a refusal is a caller's error; a clip is the documented rule doing its job, frame after frame
        logger.log(
            logging.WARNING if event == "refused" else logging.INFO, "%s (%s): %s", event, rule, message
        )
        if self.sink is not None:
            try:
                self.sink(entry)
            except Exception:  # an audit sink failing must never stop the guard from refusing
                logger.exception("safety sink failed")
        return entry

    def note_refusal(self, exc: Exception) -> None:
        """Log a refusal raised elsewhere (a value the wire cannot carry)."""
        detail: dict[str, Any] = {}
        if isinstance(exc, LimitError):
            detail = {"field": exc.field, "value": repr(exc.value)}
        self._record("refused", "value", str(exc), **detail)

    def note_clip(self, rule: str, requested_ua: int, sent_ua: int, why: str) -> None:
        self._record(
            "clipped",
            rule,
            f"pulse height lowered from {requested_ua} to {sent_ua} µA: {why}",
            requested_ua=requested_ua,
            sent_ua=sent_ua,
        )

    def note_electrode_clips(self, rule: str, message: str, **detail: Any) -> None:
        """Electrodes whose own heights were lowered (firmware v2: each electrode to its own limit)."""
        self._record("clipped", rule, message, **detail)

    def _check_charge(self, rule: str, charge_nc: float, what: str, **detail: Any) -> None:
        """Refuse (rule ``rule``) a pulse whose charge exceeds the limit; ``what`` names the pulse and its
        charge in the message."""
        if charge_nc > self.max_charge_nc + _EPS:
            raise self.refusal(
                rule,
                f"{what} exceeds the charge limit of {self.max_charge_nc:g} nC",
                charge_nc=charge_nc,
                **detail,
            )

    def refusal(self, rule: str, message: str, **detail: Any) -> SafetyError:
        """A refusal under ``rule``, recorded (log, logger, sink); the caller raises it."""
        self._record("refused", rule, message, **detail)
        return SafetyError(f"{message}; nothing was sent")

    # --- limits ---------------------------------------------------------------------------------------------

    def _region_map(self, electrodes: int) -> tuple[int, ...] | None:
        if self.regions_ua is None:
            return None
        rmap = self.region_of
        if rmap is None and electrodes == len(TACTDEFORM_REGION_OF) and len(self.regions_ua) == 9:
            rmap = TACTDEFORM_REGION_OF
        if rmap is not None and len(rmap) == electrodes:
            return rmap
        return None

    def electrode_limits(self, electrodes: int) -> list[int]:
        """The regional limit of each application electrode (cap when there are no regions; the lowest
        regional amplitude for every electrode when their positions are unknown)."""
        return list(self._limits(electrodes)[0])

    def regions_for(self, electrodes: int) -> tuple[int, ...] | None:
        """The region of each of ``electrodes`` application electrodes, or None when their positions are
        unknown (no region map of that length, and not the TactDeform array)."""
        if self.region_of is not None:
            return self.region_of if len(self.region_of) == electrodes else None
        return TACTDEFORM_REGION_OF if electrodes == len(TACTDEFORM_REGION_OF) else None

    @property
    def positions_matter(self) -> bool:
        """True when an electrode's limit depends on its region (the profile's regions differ)."""
        return self.regions_ua is not None and len({min(v, self.cap_ua) for v in self.regions_ua}) > 1

    def require_positions(self, electrodes: int, what: str = "frame") -> None:
        """Refuse when the regional limits of ``electrodes`` application electrodes cannot be told apart
        by position: no region map of that length, and not the 32-electrode TactDeform array."""
        if not self.positions_matter or self._region_map(electrodes) is not None:
            return
        if self.region_of is not None:
            src = self.region_map.source if self.region_map is not None else "the region map"
            why = f"{src} places {len(self.region_of)} electrode(s)"
        else:
            why = "no array file gives their positions; only the 32-electrode TactDeform array's are known"
        raise self.refusal(
            "region",
            f"{what} of {electrodes} electrode(s): the region of electrodes 0-{electrodes - 1} cannot be "
            f"determined ({why}), and the profile{' of ' + self.participant if self.participant else ''} has "
            "different limits per region; "
            "give the electrode-array file (--array) so each limit follows the electrode's position",
            electrodes=electrodes,
        )

    def _limits(self, electrodes: int) -> tuple[tuple[int, ...], tuple[int, ...] | None]:
        """:meth:`electrode_limits` and the region map, computed once per electrode count and set of limits
        (every frame needs them; the key holds the public attributes, so changing one takes effect)."""
        key = (electrodes, self.cap_ua, self.regions_ua, self.region_of, self.channels)
        cached = self._limits_cache
        if cached is not None and cached[0] == key:
            return cached[1], cached[2]
        rmap = self._region_map(electrodes)
        if self.regions_ua is None:
            limits = (self.cap_ua,) * electrodes
        elif rmap is None:
            limits = (min(min(self.regions_ua), self.cap_ua),) * electrodes
        else:
            limits = tuple(min(self.regions_ua[r], self.cap_ua) for r in rmap)
        if self.channels is not None:
            own = self.channels.application_limits(electrodes)
            limits = tuple(min(a, b) for a, b in zip(limits, own))
        self._limits_cache = (key, limits, rmap)
        return limits, rmap

    def charge_limit_ua(self, width_us: int) -> int:
        """The largest current (10 µA steps) whose pulse of ``width_us`` stays within the charge limit."""
        if width_us <= 0:
            return MAX_CURRENT_UA
        ua = self.max_charge_nc * 1000.0 / width_us
        return int(min(MAX_CURRENT_UA, math.floor(ua / CURRENT_STEP_UA + _EPS) * CURRENT_STEP_UA))

    def base_limit_ua(self, width_us: int) -> int:
        """Ceiling, cap and charge: what any frame may carry before its electrodes are known."""
        return min(MAX_CURRENT_UA, self.cap_ua, self.charge_limit_ua(width_us))

    def frame_limit(self, levels: Sequence[int] | None, width_us: int) -> tuple[int, dict[str, Any]]:
        """The lowest limit applicable to a frame, and why."""
        limit = self.base_limit_ua(width_us)
        why: dict[str, Any] = {"rule": "cap" if limit == self.cap_ua else "charge"}
        if self.charge_limit_ua(width_us) > self.cap_ua:
            why = {"rule": "cap"}
        if levels is None:
            return limit, why
        limits, rmap = self._limits(len(levels))
        if rmap is None and self.positions_matter and any(v in _ACTIVE for v in levels):
            self.require_positions(len(levels))
        own = self.channels.application_limits(len(levels)) if self.channels is not None else None
        for i, v in enumerate(levels):
            if v in _ACTIVE and limits[i] < limit:
                limit = limits[i]
                if (
                    own is not None
                    and own[i] == limit
                    and (
                        self.regions_ua is None
                        or rmap is None
                        or (min(self.regions_ua[rmap[i]], self.cap_ua) > limit)
                    )
                ):
                    why = {"rule": "electrode_limit", "electrode": i, "limit_ua": limit}
                    continue
                why = {"rule": "region", "electrode": i, "limit_ua": limit}
                if rmap is not None:
                    why["region"] = rmap[i]
        return limit, why

    # --- the guard: what may be sent ------------------------------------------------------------------------

    def validate_current(
        self, value: object, transfer: CurrentTransfer, field_name: str = "current_ua"
    ) -> int:
        """A wire-valid current (integer, 10 µA steps, within the ceiling) or a logged :class:`LimitError`."""
        try:
            return transfer.check_current(value, field_name)
        except LimitError as exc:
            self._record("refused", "value", str(exc), field=field_name, value=repr(value))
            raise

    def request(self, current_ua: int, field_name: str = "current_ua") -> int:
        """A current a caller asks for (already checked as a wire value): refused above the cap."""
        if current_ua > self.cap_ua:
            raise self.refusal(
                "cap",
                f"{field_name}={current_ua} µA exceeds the cap of {self.cap_ua} µA"
                + (f" for participant {self.participant}" if self.participant else ""),
                requested_ua=current_ua,
                limit_ua=self.cap_ua,
            )
        return current_ua

    def check_config(
        self,
        config: StimConfig,
        *,
        stimulating: bool = False,
        polarity_in_force: str | None = None,
        transfer: CurrentTransfer = DEFAULT_TRANSFER,
    ) -> StimConfig:
        """Refuse a configuration that breaks a limit; return it unchanged otherwise."""
        self.request(config.current_ua)
        if self.polarity is not None and config.polarity != self.polarity:
            raise self.refusal(
                "polarity",
                f"polarity={config.polarity!r} differs from the participant's calibrated {self.polarity!r}",
                requested=config.polarity,
            )
        if self.max_pulse_width_us is not None and config.pulse_width_us > self.max_pulse_width_us:
            raise self.refusal(
                "pulse_width",
                f"pulse_width_us={config.pulse_width_us} is wider than the calibrated "
                f"{self.max_pulse_width_us} µs (the calibrated amplitudes would feel stronger)",
                requested=config.pulse_width_us,
                limit=self.max_pulse_width_us,
            )
        charge = config.current_ua * config.pulse_width_us / 1000.0
        self._check_charge(
            "charge",
            charge,
            f"current_ua={config.current_ua} × pulse_width_us={config.pulse_width_us} = {charge:g} nC "
            "per pulse",
            limit_nc=self.max_charge_nc,
        )
        if config.sense_current_ua:
            sense_ua = transfer.to_ua(transfer.to_code(config.sense_current_ua, "sense_current_ua"))
            low = min(self.electrode_limits(config.electrode_count) or [self.cap_ua])
            if sense_ua > low + _EPS:
                raise self.refusal(
                    "sense",
                    f"sense_current_ua={config.sense_current_ua} reaches every channel that is off and "
                    f"exceeds the lowest electrode limit of {low} µA",
                    requested_ua=config.sense_current_ua,
                    limit_ua=low,
                )
            sense_charge = sense_ua * config.sense_width_us / 1000.0
            self._check_charge("sense_charge", sense_charge, f"sense pulse of {sense_charge:g} nC")
        scan = worst_scan_us(
            config.electrode_count, config.pulse_width_us, config.discharge_us, config.sense_width_us
        )
        if scan > SCAN_LIMIT_US:
            raise self.refusal(
                "scan_time",
                f"a scan of {config.electrode_count} electrodes at {config.pulse_width_us} µs could take "
                f"{scan / 1000:.0f} ms; the firmware reboots (interrupt watchdog) past "
                f"{INTERRUPT_WATCHDOG_US / 1000:.0f} ms",
                scan_us=scan,
            )
        if stimulating and polarity_in_force is not None and config.polarity != polarity_in_force:
            raise self.refusal(
                "polarity_change",
                f"polarity change {polarity_in_force} -> {config.polarity} while channels are stimulating; "
                "call all_off() first",
            )
        return config

    def frame_height(
        self,
        levels: Sequence[int] | None,
        target_ua: int,
        in_force_ua: int,
        width_us: int,
        *,
        raise_when_idle: bool = True,
    ) -> int:
        """The pulse height for a frame: the target, lowered to the frame's lowest limit and to the ramp.

        ``levels`` is the frame's pattern in application order (None or all-off: no electrode active).
        With no active electrode the height is never raised unless ``raise_when_idle`` (configure and
        set_current set the height for frames to come; a frame that switches everything off leaves it).
        """
        limit, why = self.frame_limit(levels, width_us)
        active = levels is not None and any(v in _ACTIVE for v in levels)
        height = min(target_ua, limit)
        if height < target_ua and active:
            self._record(
                "clipped",
                why["rule"],
                f"frame height lowered from {target_ua} to {height} µA ({why['rule']} limit"
                + (
                    f", electrode {why['electrode']}"
                    + (f" in region {why['region']}" if "region" in why else "")
                    if "electrode" in why
                    else ""
                )
                + ")",
                requested_ua=target_ua,
                sent_ua=height,
                **{k: v for k, v in why.items() if k != "rule"},
            )
        if not active and not raise_when_idle:
            height = min(height, in_force_ua)
        if self.ramp_ua_per_frame is not None and height > in_force_ua + self.ramp_ua_per_frame:
            ramped = in_force_ua + self.ramp_ua_per_frame
            if active:
                self._record(
                    "clipped",
                    "ramp",
                    f"increase from {in_force_ua} to {height} µA limited to {ramped} µA this frame "
                    f"(ramp {self.ramp_ua_per_frame} µA per frame)",
                    requested_ua=height,
                    sent_ua=ramped,
                )
            height = ramped
        return max(0, height)

    def check_scan(self, scan_us: float, period_us: float, gap_min_us: float) -> None:
        """Refuse a frame whose scan would leave the parser no time before the next alarm: back-to-back
        scans starve the main loop, and then not even an all-off would be read."""
        if scan_us > period_us - gap_min_us:
            raise self.refusal(
                "scan_overrun",
                f"this frame's scan takes about {scan_us:.0f} µs of the {period_us:.0f} µs period; with less "
                f"than {gap_min_us:.0f} µs between scans the firmware's parser cannot run and the host could "
                "not switch the frame off (fewer active electrodes, biphasic → monophasic, a shorter pulse "
                "or discharge, or a lower rate fixes it)",
                scan_us=round(scan_us, 1),
                period_us=period_us,
            )

    # --- the interlock: every command as it is written ------------------------------------------------------
    # (:class:`~tactdeform_hw.device.safety.interlock.WireInterlock`; these pass the device's calls on)

    @property
    def firmware(self) -> FirmwareSpec:
        """The firmware version whose reading of the bytes the interlock follows (its limits model v1.2's
        one pulse height per scan)."""
        return self.interlock.firmware

    @firmware.setter
    def firmware(self, spec: FirmwareSpec) -> None:
        self.interlock.firmware = spec

    def shadow(self) -> Shadow:
        """A copy of what the interlock believes the firmware holds (if every byte arrived)."""
        return self.interlock.shadow()

    @property
    def wire_state(self) -> WireState:
        """Every state the interlock believes the firmware can be in."""
        return self.interlock.wire_state

    def mark_unknown(self) -> None:
        """See :meth:`WireInterlock.mark_unknown`."""
        self.interlock.mark_unknown()

    def note_in_step(self, electrode_num: int | None = None) -> None:
        """See :meth:`WireInterlock.note_in_step`."""
        self.interlock.note_in_step(electrode_num)

    def commit(self, state: WireState) -> bool:
        """See :meth:`WireInterlock.commit`."""
        return self.interlock.commit(state)
