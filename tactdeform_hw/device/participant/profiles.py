"""Participant profiles: the calibrated limits of one person, as a versioned JSON or TOML file.

A profile is the only thing that tells the device layer how much current a particular finger may receive,
so loading one is strict: every key is checked against the schema below, unknown keys are refused (a
misspelt ``cap_ua`` must not silently leave the ceiling at 10 mA), duplicate JSON keys are refused (the
second one would silently win), and every failure names the file and the field.  A file that fails is
never partly used: :func:`load_profile` either returns a whole, valid profile or raises
:class:`~tactdeform_hw.errors.ProfileError` before any port is opened.

Schema, version 1 (currents in µA, all in 10 µA steps):

=====================  ========  =====================================================================
key                    type      meaning
=====================  ========  =====================================================================
``version``            int       1 (a newer version is refused, never guessed at)
``participant``        str       identifier, 1–64 of ``A-Z a-z 0-9 . _ -``
``cap_ua``             int       the participant's ceiling, 0–10 000 µA
``regions_ua``         int × 9   calibrated amplitude per 3 × 3 region, row-major from the fingertip
                                 side (index 0 = fingertip-left, 4 = centre, 8 = proximal-right);
                                 each ≤ ``cap_ua``
``pulse_width_us``     int       the pulse width the calibration was done at (1–65 535 µs); wider pulses
                                 are refused at configure time because the amplitudes no longer apply
``polarity``           str       ``anodic`` or ``cathodic`` (the calibrated polarity; the other is refused)
``contact_mode``       str       ``orientation`` or ``uniform`` (the participant's preferred contact
                                 rendering, TactDeform task 2)
``calibrated_on``      date      ISO date ``YYYY-MM-DD`` (a TOML date or a JSON string)
``max_charge_nc``      number    optional charge-per-pulse limit in nC (default ``cap_ua × pulse_width_us``)
``ramp_ua_per_frame``  int       optional largest increase of the pulse height from one frame to the next
``notes``              str       optional free text
=====================  ========  =====================================================================
"""

from __future__ import annotations

import datetime as _dt
import json
import math
import os
import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

from tactdeform_hw.errors import ProfileError
from tactdeform_hw.files import write_text_atomically
from tactdeform_hw.protocol.constants import CURRENT_STEP_UA, MAX_CURRENT_UA, U16_MAX

PROFILE_VERSION = 1
REGION_COUNT = 9
CENTRE_REGION = 4
MAX_PROFILE_BYTES = 64 * 1024

Polarity = Literal["anodic", "cathodic"]
ContactMode = Literal["orientation", "uniform"]
POLARITIES: tuple[str, ...] = ("anodic", "cathodic")
CONTACT_MODES: tuple[str, ...] = ("orientation", "uniform")

REQUIRED_KEYS: tuple[str, ...] = (
    "version",
    "participant",
    "cap_ua",
    "regions_ua",
    "pulse_width_us",
    "polarity",
    "contact_mode",
    "calibrated_on",
)
OPTIONAL_KEYS: tuple[str, ...] = ("max_charge_nc", "ramp_ua_per_frame", "notes")
_PARTICIPANT_RE = re.compile(r"^[A-Za-z0-9._-]{1,64}$")


@dataclass(frozen=True)
class ParticipantProfile:
    """One participant's calibrated limits (validated on construction; invalid values raise
    :class:`~tactdeform_hw.errors.ProfileError` naming the field)."""

    participant: str
    cap_ua: int
    regions_ua: tuple[int, ...]
    calibrated_on: _dt.date
    pulse_width_us: int = 200
    polarity: Polarity = "anodic"
    contact_mode: ContactMode = "orientation"
    max_charge_nc: float | None = None
    ramp_ua_per_frame: int | None = None
    notes: str = ""
    version: int = PROFILE_VERSION
    source: str = field(default="<profile>", compare=False, repr=False)

    def __post_init__(self) -> None:
        _validate(self.to_dict(), self.source)
        object.__setattr__(self, "regions_ua", tuple(self.regions_ua))

    @property
    def stimulation_ua(self) -> int:
        """The current a renderer asks for with this profile: the highest calibrated region.  The device
        layer lowers each frame to the lowest region it activates, so asking for the highest is safe."""
        return max(self.regions_ua)

    @property
    def charge_limit_nc(self) -> float:
        """Charge per pulse (per phase) this participant may receive."""
        if self.max_charge_nc is not None:
            return float(self.max_charge_nc)
        return self.cap_ua * self.pulse_width_us / 1000.0

    def to_dict(self) -> dict[str, Any]:
        d: dict[str, Any] = {
            "version": self.version,
            "participant": self.participant,
            "cap_ua": self.cap_ua,
            "regions_ua": list(self.regions_ua),
            "pulse_width_us": self.pulse_width_us,
            "polarity": self.polarity,
            "contact_mode": self.contact_mode,
            "calibrated_on": self.calibrated_on.isoformat()
            if isinstance(self.calibrated_on, _dt.date)
            else self.calibrated_on,
        }
        if self.max_charge_nc is not None:
            d["max_charge_nc"] = self.max_charge_nc
        if self.ramp_ua_per_frame is not None:
            d["ramp_ua_per_frame"] = self.ramp_ua_per_frame
        if self.notes:
            d["notes"] = self.notes
        return d


