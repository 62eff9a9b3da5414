"""Participant profiles: schema, formats, and refusals that name the field and send nothing."""

from __future__ import annotations

import datetime as dt
import json
from pathlib import Path

import pytest

from tactdeform_hw.cli import main
from tactdeform_hw.device.participant.profiles import (
    ParticipantProfile,
    dumps_profile,
    load_profile,
    profile_from_dict,
    save_profile,
)
from tactdeform_hw.errors import ProfileError

GOOD: dict[str, object] = {
    "version": 1,
    "participant": "P01",
    "cap_ua": 2000,
    "regions_ua": [1500, 1400, 1500, 1300, 1200, 1300, 1500, 1400, 1500],
    "pulse_width_us": 200,
    "polarity": "anodic",
    "contact_mode": "orientation",
    "calibrated_on": "2024-05-01",
}


def write_json(tmp_path: Path, data: object, name: str = "p.json") -> Path:
    path = tmp_path / name
    path.write_text(json.dumps(data), encoding="utf-8")
    return path


def test_json_and_toml_round_trip(tmp_path: Path) -> None:
    prof = profile_from_dict(GOOD)
    assert prof.calibrated_on == dt.date(2024, 5, 1) and prof.regions_ua[4] == 1200
    assert prof.stimulation_ua == 1500 and prof.charge_limit_nc == 400.0
    for ext in ("json", "toml"):
        path = save_profile(prof, tmp_path / f"P01.{ext}")
        again = load_profile(path)
        assert again == prof
    toml_text = dumps_profile(prof, "toml")
    assert "calibrated_on = 2024-05-01" in toml_text and 'participant = "P01"' in toml_text


