"""Upstream eTactileKit calibration profiles (``etactilekit_calibration_profile``, version "1.0").

The desktop calibration application and the Unity API keep one record per electrode: its application
``id``, a ``label``, the hardware channel it is wired to (``mapping``) and the DAC code applied when it is
active (``intensity``)::

    {"format": "etactilekit_calibration_profile", "version": "1.0", "created_at": "2026-06-29T22:48:24",
     "layout": {"name": "...", "slug": "...", "electrode_count": 32},
     "electrodes": [{"id": 0, "label": "E0", "mapping": 0, "intensity": 300}, ...]}

A profile is checked as upstream's ``CalibrationProfile.Validate`` does (a positive electrode count,
one record per electrode, ids and mappings in ``0 .. count-1``, the mapping a permutation) and then
against this package's limits, because an intensity goes to a participant: every key known (a misspelt
``intensity`` must not leave a channel at an old value), ids unique, intensities integer DAC codes no
higher than the 10 mA ceiling under the board's current transfer, at most 255 electrodes (the wire's
count).  Upstream clamps a negative intensity to 0 silently; here it is refused.  Every failure raises
:class:`~tactdeform_hw.errors.ProfileError` naming the file and the field.

Conversion to the package's participant profiles goes through the array geometry: the caller gives the
calibration region of each electrode (``ElectrodeArray.regions``).  A region's limit is the lowest
intensity among its electrodes (a per-region profile cannot hold more without letting some electrode
exceed its own calibration), so the conversion is exact only when a region's electrodes agree; the
per-electrode currents stay available (:meth:`CalibrationProfile.currents_ua`) for firmware that takes a
height per electrode.

Each electrode's intensity was calibrated on the hardware channel its ``mapping`` names, so that is the
channel it limits: :func:`calibrated_channels` binds each intensity to its channel for the safety guard,
and :func:`calibration_guard` builds the guard after refusing a device mapping (an array file's
``Mapping_func``, or the identity without one) that wires any electrode elsewhere.  Everything that writes a
profile keeps the mapping.
"""

from __future__ import annotations

import datetime as _dt
import json
import os
import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from ..errors import LimitError, ProfileError
from ..files import write_text_atomically
from ..protocol.constants import CURRENT_STEP_UA, DAC_MAX_CODE, MAX_ELECTRODES
from ..protocol.units import DEFAULT_TRANSFER, CurrentTransfer

FORMAT = "etactilekit_calibration_profile"
VERSION = "1.0"
REGION_COUNT = 9
MAX_FILE_BYTES = 1024 * 1024

_TOP_KEYS = ("format", "version", "created_at", "layout", "electrodes")
_LAYOUT_KEYS = ("name", "slug", "electrode_count")
_ELECTRODE_KEYS = ("id", "label", "mapping", "intensity")
_SLUG_RE = re.compile(r"[^A-Za-z0-9._-]+")


@dataclass(frozen=True)
class CalibrationElectrode:
    id: int
    label: str
    mapping: int
    intensity: int  # DAC code


@dataclass(frozen=True)
class CalibrationProfile:
    """A validated upstream calibration profile (construct one through :func:`calibration_from_dict`)."""

    layout_name: str
    layout_slug: str
    electrodes: tuple[CalibrationElectrode, ...]
    created_at: str | None = None
    source: str = "<calibration profile>"

    @property
    def electrode_count(self) -> int:
        return len(self.electrodes)

    def _by_id(self) -> list[CalibrationElectrode]:
        return sorted(self.electrodes, key=lambda e: e.id)

    def mapping(self) -> tuple[int, ...]:
        """Application electrode → hardware channel, indexed by id (upstream's ``BuildMapping``)."""
        return tuple(e.mapping for e in self._by_id())

    def intensities(self) -> tuple[int, ...]:
        """DAC code per application electrode, indexed by id (upstream's ``BuildIntensities``)."""
        return tuple(e.intensity for e in self._by_id())

    def currents_ua(self, transfer: CurrentTransfer = DEFAULT_TRANSFER) -> tuple[int, ...]:
        """Each electrode's calibrated current, rounded down to the package's 10 µA step."""
        return tuple(_floor_step(transfer.to_ua(code)) for code in self.intensities())

    def channel_currents_ua(self, transfer: CurrentTransfer = DEFAULT_TRANSFER) -> tuple[int, ...]:
        """The calibrated current of each **hardware channel** (indexed by channel): the current of the
        electrode whose ``mapping`` names it."""
        out = [0] * self.electrode_count
        for ch, ua in zip(self.mapping(), self.currents_ua(transfer)):
            out[ch] = ua
        return tuple(out)

    def to_dict(self) -> dict[str, Any]:
        d: dict[str, Any] = {"format": FORMAT, "version": VERSION}
        if self.created_at is not None:
            d["created_at"] = self.created_at
        d["layout"] = {
            "name": self.layout_name,
            "slug": self.layout_slug,
            "electrode_count": self.electrode_count,
        }
        d["electrodes"] = [
            {"id": e.id, "label": e.label, "mapping": e.mapping, "intensity": e.intensity}
            for e in self._by_id()
        ]
        return d


