"""Upstream eTactileKit calibration profiles: read, write, validate, convert, and ``--participant``."""

from __future__ import annotations

import copy
import datetime as dt
import json
from pathlib import Path
from typing import Any

import pytest

from tactdeform_hw.device.participant.mapping import ChannelMapping
from tactdeform_hw.device.participant.profiles import ParticipantProfile, save_profile
from tactdeform_hw.errors import ProfileError, SafetyError
from tactdeform_hw.formats import calibration_profile as cp
from tactdeform_hw.protocol.units import CurrentTransfer
from tactdeform_hw.render.array import ElectrodeArray

REGIONS = list(ElectrodeArray.tactdeform().regions)


def upstream(count: int = 32, intensity: int = 300) -> dict[str, Any]:
    return {
        "format": "etactilekit_calibration_profile",
        "version": "1.0",
        "created_at": "2026-06-29T22:48:24",
        "layout": {"name": "Finger pad", "slug": "finger-pad", "electrode_count": count},
        "electrodes": [
            {
                "id": i,
                "label": f"E{i}",
                "mapping": (i * 5) % count if count % 5 else i,
                "intensity": intensity,
            }
            for i in range(count)
        ],
    }


def test_reads_and_writes_round_trip(tmp_path: Path) -> None:
    d = upstream()
    d["electrodes"][3]["intensity"] = 120
    prof = cp.calibration_from_dict(d, "p.json")
    assert prof.electrode_count == 32 and prof.intensities()[3] == 120
    assert sorted(prof.mapping()) == list(range(32))
    path = cp.save_calibration_profile(prof, tmp_path / "cal.json")
    again = cp.load_calibration_profile(path)
    assert again.to_dict() == d
    assert json.loads(path.read_text())["format"] == "etactilekit_calibration_profile"


def test_records_in_any_order_are_indexed_by_id() -> None:
    d = upstream(4)
    d["electrodes"].reverse()
    d["electrodes"][0]["intensity"] = 77  # id 3
    prof = cp.calibration_from_dict(d)
    assert prof.intensities() == (300, 300, 300, 77)


def _mutate(path: str, value: Any) -> dict[str, Any]:
    d = upstream(4)
    target: Any = d
    keys = path.split(".")
    for k in keys[:-1]:
        target = target[int(k)] if k.isdigit() else target[k]
    last = keys[-1]
    if value is KeyError:
        del target[last]
    elif last.isdigit():
        target[int(last)] = value
    else:
        target[last] = value
    return d


@pytest.mark.parametrize(
    ("path", "value", "field", "message"),
    [
        # upstream's Validate
        ("layout.electrode_count", 0, "layout.electrode_count", "no layout / electrode_count"),
        ("layout", None, "layout", "no layout / electrode_count"),
        (
            "layout.electrode_count",
            5,
            "electrodes",
            r"electrodes array length \(4\) does not match electrode_count \(5\)",
        ),
        ("electrodes.1.id", 4, "electrodes[1].id", r"Electrode id 4 is out of range \[0, 3\]"),
        ("electrodes.1.id", -1, "electrodes[1].id", "out of range"),
        (
            "electrodes.2.mapping",
            9,
            "electrodes[2].mapping",
            r"Electrode 2 mapping 9 is out of range \[0, 3\]",
        ),
        (
            "electrodes.2.mapping",
            1,
            "electrodes[2].mapping",
            "Duplicate hardware mapping 1; mapping must be a permutation",
        ),
        # this package's limits
        ("electrodes.2.id", 1, "electrodes[2].id", "ids must be unique"),
        ("electrodes.0.intensity", -1, "electrodes[0].intensity", "0 to 1000"),
        (
            "electrodes.0.intensity",
            1001,
            "electrodes[0].intensity",
            r"1001 is out of range: 0 to 1000 \(DAC code; the 10000 µA ceiling",
        ),
        ("electrodes.0.intensity", 1.5, "electrodes[0].intensity", "not an integer"),
        ("electrodes.0.intensity", KeyError, "electrodes[0].intensity", "missing"),
        ("electrodes.0.intensty", 5, "electrodes[0].intensty", "unknown key"),
        ("version", "2.0", "version", "reads version '1.0' only"),
        ("format", "other", "format", "is not 'etactilekit_calibration_profile'"),
        ("layout.electrode_count", 256, "layout.electrode_count", "1 to 255"),
    ],
)
def test_validation_names_field_and_value(path: str, value: Any, field: str, message: str) -> None:
    with pytest.raises(ProfileError, match=message) as err:
        cp.calibration_from_dict(_mutate(path, value), "cal.json")
    assert err.value.field == field and err.value.source == "cal.json"