def test_a_write_cut_short_leaves_the_profile_that_was_there(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The new text goes to a file beside the profile and replaces it only once whole: a crash mid-write
    (here: the disk fills after half the text) leaves the earlier profile loadable."""
    path = save_profile(profile_from_dict(GOOD), tmp_path / "P01.json")
    before = path.read_text(encoding="utf-8")
    raised = dict(GOOD, cap_ua=1800)

    def half_then_full(self: Path, text: str, encoding: str | None = None) -> int:
        with open(self, "w", encoding=encoding) as f:
            f.write(text[: len(text) // 2])
        raise OSError(28, "No space left on device", str(self))

    monkeypatch.setattr(Path, "write_text", half_then_full)
    with pytest.raises(OSError):
        save_profile(profile_from_dict(raised), path)
    monkeypatch.undo()
    assert path.read_text(encoding="utf-8") == before
    assert load_profile(path) == profile_from_dict(GOOD)


def test_optional_keys(tmp_path: Path) -> None:
    prof = load_profile(
        write_json(tmp_path, {**GOOD, "max_charge_nc": 250.5, "ramp_ua_per_frame": 300, "notes": "x"})
    )
    assert prof.charge_limit_nc == 250.5 and prof.ramp_ua_per_frame == 300 and prof.notes == "x"


BAD_CASES = [
    ({**GOOD, "version": 2}, "version", "unknown version 2"),
    ({k: v for k, v in GOOD.items() if k != "version"}, "version", "missing"),
    ({**GOOD, "version": "1"}, "version", "not an integer"),
    ({**GOOD, "version": True}, "version", "not an integer"),
    ({**GOOD, "cap_ua": 10_010}, "cap_ua", "out of range"),
    ({**GOOD, "cap_ua": -10}, "cap_ua", "out of range"),
    ({**GOOD, "cap_ua": 1995}, "cap_ua", "multiple of 10"),
    ({**GOOD, "cap_ua": 2000.0}, "cap_ua", "not an integer"),
    ({**GOOD, "regions_ua": [100] * 8}, "regions_ua", "expected 9"),
    ({**GOOD, "regions_ua": "100"}, "regions_ua", "not a list"),
    ({**GOOD, "regions_ua": [100] * 8 + [2010]}, "regions_ua[8]", "out of range"),
    ({**GOOD, "regions_ua": [100] * 4 + [None] + [100] * 4}, "regions_ua[4]", "not an integer"),
    ({**GOOD, "regions_ua": [105] + [100] * 8}, "regions_ua[0]", "multiple of 10"),
    ({**GOOD, "pulse_width_us": 0}, "pulse_width_us", "out of range"),
    ({**GOOD, "pulse_width_us": 70_000}, "pulse_width_us", "out of range"),
    ({**GOOD, "polarity": "biphasic"}, "polarity", "not one of"),
    ({**GOOD, "contact_mode": "Uniform"}, "contact_mode", "not one of"),
    ({**GOOD, "calibrated_on": "01/05/2024"}, "calibrated_on", "ISO date"),
    ({**GOOD, "calibrated_on": "2024-02-30"}, "calibrated_on", "not a valid date"),
    ({**GOOD, "participant": ""}, "participant", "1-64"),
    ({**GOOD, "participant": "P 01/../x"}, "participant", "1-64"),
    ({**GOOD, "cap_mA": 2}, "cap_mA", "unknown key"),
    ({k: v for k, v in GOOD.items() if k != "polarity"}, "polarity", "missing"),
    ({**GOOD, "max_charge_nc": "200"}, "max_charge_nc", "finite"),
    ({**GOOD, "ramp_ua_per_frame": 5}, "ramp_ua_per_frame", "out of range"),
    ([1, 2, 3], "<top level>", "table of keys"),
]


@pytest.mark.parametrize(("data", "field", "text"), BAD_CASES, ids=[c[1] + ":" + c[2] for c in BAD_CASES])
def test_malformed_profiles_name_the_field(tmp_path: Path, data: object, field: str, text: str) -> None:
    path = write_json(tmp_path, data)
    with pytest.raises(ProfileError) as err:
        load_profile(path)
    assert err.value.field == field
    assert text in str(err.value) and str(path) in str(err.value) and "nothing was sent" in str(err.value)


def test_file_level_errors(tmp_path: Path) -> None:
    dup = tmp_path / "dup.json"
    dup.write_text('{"version": 1, "cap_ua": 100, "cap_ua": 9000}', encoding="utf-8")
    with pytest.raises(ProfileError, match="duplicate key 'cap_ua'"):
        load_profile(dup)
    nan = tmp_path / "nan.json"
    nan.write_text(json.dumps(GOOD).replace("2000", "NaN"), encoding="utf-8")
    with pytest.raises(ProfileError, match="NaN"):
        load_profile(nan)
    with pytest.raises(ProfileError) as err:
        load_profile(tmp_path / "p.yaml")
    assert err.value.field == "file"
    with pytest.raises(ProfileError, match="cannot be read"):
        load_profile(tmp_path / "missing.json")
    bad_toml = tmp_path / "bad.toml"
    bad_toml.write_text("version = 1\ncap_ua = [", encoding="utf-8")
    with pytest.raises(ProfileError, match="not valid TOML"):
        load_profile(bad_toml)
    big = tmp_path / "big.json"
    big.write_text(" " * 70_000 + "{}", encoding="utf-8")
    with pytest.raises(ProfileError, match="at most"):
        load_profile(big)


def test_toml_native_date_and_datetime_refused(tmp_path: Path) -> None:
    text = dumps_profile(profile_from_dict(GOOD), "toml")
    path = tmp_path / "p.toml"
    path.write_text(text.replace("2024-05-01", "2024-05-01T10:00:00"), encoding="utf-8")
    with pytest.raises(ProfileError) as err:
        load_profile(path)
    assert err.value.field == "calibrated_on"


def test_toml_infinity_is_refused_by_field(tmp_path: Path) -> None:
    path = tmp_path / "p.toml"
    path.write_text(
        dumps_profile(profile_from_dict(GOOD), "toml") + "max_charge_nc = inf\n", encoding="utf-8"
    )
    with pytest.raises(ProfileError) as err:
        load_profile(path)
    assert err.value.field == "max_charge_nc"


def test_constructor_validates_too() -> None:
    with pytest.raises(ProfileError) as err:
        ParticipantProfile("P01", 2000, (100,) * 9 + (100,), dt.date(2024, 1, 1))
    assert err.value.field == "regions_ua"


@pytest.mark.parametrize("command", ["send", "calibrate", "render", "play"])
def test_cli_refuses_bad_profile_before_opening_the_device(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], command: str
) -> None:
    from tactdeform_hw.emulator.serving.urlhandler.protocol_etactile import forget_shared, shared_emulator

    forget_shared()
    bad = write_json(tmp_path, {**GOOD, "cap_ua": 12_000})
    if command in ("render", "play"):
        if command == "render":
            argv = ["render", "--scene", "cube", "--trajectory", "approach-face", "--quiet"]
        else:
            pattern = (
                Path(__file__).resolve().parents[1]
                / ".."
                / "shared"
                / "etactilekit-formats"
                / "test_pattern.json"
            )
            if not pattern.exists():
                pytest.skip(
                    f"{pattern} is not available (the shared reference data sits beside the repository)"
                )
            argv = ["play", str(pattern), "--quiet"]
        rc = main([*argv, "--device", "etactile://bad-profile", "--participant", str(bad)])
        assert rc == 1 and "cap_ua" in capsys.readouterr().err
        assert shared_emulator("bad-profile") is None
        if command == "play":
            # an 8-electrode pattern has no known positions without its array file: its regional limits
            # cannot be told apart, so it is refused, never mapped by index
            good = str(write_json(tmp_path, GOOD, "g.json"))
            rc = main([*argv, "--device", "etactile://no-array?timed=0", "--participant", good])
            assert rc == 1 and "cannot be determined" in capsys.readouterr().err
            argv += ["--array", str(pattern.parent / "electrode_array_main_board.json")]
        rc = main(
            [
                *argv,
                "--device",
                "etactile://good-profile?timed=0",
                "--participant",
                str(write_json(tmp_path, GOOD, "g.json")),
            ]
        )
        assert rc == 0
        capsys.readouterr()
        forget_shared()
        return
    if command == "send":
        argv = [
            "send",
            "--device",
            "etactile://bad-profile",
            "--participant",
            str(bad),
            "--pattern",
            "all:1",
            "--current-ua",
            "100",
        ]
        rc = main(argv)
        assert rc == 1
        assert "cap_ua" in capsys.readouterr().err
        assert shared_emulator("bad-profile") is None  # the port was never opened: nothing sent
    else:
        keys = tmp_path / "k.txt"
        keys.write_text("q")
        rc = main(
            [
                "calibrate",
                "--device",
                "etactile://bad-profile",
                "--participant",
                str(tmp_path / "x.yaml"),
                "--keys",
                str(keys),
            ]
        )
        assert rc == 1
        assert ".json or .toml" in capsys.readouterr().err
        assert shared_emulator("bad-profile") is None
    forget_shared()


def test_send_with_profile_clips_to_region_and_refuses_above_cap(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    from tactdeform_hw.emulator.serving.urlhandler.protocol_etactile import forget_shared

    forget_shared()
    prof = write_json(tmp_path, GOOD)
    rc = main(["send", "--participant", str(prof), "--pattern", "all:1", "--current-ua", "1800", "--json"])
    assert rc == 0
    out = json.loads(capsys.readouterr().out)
    # every region is active: the frame's height is the lowest, the centre's
    assert out["sent_current_ua"] == 1200
    assert any(e["rule"] == "region" for e in out["safety"])
    rc = main(["send", "--participant", str(prof), "--pattern", "all:1", "--current-ua", "2010"])
    assert rc == 1 and "exceeds the cap of 2000" in capsys.readouterr().err