def _floor_step(ua: float) -> int:
    return int(ua // CURRENT_STEP_UA) * CURRENT_STEP_UA


# --- validation ------------------------------------------------------------------------------------------


def _fail(source: str, field: str, problem: str) -> ProfileError:
    return ProfileError(source, field, problem)


def _int(source: str, field: str, value: object) -> int:
    if isinstance(value, bool) or not isinstance(value, int):
        raise _fail(source, field, f"{value!r} is not an integer")
    return value


def _text(source: str, field: str, value: object, *, required: bool = True) -> str:
    if value is None and not required:
        return ""
    if not isinstance(value, str):
        raise _fail(source, field, f"{value!r} is not text")
    return value


def _keys(source: str, where: str, data: Mapping[str, Any], known: Sequence[str]) -> None:
    for key in data:
        if key not in known:
            raise _fail(source, f"{where}{key}", f"unknown key (known: {', '.join(known)})")


def is_calibration_profile(data: object) -> bool:
    """Whether a parsed JSON document says it is an upstream calibration profile."""
    return isinstance(data, Mapping) and data.get("format") == FORMAT


def calibration_from_dict(
    data: Mapping[str, Any], source: str = "<dict>", *, transfer: CurrentTransfer = DEFAULT_TRANSFER
) -> CalibrationProfile:
    """Check a parsed profile as upstream's ``Validate`` does, then against this package's limits."""
    if not isinstance(data, Mapping):
        raise _fail(source, "<top level>", f"expected an object, got {type(data).__name__}")
    if data.get("format") != FORMAT:
        raise _fail(source, "format", f"{data.get('format')!r} is not {FORMAT!r}")
    if data.get("version") != VERSION:
        raise _fail(
            source, "version", f"{data.get('version')!r}: this package reads version {VERSION!r} only"
        )
    _keys(source, "", data, _TOP_KEYS)
    created = data.get("created_at")
    if created is not None:
        _text(source, "created_at", created)
    layout = data.get("layout")
    if not isinstance(layout, Mapping):
        raise _fail(source, "layout", "Profile has no layout / electrode_count.")
    _keys(source, "layout.", layout, _LAYOUT_KEYS)
    count = layout.get("electrode_count")
    if isinstance(count, bool) or not isinstance(count, int) or count <= 0:
        raise _fail(source, "layout.electrode_count", f"{count!r}: Profile has no layout / electrode_count.")
    if count > MAX_ELECTRODES:
        raise _fail(
            source,
            "layout.electrode_count",
            f"{count} is out of range: 1 to {MAX_ELECTRODES} (the wire's count)",
        )
    name = _text(source, "layout.name", layout.get("name"), required=False)
    slug = _text(source, "layout.slug", layout.get("slug"), required=False)
    items = data.get("electrodes")
    if not isinstance(items, list) or len(items) != count:
        have = len(items) if isinstance(items, list) else 0
        raise _fail(
            source,
            "electrodes",
            f"electrodes array length ({have}) does not match electrode_count ({count}).",
        )
    out = _electrodes(source, items, count, _code_limit(transfer), transfer)
    return CalibrationProfile(name, slug, tuple(out), created, source)


def _electrodes(
    source: str, items: list[Any], count: int, limit: int, transfer: CurrentTransfer
) -> list[CalibrationElectrode]:
    """Each electrode of a profile checked: its keys, an id and a hardware mapping in range and each used
    once (the mapping a permutation), an intensity the hardware ceiling allows (``limit``, a DAC code)."""
    seen_mapping = [False] * count
    seen_id: dict[int, int] = {}
    out: list[CalibrationElectrode] = []
    for k, item in enumerate(items):
        where = f"electrodes[{k}]"
        if not isinstance(item, Mapping):
            raise _fail(source, where, f"expected an object, got {type(item).__name__}")
        _keys(source, f"{where}.", item, _ELECTRODE_KEYS)
        for key in ("id", "mapping", "intensity"):
            if key not in item:
                raise _fail(source, f"{where}.{key}", "missing")
        eid = _int(source, f"{where}.id", item["id"])
        if not 0 <= eid < count:
            raise _fail(source, f"{where}.id", f"Electrode id {eid} is out of range [0, {count - 1}].")
        mapping = _int(source, f"{where}.mapping", item["mapping"])
        if not 0 <= mapping < count:
            raise _fail(
                source,
                f"{where}.mapping",
                f"Electrode {eid} mapping {mapping} is out of range [0, {count - 1}].",
            )
        if seen_mapping[mapping]:
            raise _fail(
                source,
                f"{where}.mapping",
                f"Duplicate hardware mapping {mapping}; mapping must be a permutation.",
            )
        seen_mapping[mapping] = True
        if eid in seen_id:
            raise _fail(
                source,
                f"{where}.id",
                f"electrode id {eid} also at electrodes[{seen_id[eid]}]; ids must be unique",
            )
        seen_id[eid] = k
        intensity = _int(source, f"{where}.intensity", item["intensity"])
        if not 0 <= intensity <= limit:
            raise _fail(
                source,
                f"{where}.intensity",
                f"{intensity} is out of range: 0 to {limit} "
                f"(DAC code; the {transfer.max_current_ua} µA ceiling under the board's transfer)",
            )
        label = _text(source, f"{where}.label", item.get("label"), required=False)
        out.append(CalibrationElectrode(eid, label, mapping, intensity))
    return out


def _code_limit(transfer: CurrentTransfer) -> int:
    """The highest DAC code whose current stays within the hardware ceiling (and the DAC's 4095)."""
    code = int((transfer.max_current_ua - transfer.offset_ua) // transfer.ua_per_code)
    while code > 0 and transfer.to_ua(code) > transfer.max_current_ua:
        code -= 1
    return max(0, min(DAC_MAX_CODE, code))


# --- files -----------------------------------------------------------------------------------------------


def read_json_file(path: str | os.PathLike[str]) -> Any:
    """A JSON document from ``path`` (strict JSON, duplicate keys refused), errors naming the file."""
    from tactdeform_hw.device.participant.profiles import no_duplicate_keys, read_profile_bytes

    p = Path(path)
    source = str(p)
    raw = read_profile_bytes(p, MAX_FILE_BYTES, "a calibration profile")
    try:
        return json.loads(raw.decode("utf-8"), object_pairs_hook=no_duplicate_keys)
    except (UnicodeDecodeError, ValueError) as exc:
        raise _fail(source, "file", f"is not valid JSON: {exc}") from exc


def load_calibration_profile(
    path: str | os.PathLike[str], *, transfer: CurrentTransfer = DEFAULT_TRANSFER
) -> CalibrationProfile:
    return calibration_from_dict(read_json_file(path), str(path), transfer=transfer)


def dumps_calibration_profile(profile: CalibrationProfile) -> str:
    return json.dumps(profile.to_dict(), indent=2, ensure_ascii=False) + "\n"


def save_calibration_profile(profile: CalibrationProfile, path: str | os.PathLike[str]) -> Path:
    """Write atomically; what is written must load back."""
    p = Path(path)
    text = dumps_calibration_profile(profile)
    calibration_from_dict(json.loads(text), str(p))
    return write_text_atomically(p, text)


# --- conversion to and from participant profiles ------------------------------------------------------------


def _check_regions(region_of: Sequence[int], count: int, source: str) -> list[int]:
    regions = [int(r) for r in region_of]
    if len(regions) != count:
        raise _fail(
            source,
            "layout.electrode_count",
            f"{count} electrodes, but the array has {len(regions)}: the profile is for another layout",
        )
    for i, r in enumerate(regions):
        if not 0 <= r < REGION_COUNT:
            raise LimitError(f"region_of[{i}]", r, f"0 to {REGION_COUNT - 1}")
    return regions


def to_participant(
    profile: CalibrationProfile,
    region_of: Sequence[int],
    *,
    participant: str | None = None,
    transfer: CurrentTransfer = DEFAULT_TRANSFER,
    pulse_width_us: int = 200,
    polarity: str = "anodic",
    contact_mode: str = "orientation",
    calibrated_on: _dt.date | None = None,
) -> Any:
    """A :class:`~tactdeform_hw.device.participant.profiles.ParticipantProfile`: each region at the lowest
    current
    among its electrodes (empty regions 0), the cap at the highest electrode current."""
    from tactdeform_hw.device.participant.profiles import ParticipantProfile

    source = profile.source
    regions = _check_regions(region_of, profile.electrode_count, source)
    currents = profile.currents_ua(transfer)
    per_region: list[list[int]] = [[] for _ in range(REGION_COUNT)]
    for eid, ua in enumerate(currents):
        per_region[regions[eid]].append(ua)
    regions_ua = tuple(min(v) if v else 0 for v in per_region)
    if calibrated_on is None:
        calibrated_on = _date_of(profile.created_at) or _dt.date.today()
    name = participant or (
        _SLUG_RE.sub("-", profile.layout_slug or profile.layout_name).strip("-")[:64] or "etactilekit"
    )
    return ParticipantProfile(
        participant=name,
        cap_ua=max(currents) if currents else 0,
        regions_ua=regions_ua,
        calibrated_on=calibrated_on,
        pulse_width_us=pulse_width_us,
        polarity=polarity,  # type: ignore[arg-type]
        contact_mode=contact_mode,  # type: ignore[arg-type]
        notes=f"from eTactileKit calibration profile {profile.layout_name or profile.layout_slug} "
        f"({profile.electrode_count} electrodes; regions at their lowest electrode)",
        source=source,
    )


def calibrated_channels(
    profile: CalibrationProfile, *, transfer: CurrentTransfer = DEFAULT_TRANSFER, channel_offset: int = 0
) -> Any:
    """The profile's limits bound to hardware channels
    (:class:`~tactdeform_hw.device.participant.mapping.CalibratedChannels`): each electrode's calibrated
    current on
    the channel its ``mapping`` names, plus ``channel_offset`` (24 for an on-board array, which the kit
    drives as the last 8 of 32 channels)."""
    from tactdeform_hw.device.participant.mapping import CalibratedChannels

    return CalibratedChannels(
        tuple(channel_offset + ch for ch in profile.mapping()),
        profile.currents_ua(transfer),
        f"calibration profile {profile.source}",
    )


def check_mapping(
    profile: CalibrationProfile,
    mapping: Any = None,
    *,
    against: str | None = None,
    transfer: CurrentTransfer = DEFAULT_TRANSFER,
    channel_offset: int = 0,
) -> None:
    """Refuse (:class:`~tactdeform_hw.errors.SafetyError`, one line naming the file, the electrode id, the
    profile's channel and the other channel) a device mapping that disagrees with the profile's:
    ``mapping`` is a :class:`~tactdeform_hw.device.participant.mapping.ChannelMapping`, a list of channels by
    electrode, or None for the identity; ``against`` names it (e.g. "array file grid.json's
    Mapping_func")."""
    calibrated_channels(profile, transfer=transfer, channel_offset=channel_offset).check_wiring(
        mapping, against
    )


def calibration_guard(
    profile: CalibrationProfile,
    region_of: Sequence[int],
    *,
    region_map: Any = None,
    mapping: Any = None,
    against: str | None = None,
    transfer: CurrentTransfer = DEFAULT_TRANSFER,
    participant: str | None = None,
    sink: Any = None,
    channel_offset: int = 0,
) -> Any:
    """The :class:`~tactdeform_hw.device.safety.guard.SafetyGuard` of a calibration profile, for a device
    driven
    with ``mapping`` (a ``ChannelMapping``, a list of channels by electrode, or None for the identity).

    Refuses first a ``mapping`` that disagrees with the profile's (see :func:`check_mapping`).  The guard
    holds every electrode's own calibrated current on the hardware channel it is wired to, for the
    interlock and the guard alike, in place of the regional view of :func:`to_participant` (each region at
    its lowest electrode, which would hold most electrodes below their calibration); the rest comes from
    that participant profile: the cap (the highest electrode), the charge limit, pulse width and polarity.
    ``region_of`` (one region per electrode by id) is what the conversion needs; ``region_map`` (the
    electrode positions, a :class:`~tactdeform_hw.device.participant.regions.RegionMap`) names each
    electrode's region
    in reports.  Pass ``ChannelMapping(profile.mapping(), profile.electrode_count)`` as ``mapping`` to both
    this and ``open_device`` to drive the profile's own wiring."""
    from tactdeform_hw.device.safety.guard import SafetyGuard

    channels = calibrated_channels(profile, transfer=transfer, channel_offset=channel_offset)
    channels.check_wiring(mapping, against)
    person = to_participant(profile, region_of, participant=participant, transfer=transfer)
    return SafetyGuard.from_profile(
        person,
        region_of=region_map if region_map is not None else tuple(region_of),
        sink=sink,
        channels=channels,
        regional=False,
    )


def _date_of(created_at: str | None) -> _dt.date | None:
    if not created_at:
        return None
    try:
        return _dt.datetime.fromisoformat(created_at).date()
    except ValueError:
        return None


def from_participant(
    profile: Any,
    region_of: Sequence[int],
    *,
    mapping: Sequence[int] | None = None,
    layout_name: str = "TactDeform finger pad",
    layout_slug: str = "tactdeform-32",
    transfer: CurrentTransfer = DEFAULT_TRANSFER,
    created_at: str | None = None,
) -> CalibrationProfile:
    """Per-electrode intensities from a participant profile's regions (each electrode its region's
    current as a DAC code); ``mapping`` is the array's application → hardware channel order."""
    count = len(region_of)
    regions = _check_regions(region_of, count, profile.source)
    chans = list(range(count)) if mapping is None else [int(c) for c in mapping]
    electrodes = tuple(
        CalibrationElectrode(
            i,
            f"E{i}",
            chans[i],
            transfer.to_code(profile.regions_ua[regions[i]], f"regions_ua[{regions[i]}]"),
        )
        for i in range(count)
    )
    if created_at is None:
        created_at = _dt.datetime.combine(profile.calibrated_on, _dt.time()).isoformat()
    data = CalibrationProfile(layout_name, layout_slug, electrodes, created_at, profile.source).to_dict()
    return calibration_from_dict(data, profile.source, transfer=transfer)


def read_participant_file(
    path: str | os.PathLike[str], region_of: Sequence[int], *, transfer: CurrentTransfer = DEFAULT_TRANSFER
) -> tuple[Any, CalibrationProfile | None]:
    """``--participant FILE``: a participant profile (.json/.toml) or an upstream calibration profile
    (.json whose ``format`` says so), the latter converted through ``region_of`` and returned too (its
    per-electrode limits and mapping bind hardware channels: :func:`calibrated_channels`)."""
    from tactdeform_hw.device.participant.profiles import load_profile

    p = Path(path)
    if p.suffix.lower() == ".json":
        data = read_json_file(p)
        if is_calibration_profile(data):
            cal = calibration_from_dict(data, str(p), transfer=transfer)
            return to_participant(cal, region_of, transfer=transfer), cal
    return load_profile(p), None


def load_participant_or_calibration(
    path: str | os.PathLike[str], region_of: Sequence[int], *, transfer: CurrentTransfer = DEFAULT_TRANSFER
) -> Any:
    """The participant profile of :func:`read_participant_file` (a calibration profile's regional view
    only: use :func:`read_participant_file` and :func:`calibration_guard` to keep its channel limits)."""
    return read_participant_file(path, region_of, transfer=transfer)[0]