# --- validation ------------------------------------------------------------------------------------------


def _fail(source: str, fld: str, problem: str) -> ProfileError:
    return ProfileError(source, fld, problem)


def _int(source: str, fld: str, value: object, lo: int, hi: int, step: int = 1, unit: str = "") -> int:
    u = f" {unit}" if unit else ""
    if isinstance(value, bool) or not isinstance(value, int):
        raise _fail(source, fld, f"{value!r} is not an integer (expected {lo} to {hi}{u})")
    if not lo <= value <= hi:
        raise _fail(source, fld, f"{value} is out of range: {lo} to {hi}{u}")
    if step > 1 and value % step:
        raise _fail(source, fld, f"{value} is not a multiple of {step}{u}")
    return value


def _choice(source: str, fld: str, value: object, choices: Sequence[str]) -> str:
    if not isinstance(value, str) or value not in choices:
        raise _fail(source, fld, f"{value!r} is not one of {', '.join(repr(c) for c in choices)}")
    return value


def _date(source: str, fld: str, value: object) -> _dt.date:
    if isinstance(value, _dt.datetime):
        raise _fail(source, fld, f"{value!r} has a time of day; expected a date YYYY-MM-DD")
    if isinstance(value, _dt.date):
        return value
    if isinstance(value, str) and re.fullmatch(r"\d{4}-\d{2}-\d{2}", value):
        try:
            return _dt.date.fromisoformat(value)
        except ValueError as exc:
            raise _fail(source, fld, f"{value!r} is not a valid date ({exc})") from exc
    raise _fail(source, fld, f"{value!r} is not an ISO date YYYY-MM-DD")


def _validate(data: Mapping[str, Any], source: str) -> dict[str, Any]:
    """Check every key of a profile mapping; return the normalised values."""
    if not isinstance(data, Mapping):
        raise _fail(source, "<top level>", f"expected a table of keys, got {type(data).__name__}")
    if "version" not in data:
        raise _fail(source, "version", "missing (this package reads profile version 1)")
    version = data["version"]
    if isinstance(version, bool) or not isinstance(version, int):
        raise _fail(source, "version", f"{version!r} is not an integer version number")
    if version != PROFILE_VERSION:
        raise _fail(
            source, "version", f"unknown version {version}: this package reads version {PROFILE_VERSION} only"
        )
    for key in data:
        if key not in REQUIRED_KEYS and key not in OPTIONAL_KEYS:
            raise _fail(source, str(key), f"unknown key (known: {', '.join(REQUIRED_KEYS + OPTIONAL_KEYS)})")
    for key in REQUIRED_KEYS:
        if key not in data:
            raise _fail(source, key, "missing")
    out: dict[str, Any] = {"version": version}
    participant = data["participant"]
    if not isinstance(participant, str) or not _PARTICIPANT_RE.match(participant):
        raise _fail(source, "participant", f"{participant!r} must be 1-64 characters of A-Z a-z 0-9 . _ -")
    out["participant"] = participant
    cap = _int(source, "cap_ua", data["cap_ua"], 0, MAX_CURRENT_UA, CURRENT_STEP_UA, "µA")
    out["cap_ua"] = cap
    regions = data["regions_ua"]
    if isinstance(regions, (str, bytes)) or not isinstance(regions, Sequence):
        raise _fail(source, "regions_ua", f"{regions!r} is not a list of {REGION_COUNT} currents")
    if len(regions) != REGION_COUNT:
        raise _fail(
            source,
            "regions_ua",
            f"has {len(regions)} value(s); expected {REGION_COUNT} (3 x 3 regions, centre = index 4)",
        )
    out["regions_ua"] = tuple(
        _int(source, f"regions_ua[{i}]", v, 0, cap, CURRENT_STEP_UA, "µA (the participant's cap_ua)")
        for i, v in enumerate(regions)
    )
    out["pulse_width_us"] = _int(source, "pulse_width_us", data["pulse_width_us"], 1, U16_MAX, 1, "µs")
    out["polarity"] = _choice(source, "polarity", data["polarity"], POLARITIES)
    out["contact_mode"] = _choice(source, "contact_mode", data["contact_mode"], CONTACT_MODES)
    out["calibrated_on"] = _date(source, "calibrated_on", data["calibrated_on"])
    charge = data.get("max_charge_nc")
    if charge is not None:
        if isinstance(charge, bool) or not isinstance(charge, (int, float)) or not math.isfinite(charge):
            raise _fail(source, "max_charge_nc", f"{charge!r} is not a finite number of nC")
        hw = MAX_CURRENT_UA * U16_MAX / 1000.0
        if not 0 <= charge <= hw:
            raise _fail(source, "max_charge_nc", f"{charge} is out of range: 0 to {hw:g} nC")
        out["max_charge_nc"] = float(charge)
    ramp = data.get("ramp_ua_per_frame")
    if ramp is not None:
        out["ramp_ua_per_frame"] = _int(
            source, "ramp_ua_per_frame", ramp, CURRENT_STEP_UA, MAX_CURRENT_UA, CURRENT_STEP_UA, "µA"
        )
    notes = data.get("notes", "")
    if not isinstance(notes, str):
        raise _fail(source, "notes", f"{notes!r} is not text")
    out["notes"] = notes
    return out