def test_intensity_limit_follows_the_board_transfer() -> None:
    d = upstream(4, intensity=2000)
    with pytest.raises(ProfileError, match="0 to 1000"):
        cp.calibration_from_dict(d)
    assert cp.calibration_from_dict(d, transfer=CurrentTransfer(ua_per_code=5.0)).intensities()[0] == 2000


def test_to_participant_takes_each_region_at_its_lowest_electrode() -> None:
    d = upstream()
    centre = [i for i, r in enumerate(REGIONS) if r == 4]
    d["electrodes"][centre[0]]["intensity"] = 150
    prof = cp.to_participant(cp.calibration_from_dict(d, "cal.json"), REGIONS)
    assert isinstance(prof, ParticipantProfile)
    assert prof.regions_ua[4] == 1500 and prof.cap_ua == 3000
    assert all(v == 3000 for i, v in enumerate(prof.regions_ua) if i != 4)
    assert prof.calibrated_on == dt.date(2026, 6, 29) and prof.participant == "finger-pad"


def test_conversion_round_trip_is_exact_when_regions_agree() -> None:
    prof = ParticipantProfile("P01", 2000, (100, 200, 300, 400, 500, 600, 700, 800, 900), dt.date(2026, 1, 2))
    cal = cp.from_participant(prof, REGIONS)
    assert cal.intensities() == tuple(prof.regions_ua[r] // 10 for r in REGIONS)
    back = cp.to_participant(cal, REGIONS, participant="P01")
    assert back.regions_ua == prof.regions_ua and back.calibrated_on == prof.calibrated_on


def test_layout_mismatch_is_refused() -> None:
    with pytest.raises(ProfileError, match="16 electrodes, but the array has 32"):
        cp.to_participant(cp.calibration_from_dict(upstream(16)), REGIONS)


def test_participant_flag_takes_either_format(tmp_path: Path) -> None:
    from tactdeform_hw.session import Session, Wiring, read_participant

    cal_path = tmp_path / "cal.json"
    cal_path.write_text(json.dumps(upstream(intensity=250)))
    own = ParticipantProfile("P02", 2500, (2500,) * 9, dt.date(2026, 1, 2))
    own_path = save_profile(own, tmp_path / "p02.json")
    from_cal = read_participant(str(cal_path))[0]
    assert from_cal.cap_ua == 2500 and from_cal.regions_ua == (2500,) * 9
    assert read_participant(str(own_path))[0] == own
    # the profile wires electrode i to channel 5i mod 32: the guard is for a device wired the same way
    wired = ChannelMapping(tuple((i * 5) % 32 for i in range(32)), 32)
    assert Session(participant_file=str(cal_path), wiring=Wiring(mapping=wired)).guard.cap_ua == 2500
    with pytest.raises(SafetyError, match="electrode 1 is calibrated on hardware channel 5"):
        Session(participant_file=str(cal_path))  # the identity wires it elsewhere


def test_a_bad_calibration_file_is_refused_before_anything_is_sent(tmp_path: Path) -> None:
    from tactdeform_hw.session import read_participant

    bad = copy.deepcopy(upstream())
    bad["electrodes"][5]["mapping"] = 0
    path = tmp_path / "bad.json"
    path.write_text(json.dumps(bad))
    with pytest.raises(
        ProfileError,
        match=r"bad.json: electrodes\[5\].mapping: Duplicate hardware mapping 0.*nothing was sent",
    ):
        read_participant(str(path))
    path.write_text('{"format": "etactilekit_calibration_profile", "format": "x"}')
    with pytest.raises(ProfileError, match="duplicate key"):
        read_participant(str(path))
