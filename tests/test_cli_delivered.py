"""The console and ``--json`` say what was delivered, not what was asked for.

With a participant whose centre region is calibrated at 1200 µA and whose ramp is 400 µA per frame, a
request of 1600 µA on the centre electrodes reaches the board as 400, 800, then 1200 µA.  The commands
must say so — the request, each lowering with its rule (region and limit, ramp), the heights on the wire —
and the figures must match what the emulated board's scans delivered (the audit log replayed on the timed
emulator).
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from tactdeform_hw.cli import main
from tactdeform_hw.cli.replay_log import replay
from tactdeform_hw.device.safety.guard import TACTDEFORM_REGION_OF

PROFILE = """version = 1
participant = "P07"
cap_ua = 2000
regions_ua = [400, 1000, 1000, 1000, 1200, 1000, 1000, 1000, 1000]
pulse_width_us = 200
polarity = "anodic"
contact_mode = "orientation"
calibrated_on = 2024-05-01
ramp_ua_per_frame = 400
"""
CENTRE = ",".join("1" if r == 4 else "0" for r in TACTDEFORM_REGION_OF)
CENTRE_ELECTRODES = [i for i, r in enumerate(TACTDEFORM_REGION_OF) if r == 4]


@pytest.fixture()
def profile(tmp_path: Path) -> Path:
    p = tmp_path / "P07.toml"
    p.write_text(PROFILE, encoding="utf-8")
    return p


def test_send_console_shows_request_lowerings_and_delivered(
    profile: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    rc = main(
        ["send", "--participant", str(profile), "--current-ua", "1600", "--pattern", CENTRE, "--hold", "0.1"]
    )
    assert rc == 0
    out = capsys.readouterr().out
    assert "at 1600 µA" not in out  # the request is never reported as what was sent
    assert "requested 1600 µA; delivered at most 1200 µA" in out
    # the frame's height is set by the first of its electrodes with the lowest limit
    assert "lowered by region 4 limit 1200 µA on electrode 12: 1600 → 1200 µA" in out
    assert "lowered by ramp: 1 frame(s) held below their height, at 800 µA" in out
    assert "pulse heights sent: 400, 800, 1200 µA" in out
    assert "1200 µA at most on electrode(s) 12-13, 18-19 (region 4)" in out


def test_send_json_delivered_matches_the_boards_pulses(
    profile: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    log = tmp_path / "send.jsonl"
    rc = main(
        [
            "send",
            "--participant",
            str(profile),
            "--current-ua",
            "1600",
            "--pattern",
            CENTRE,
            "--hold",
            "0.1",
            "--audit-log",
            str(log),
            "--json",
        ]
    )
    assert rc == 0
    out = json.loads(capsys.readouterr().out)
    d = out["delivered"]
    assert out["requested_current_ua"] == 1600 and d["requested_ua"] == 1600
    assert d["max_delivered_ua"] == 1200 and d["pulse_heights_ua"] == [400, 800, 1200]
    region = [e for e in d["lowered"] if e["rule"] == "region"]
    assert (
        region and region[0]["region"] == 4 and region[0]["limit_ua"] == 1200 and region[0]["sent_ua"] == 1200
    )
    assert region[0]["electrodes"] == [CENTRE_ELECTRODES[0]]
    assert any(e["rule"] == "ramp" and e["sent_ua"] == 800 for e in d["lowered"])
    assert [(e["electrode"], e["max_ua"], e["region"]) for e in d["electrodes"]] == [
        (i, 1200, 4) for i in CENTRE_ELECTRODES
    ]
    # the board's scans, replayed on the timed emulator, agree: the centre channels, up to 1200 µA, ramped
    rep = replay(str(log))
    table = rep.pop("_table")
    live = table["current_ua"] > 0
    assert sorted(set(table["channel"][live].tolist())) == CENTRE_ELECTRODES
    assert float(table["current_ua"][live].max()) == pytest.approx(1200.0)
    heights = sorted({round(float(v)) for v in table["current_ua"][live]})
    assert heights[0] < 1200  # the first scans ran below the final height: the ramp reached the board
    # the clips are in the audit log too, where the report took them from
    lines = [json.loads(x) for x in log.read_text().splitlines()]
    assert any(r["type"] == "safety" and r.get("rule") == "region" for r in lines)
    assert lines[0]["positions_mm"] and lines[0]["mapping"] == list(range(32))


def test_play_json_reports_the_delivered_currents(
    profile: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    seq = {
        "Execution": True,
        "Simulation": True,
        "Pattern_Data": [
            [
                {
                    "delay": {"ON": 30, "OFF": 0},
                    "pattern": [int(v) for v in CENTRE.split(",")],
                    "params": {"frequency": 125, "stim_mode": 1},
                }
            ],
            [
                {
                    "delay": {"ON": 30, "OFF": 0},
                    "pattern": [1 if r == 0 else 0 for r in TACTDEFORM_REGION_OF],
                    "params": {"frequency": 125, "stim_mode": 1},
                }
            ],
        ],
    }
    pat = tmp_path / "two.json"
    pat.write_text(json.dumps(seq))
    rc = main(["play", str(pat), "--participant", str(profile), "--current-ua", "1600", "--quiet", "--json"])
    assert rc == 0
    d = json.loads(capsys.readouterr().out)["delivered"]
    assert d["requested_ua"] == 1600 and d["max_delivered_ua"] <= 1200
    rules = {(e["rule"], e.get("region"), e.get("limit_ua")) for e in d["lowered"]}
    assert ("region", 4, 1200) in rules and ("region", 0, 400) in rules
    per = {e["electrode"]: e["max_ua"] for e in d["electrodes"]}
    assert all(per[i] <= 400 for i, r in enumerate(TACTDEFORM_REGION_OF) if r == 0)
    rc = main(["play", str(pat), "--participant", str(profile), "--current-ua", "1600", "--quiet"])
    text = capsys.readouterr().out
    assert rc == 0 and "requested 1600 µA" in text and "lowered by region 0 limit 400 µA" in text


def test_render_reports_what_was_delivered(profile: Path, capsys: pytest.CaptureFixture[str]) -> None:
    rc = main(
        [
            "render",
            "--scene",
            "cube",
            "--trajectory",
            "approach-face",
            "--participant",
            str(profile),
            "--quiet",
            "--json",
        ]
    )
    assert rc == 0
    d = json.loads(capsys.readouterr().out)["delivered"]
    assert d["requested_ua"] == 1200  # the participant's highest region
    assert d["max_delivered_ua"] <= 1200 and d["pulse_heights_ua"][0] == 400  # ramped from 0
    limits = [400, 1000, 1000, 1000, 1200, 1000, 1000, 1000, 1000]
    assert d["electrodes"] and all(e["max_ua"] <= limits[e["region"]] for e in d["electrodes"])


def test_study_reports_what_was_sent_and_it_matches_the_timed_replay(
    profile: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out_dir = tmp_path / "run"
    rc = main(
        [
            "study",
            "task1",
            "--quick",
            "--out",
            str(out_dir),
            "--participant",
            str(profile),
            "--quiet",
            "--no-pictures",
            "--json",
        ]
    )
    assert rc == 0
    d = json.loads(capsys.readouterr().out)["delivered"]
    report = json.loads((out_dir / "report.json").read_text())
    assert report["sent"] == d
    assert d["requested_ua"] == 1200 and any(e["rule"] == "region" for e in d["lowered"])
    # the highest height an active electrode was sent is the highest current the emulated scans delivered
    assert float(d["max_delivered_ua"]) == report["summary"]["max_current_ua"]