def profile_from_dict(data: Mapping[str, Any], source: str = "<dict>") -> ParticipantProfile:
    """A profile from a mapping (as read from JSON or TOML), checked against the schema."""
    v = _validate(data, source)
    return ParticipantProfile(
        participant=v["participant"],
        cap_ua=v["cap_ua"],
        regions_ua=v["regions_ua"],
        calibrated_on=v["calibrated_on"],
        pulse_width_us=v["pulse_width_us"],
        polarity=v["polarity"],
        contact_mode=v["contact_mode"],
        max_charge_nc=v.get("max_charge_nc"),
        ramp_ua_per_frame=v.get("ramp_ua_per_frame"),
        notes=v["notes"],
        version=v["version"],
        source=source,
    )


# --- files -----------------------------------------------------------------------------------------------


def no_duplicate_keys(pairs: list[tuple[str, Any]]) -> dict[str, Any]:
    """``object_pairs_hook`` for ``json.loads`` that refuses a key given twice: the standard library keeps
    the last one silently, and a profile whose limit is written twice must not pick one unseen."""
    out: dict[str, Any] = {}
    for k, v in pairs:
        if k in out:
            raise ValueError(f"duplicate key {k!r}")
        out[k] = v
    return out


def _reject_constant(name: str) -> None:
    raise ValueError(f"{name} is not a number a profile may hold")


def _file_format(path: Path) -> str:
    ext = path.suffix.lower()
    if ext == ".json":
        return "json"
    if ext == ".toml":
        return "toml"
    raise ProfileError(str(path), "file", f"extension {ext or '(none)'!r} is neither .json nor .toml")


def _toml_loads(text: str, source: str) -> dict[str, Any]:
    try:
        import tomllib
    except ModuleNotFoundError:  # Python 3.10: the same parser, as the tomli package (a dependency there)
        try:
            import tomli as tomllib  # type: ignore[no-redef,import-not-found,unused-ignore]
        except ModuleNotFoundError as exc:
            raise ProfileError(
                source, "file", "reading TOML on Python 3.10 needs the 'tomli' package"
            ) from exc
    data: dict[str, Any] = tomllib.loads(text)
    return data


def read_profile_bytes(path: Path, max_bytes: int, kind: str) -> bytes:
    """The bytes of a profile file, refused with a :class:`ProfileError` naming the file when it cannot be
    read or is larger than ``max_bytes`` (``kind`` names what the limit is for, "a profile")."""
    source = str(path)
    try:
        raw = path.read_bytes()
    except OSError as exc:
        raise ProfileError(source, "file", f"cannot be read ({exc.strerror or exc})") from exc
    if len(raw) > max_bytes:
        raise ProfileError(source, "file", f"is {len(raw)} bytes; {kind} is at most {max_bytes}")
    return raw


def load_profile(path: str | os.PathLike[str]) -> ParticipantProfile:
    """Read and check a profile; JSON or TOML by extension."""
    p = Path(path)
    source = str(p)
    fmt = _file_format(p)
    raw = read_profile_bytes(p, MAX_PROFILE_BYTES, "a profile")
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise ProfileError(source, "file", f"is not UTF-8 text ({exc})") from exc
    try:
        if fmt == "json":
            data = json.loads(text, object_pairs_hook=no_duplicate_keys, parse_constant=_reject_constant)
        else:
            data = _toml_loads(text, source)
    except ValueError as exc:  # json.JSONDecodeError and tomllib.TOMLDecodeError are ValueErrors
        raise ProfileError(source, "file", f"is not valid {fmt.upper()}: {exc}") from exc
    return profile_from_dict(data, source)


def _toml_value(v: Any) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, (int, float)):
        return repr(v)
    if isinstance(v, _dt.date):
        return v.isoformat()
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    return json.dumps(str(v), ensure_ascii=False)  # a JSON string is a valid TOML basic string


def dumps_profile(profile: ParticipantProfile, fmt: str = "json") -> str:
    d = profile.to_dict()
    if fmt == "json":
        return json.dumps(d, indent=2, ensure_ascii=False) + "\n"
    d["calibrated_on"] = profile.calibrated_on
    return "".join(f"{k} = {_toml_value(v)}\n" for k, v in d.items())


def save_profile(profile: ParticipantProfile, path: str | os.PathLike[str]) -> Path:
    """Write a profile (format by extension) atomically: a crash mid-write never leaves half a file where
    a valid profile used to be."""
    p = Path(path)
    text = dumps_profile(profile, _file_format(p))
    profile_from_dict(json.loads(dumps_profile(profile, "json")), str(p))  # what we write must load back
    return write_text_atomically(p, text)
