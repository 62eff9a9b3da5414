"""Regional limits follow each electrode's position, never its place in a list.

The participant's amplitudes belong to regions of the finger pad.  An array file that lists the TactDeform
electrodes in another order must give every electrode the limit of where it sits; an electrode whose region
cannot be determined is refused; and ``replay-log`` judges a session by the same positions.  Deliveries are
judged on the pulses the timed emulator's scans delivered (the audit log replayed), not on the bytes meant.
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from tactdeform_hw.cli import main
from tactdeform_hw.cli.replay_log import replay
from tactdeform_hw.device.participant.regions import (
    TACTDEFORM_POSITIONS_MM,
    region_map_from_positions,
    tactdeform_region_map,
)
from tactdeform_hw.device.safety.guard import TACTDEFORM_REGION_OF, SafetyGuard, grid_regions
from tactdeform_hw.errors import SafetyError

#: Region 0 (fingertip-left) is the most sensitive: 400 µA; every other region 2000 µA.
PROFILE = {
    "version": 1,
    "participant": "P07",
    "cap_ua": 2000,
    "regions_ua": [400] + [2000] * 8,
    "pulse_width_us": 200,
    "polarity": "anodic",
    "contact_mode": "orientation",
    "calibrated_on": "2024-05-01",
}


def _files(tmp_path: Path) -> dict[str, Path]:
    """The TactDeform array listed in reverse order (electrode 31 of the file sits at the fingertip-left,
    region 0), a one-step pattern activating only that electrode, and the profile."""
    positions = list(reversed(TACTDEFORM_POSITIONS_MM))
    array = {
        "outline": [],
        "electrodes": [{"x": x, "y": y} for x, y in positions],
        "Electrodes_Number": 32,
        "Mapping_func": list(range(32)),
        "electrode_radius": 0.7,
    }
    pattern = [0] * 32
    pattern[31] = 1
    seq = {
        "Execution": True,
        "Simulation": True,
        "Pattern_Data": [
            [
                {
                    "delay": {"ON": 60, "OFF": 0},
                    "pattern": pattern,
                    "params": {"frequency": 125, "stim_mode": 1},
                }
            ]
        ],
    }
    out = {
        "array": tmp_path / "reversed.json",
        "pattern": tmp_path / "pattern.json",
        "profile": tmp_path / "P07.json",
    }
    out["array"].write_text(json.dumps(array))
    out["pattern"].write_text(json.dumps(seq))
    out["profile"].write_text(json.dumps(PROFILE))
    return out


def test_tactdeform_regions_come_from_positions() -> None:
    rmap = tactdeform_region_map()
    assert rmap.ambiguous == ()
    assert rmap.resolve(None) == TACTDEFORM_REGION_OF == grid_regions()
    reversed_map = region_map_from_positions(list(reversed(TACTDEFORM_POSITIONS_MM)))
    assert reversed_map.resolve(None) == tuple(reversed(TACTDEFORM_REGION_OF))


def test_guard_limits_follow_positions_not_list_order() -> None:
    from tactdeform_hw.device.participant.profiles import profile_from_dict

    prof = profile_from_dict(PROFILE)
    by_position = SafetyGuard.from_profile(
        prof, region_of=region_map_from_positions(list(reversed(TACTDEFORM_POSITIONS_MM)))
    )
    limits = by_position.electrode_limits(32)
    assert limits[31] == 400 and limits[0] == 2000  # electrode 31 of the file sits in region 0
    frame = [0] * 32
    frame[31] = 1
    assert by_position.frame_limit(frame, 200)[0] == 400
    # the list-order default (the TactDeform array in its own order) would have allowed 2000 µA there
    assert SafetyGuard.from_profile(prof).frame_limit(frame, 200)[0] == 2000


def test_border_electrode_is_refused_only_when_its_regions_differ() -> None:
    # a 4 × 4 grid: the inner columns and rows sit exactly on the third-lines of the pad
    pts = [(x, y) for y in (3.0, 1.0, -1.0, -3.0) for x in (-3.0, -1.0, 1.0, 3.0)]
    rmap = region_map_from_positions(pts, "grid.json")
    assert rmap.candidates[0] == (0,) and rmap.candidates[1] == (0, 1) and rmap.candidates[5] == (0, 1, 3, 4)
    with pytest.raises(
        SafetyError, match=r"electrode 1 at \(-1, 3\) mm of grid.json.*region 0 400 µA, region 1 2000 µA"
    ):
        rmap.resolve(PROFILE["regions_ua"])
    assert rmap.resolve([700] * 9)[1] in (0, 1)  # same limit either way: nothing to decide
    with pytest.raises(SafetyError, match="electrode 1"):
        SafetyGuard(2000, regions_ua=PROFILE["regions_ua"], region_of=rmap)
    # one row of electrodes spans no height: which row of regions they lie in cannot be told
    row = region_map_from_positions([(-4.0, 0.0), (0.0, 0.0), (4.0, 0.0)])
    assert row.candidates == ((0, 3, 6), (1, 4, 7), (2, 5, 8))
    with pytest.raises(SafetyError, match="electrode 0 at"):
        row.resolve(PROFILE["regions_ua"])
    limits = [900, 800, 700] * 3  # each column the same from fingertip to base: the limit is known
    assert [limits[r] for r in row.resolve(limits)] == [900, 800, 700]


def test_no_position_means_refusal_never_a_map_by_index() -> None:
    from tactdeform_hw.device import EtactileKitDevice
    from tactdeform_hw.device.driver.config import StimConfig

    from .safety_helpers import RecordingPort

    guard = SafetyGuard(2000, regions_ua=PROFILE["regions_ua"], participant="P07")
    port = RecordingPort()
    dev = EtactileKitDevice(port, guard=guard)
    dev.configure(StimConfig(electrode_count=8, current_ua=400))  # nothing active yet: no limit depends on it
    written = len(port.writes)
    with pytest.raises(
        SafetyError, match=r"frame of 8 electrode\(s\): the region of electrodes 0-7 cannot be determined"
    ):
        dev.send_pattern([1] + [0] * 7)
    assert len(port.writes) == written  # nothing was sent
    assert guard.counts.get("refused:region") == 1
    dev.close()
    with pytest.raises(SafetyError, match="no finite position"):
        region_map_from_positions([(0.0, 0.0), (float("nan"), 1.0)])
    # the same limit in every region: positions do not matter, nothing is refused
    SafetyGuard(2000, regions_ua=[500] * 9).frame_limit([1] * 8, 200)


def test_play_with_a_reordered_array_delivers_the_limit_of_the_position(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    f = _files(tmp_path)
    log = tmp_path / "session.jsonl"
    rc = main(
        [
            "play",
            str(f["pattern"]),
            "--array",
            str(f["array"]),
            "--participant",
            str(f["profile"]),
            "--current-ua",
            "2000",
            "--audit-log",
            str(log),
            "--quiet",
            "--json",
        ]
    )
    assert rc == 0
    out = json.loads(capsys.readouterr().out)
    assert out["regions"][31] == 0 and out["regions"][0] == 8
    assert out["delivered"]["electrodes"] == [{"electrode": 31, "channel": 31, "max_ua": 400, "region": 0}]
    # what the emulated board's scans delivered, pulse by pulse
    rep = replay(str(log))
    table = rep.pop("_table")
    live = table["current_ua"] > 0
    assert set(table["channel"][live].tolist()) == {31}
    assert 0 < float(table["current_ua"][live].max()) <= 400.0
    assert rep["channels"][31]["pulses"] > 3


def test_replay_log_reports_every_excess_by_position(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    f = _files(tmp_path)
    log = tmp_path / "unguarded.jsonl"
    # played without the profile: nothing limits the electrode at the fingertip-left to its 400 µA
    assert (
        main(
            [
                "play",
                str(f["pattern"]),
                "--array",
                str(f["array"]),
                "--current-ua",
                "2000",
                "--audit-log",
                str(log),
                "--quiet",
            ]
        )
        == 0
    )
    capsys.readouterr()
    rc = main(["replay-log", str(log), "--participant", str(f["profile"]), "--json"])
    assert rc == 3
    out = json.loads(capsys.readouterr().out)
    pulses = out["channels"]["31"]["pulses"] if "31" in out["channels"] else out["channels"][31]["pulses"]
    assert out["above_limit_count"] == pulses > 3  # every pulse, none left out
    assert {(o["channel"], o["electrode"], o["region"], o["limit_ua"]) for o in out["above_limit"]} == {
        (31, 31, 0, 400.0)
    }
    assert out["above_limit_by_channel"][0]["max_current_ua"] == 2000.0
    # the text report names the channel, the electrode, its region and its limit
    assert main(["replay-log", str(log), "--participant", str(f["profile"])]) == 3
    text = capsys.readouterr().out
    assert "EXCESS channel 31 (electrode 31 in region 0, limit 400 µA)" in text
    # judged by the array file given on the command line: the same verdict
    assert (
        main(
            ["replay-log", str(log), "--participant", str(f["profile"]), "--array", str(f["array"]), "--json"]
        )
        == 3
    )
    assert json.loads(capsys.readouterr().out)["above_limit_count"] == pulses


def test_replay_log_without_positions_is_refused_when_regions_differ(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    f = _files(tmp_path)
    log = tmp_path / "eight.jsonl"
    assert (
        main(
            [
                "send",
                "--pattern",
                "1,0,0,0,0,0,0,0",
                "--electrodes",
                "8",
                "--current-ua",
                "500",
                "--audit-log",
                str(log),
            ]
        )
        == 0
    )
    capsys.readouterr()
    assert main(["replay-log", str(log), "--participant", str(f["profile"])]) == 1
    assert "records no electrode positions" in capsys.readouterr().err


def test_play_refuses_an_array_with_an_electrode_on_a_border(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    from tactdeform_hw.emulator.serving.urlhandler.protocol_etactile import forget_shared, shared_emulator

    forget_shared()
    f = _files(tmp_path)
    pts = [(x, y) for y in (3.0, 1.0, -1.0, -3.0) for x in (-3.0, -1.0, 1.0, 3.0)]
    grid = tmp_path / "grid.json"
    grid.write_text(json.dumps({"electrodes": [{"x": x, "y": y} for x, y in pts], "electrode_radius": 0.5}))
    seq = json.loads(f["pattern"].read_text())
    seq["Pattern_Data"][0][0]["pattern"] = [1] + [0] * 15
    pat = tmp_path / "p16.json"
    pat.write_text(json.dumps(seq))
    rc = main(
        [
            "play",
            str(pat),
            "--array",
            str(grid),
            "--participant",
            str(f["profile"]),
            "--current-ua",
            "400",
            "--device",
            "etactile://border",
            "--quiet",
        ]
    )
    assert rc == 1
    err = capsys.readouterr().err
    assert "electrode 1 at (-1, 3) mm of array file grid.json" in err and "cannot be determined" in err
    assert shared_emulator("border") is None  # refused before the port was opened
    forget_shared()


def test_calibrate_lights_each_region_by_position(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    f = _files(tmp_path)
    keys = tmp_path / "keys.txt"
    keys.write_text("+ + a")  # centre up to 20 µA, then stop in the next phase
    rc = main(
        [
            "calibrate",
            "--participant",
            str(tmp_path / "C01.json"),
            "--keys",
            str(keys),
            "--array",
            str(f["array"]),
            "--json",
        ]
    )
    assert rc == 1  # not finished: no profile, but the centre was felt
    out = json.loads(capsys.readouterr().out)
    centre = sorted(i for i, r in enumerate(reversed(TACTDEFORM_REGION_OF)) if r == 4)
    assert sorted(e["electrode"] for e in out["delivered"]["electrodes"]) == centre
    assert {e["region"] for e in out["delivered"]["electrodes"]} == {4}


def test_send_with_an_array_file_limits_by_position(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    f = _files(tmp_path)
    pattern = ",".join("1" if i == 31 else "0" for i in range(32))
    rc = main(
        [
            "send",
            "--array",
            str(f["array"]),
            "--participant",
            str(f["profile"]),
            "--current-ua",
            "2000",
            "--pattern",
            pattern,
            "--json",
        ]
    )
    assert rc == 0
    out = json.loads(capsys.readouterr().out)
    assert out["sent_current_ua"] == 400 and out["emulator_pattern"][31] == 1  # the emulator's registers
    assert out["delivered"]["electrodes"] == [{"electrode": 31, "channel": 31, "max_ua": 400, "region": 0}]


def test_replay_log_with_the_tactdeform_array_named(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    f = _files(tmp_path)
    log = tmp_path / "identity.jsonl"
    corner = ",".join("1" if r == 0 else "0" for r in TACTDEFORM_REGION_OF)
    assert (
        main(["send", "--pattern", corner, "--current-ua", "1000", "--hold", "0.05", "--audit-log", str(log)])
        == 0
    )
    capsys.readouterr()
    # the log records the TactDeform positions; naming the array explicitly gives the same verdict
    for extra in ([], ["--array", "tactdeform"]):
        assert main(["replay-log", str(log), "--participant", str(f["profile"]), "--json", *extra]) == 3
        out = json.loads(capsys.readouterr().out)
        corner_electrodes = {i for i, r in enumerate(TACTDEFORM_REGION_OF) if r == 0}
        assert {o["channel"] for o in out["above_limit"]} == corner_electrodes
        assert all(o["region"] == 0 and o["limit_ua"] == 400 for o in out["above_limit"])


def test_region_map_of_the_kits_own_array_files() -> None:
    from tactdeform_hw.formats import read_array_file

    shared = Path(__file__).resolve().parents[1] / ".." / "shared" / "etactilekit-formats"
    board, grid = shared / "electrode_array_main_board.json", shared / "electrodes_64.json"
    if not board.exists() or not grid.exists():
        pytest.skip(f"{shared} is not available (the shared reference data sits beside the repository)")
    on_board = read_array_file(board)
    # (-5, 15) and (5, 15) on the top row, three per row below: no electrode on a border
    assert on_board.region_map().resolve(PROFILE["regions_ua"]) == (0, 2, 3, 4, 5, 6, 7, 8)
    # channel 24 + Mapping_func
    assert on_board.hardware_regions(on_board.region_map().resolve(None))[24] == (0, 0)
    sixty_four = read_array_file(grid).region_map()
    assert sixty_four.ambiguous == () and sorted(set(sixty_four.resolve(None))) == list(range(9))


def test_replay_log_of_a_v2_session_reports_each_electrode_by_its_own_height(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    # On firmware v2 every electrode has its own height: played under a profile allowing 1000 µA in
    # region 0, electrode 31 (fingertip-left) gets 1000 µA while electrode 0 gets the 2000 µA asked for.
    f = _files(tmp_path)
    seq = json.loads(f["pattern"].read_text())
    seq["Pattern_Data"][0][0]["pattern"][0] = 1
    f["pattern"].write_text(json.dumps(seq))
    loose = tmp_path / "loose.json"
    loose.write_text(json.dumps({**PROFILE, "regions_ua": [1000] + [2000] * 8}))
    log = tmp_path / "v2.jsonl"
    argv = ["play", str(f["pattern"]), "--array", str(f["array"]), "--current-ua", "2000", "--quiet"]
    v2 = ["--device", "etactile://?firmware=v2&timed=0", "--firmware", "v2"]
    assert main([*argv, *v2, "--participant", str(loose), "--audit-log", str(log)]) == 0
    capsys.readouterr()
    # judged against the stricter profile (400 µA in region 0): only electrode 31 is above its limit
    assert main(["replay-log", str(log), "--participant", str(f["profile"]), "--json"]) == 3
    out = json.loads(capsys.readouterr().out)
    assert out["firmware"] == "v2" and out["firmware_source"] == "the log's firmware record"
    channels = {int(k): v for k, v in out["channels"].items()}
    assert channels[31]["heights_ua"] == [1000.0] and channels[0]["heights_ua"] == [2000.0]
    assert out["above_limit_count"] == channels[31]["pulses"] > 3  # every pulse of it, none of electrode 0
    assert [
        (b["channel"], b["electrode"], b["region"], b["limit_ua"], b["max_current_ua"])
        for b in out["above_limit_by_channel"]
    ] == [(31, 31, 0, 400.0, 1000.0)]
    assert main(["replay-log", str(log), "--participant", str(f["profile"])]) == 3
    text = capsys.readouterr().out
    assert "replayed on the firmware v2 model" in text
    assert (
        "EXCESS channel 31 (electrode 31 in region 0, limit 400 µA)" in text
        and "EXCESS channel 0 " not in text
    )
