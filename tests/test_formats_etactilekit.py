"""eTactileKit array and pattern files, frames export, and ``tactdeform-hw play`` / ``export``."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from tactdeform_hw.cli import build_parser, main
from tactdeform_hw.cli import play as play_cli
from tactdeform_hw.errors import ConfigurationError, LimitError
from tactdeform_hw.formats import (
    Frame,
    PatternSequence,
    PatternStep,
    dumps_pattern,
    pattern_to_dict,
    read_array_file,
    read_frames_file,
    read_pattern_file,
    sequence_from_frames,
    write_array_file,
    write_pattern_file,
)
from tactdeform_hw.render.array import ElectrodeArray

from .conftest import shared_path


def sample(name: str) -> Path:
    return shared_path("etactilekit-formats", name)


def step_doc(pattern, on=200, off=0, frequency=75, stim_mode=1):
    return [
        {
            "delay": {"ON": on, "OFF": off},
            "pattern": pattern,
            "params": {"frequency": frequency, "stim_mode": stim_mode},
        }
    ]


def write_json(path: Path, doc) -> Path:
    path.write_text(json.dumps(doc))
    return path


class FakeClock:
    """Time that moves only when the player sleeps (plus an optional cost per clock read)."""

    def __init__(self) -> None:
        self.now = 100.0
        self.sleeps: list[float] = []

    def clock(self) -> float:
        return self.now

    def sleep(self, seconds: float) -> None:
        assert seconds >= 0
        self.sleeps.append(seconds)
        self.now += seconds


# --- the shipped samples ------------------------------------------------------------------------------------


def test_sample_array_64_matches_file() -> None:
    path = sample("electrodes_64.json")
    raw = json.loads(path.read_text())
    af = read_array_file(path)
    assert af.electrodes == len(raw["electrodes"]) == raw["Electrodes_Number"]
    np.testing.assert_array_equal(af.array.positions_mm, [[e["x"], e["y"]] for e in raw["electrodes"]])
    assert af.array.radius_mm == raw["electrode_radius"]
    assert af.mapping_func == tuple(raw["Mapping_func"])
    assert af.channel_mapping().app_to_hw == tuple(raw["Mapping_func"])
    assert af.hw_channels == max(raw["Mapping_func"]) + 1
    np.testing.assert_array_equal(af.outline_mm, [[p["x"], p["y"]] for p in raw["outline"]])
    assert not af.on_board and af.pattern_offset == 0 and af.notes == ()
    # y up: the file's first row is the top row.
    assert af.array.positions_mm[0, 1] > af.array.positions_mm[-1, 1]


def test_sample_main_board_needs_the_gui_tolerant_json() -> None:
    path = sample("electrode_array_main_board.json")
    with pytest.raises(json.JSONDecodeError):
        json.loads(path.read_text())
    af = read_array_file(path)
    assert af.board == "on_board" and af.on_board
    assert af.electrodes == 8
    assert len(af.notes) == 1 and "on_board" in af.notes[0] and "line 74" in af.notes[0]
    # The GUI scans 32 channels for the on-board array; its electrodes are the last 8.
    assert af.hw_channels == 32
    assert af.channel_mapping().app_to_hw == tuple(24 + c for c in af.mapping_func)
    assert af.levels_for([0] * 24 + [1, 0, 0, 0, 0, 0, 0, 2]) == (1, 0, 0, 0, 0, 0, 0, 2)
    assert af.levels_for([1] * 8) == (1,) * 8
    with pytest.raises(ConfigurationError, match="has 9 value"):
        af.levels_for([0] * 9)


@pytest.mark.parametrize("name", ["test_pattern.json", "diverging_ring_pattern_64_elecs.json"])
def test_sample_patterns_read_and_round_trip(name: str, tmp_path: Path) -> None:
    path = sample(name)
    raw = json.loads(path.read_text())
    seq = read_pattern_file(path)
    assert len(seq.steps) == len(raw["Pattern_Data"])
    for step, group in zip(seq.steps, raw["Pattern_Data"]):
        entry = group[0]
        assert step.levels == tuple(entry["pattern"])
        assert (step.on_ms, step.off_ms) == (entry["delay"]["ON"], entry["delay"]["OFF"])
        assert (step.frequency_hz, step.stim_mode) == (
            entry["params"]["frequency"],
            entry["params"]["stim_mode"],
        )
    assert seq.execution is raw["Execution"] and seq.simulation is raw["Simulation"]
    assert seq.duration_ms == sum(g[0]["delay"]["ON"] + g[0]["delay"]["OFF"] for g in raw["Pattern_Data"])
    # Writing gives back the same document, and the written text is read identically.
    assert pattern_to_dict(seq) == raw
    out = write_pattern_file(seq, tmp_path / name)
    assert json.loads(out.read_text()) == raw
    assert read_pattern_file(out).steps == seq.steps


def test_sample_ring_fits_the_64_array_and_not_the_main_board() -> None:
    seq = read_pattern_file(sample("diverging_ring_pattern_64_elecs.json"))
    big = read_array_file(sample("electrodes_64.json"))
    assert big.levels_for(seq.steps[0].levels) == seq.steps[0].levels
    board = read_array_file(sample("electrode_array_main_board.json"))
    with pytest.raises(ConfigurationError, match="64 value.*8 electrode"):
        board.levels_for(seq.steps[0].levels, "Pattern_Data[0][0].pattern")


# --- malformed pattern files: the error names the field and the position -----------------------------------


def _pattern_with(tmp_path: Path, mutate) -> Path:
    doc = {"Execution": True, "Simulation": True, "Pattern_Data": [step_doc([0, 1, 0, 2]) for _ in range(5)]}
    mutate(doc)
    return write_json(tmp_path / "p.json", doc)


@pytest.mark.parametrize(
    ("mutate", "expected"),
    [
        (
            lambda d: d["Pattern_Data"][3][0]["delay"].__setitem__("ON", "x"),
            'p.json: Pattern_Data[3][0].delay.ON: expected a non-negative number, got "x"',
        ),
        (
            lambda d: d["Pattern_Data"][1][0]["delay"].__setitem__("OFF", -5),
            "Pattern_Data[1][0].delay.OFF: expected a non-negative number, got -5",
        ),
        (lambda d: d["Pattern_Data"][2][0]["delay"].pop("OFF"), "Pattern_Data[2][0].delay.OFF: missing"),
        (
            lambda d: d["Pattern_Data"][4][0]["params"].pop("frequency"),
            "Pattern_Data[4][0].params.frequency: missing",
        ),
        (
            lambda d: d["Pattern_Data"][0][0]["params"].__setitem__("frequency", 0),
            "Pattern_Data[0][0].params.frequency: expected a stimulation frequency in Hz from 1 to "
            "65535, got 0",
        ),
        (
            lambda d: d["Pattern_Data"][2][0]["params"].__setitem__("stim_mode", 2),
            "Pattern_Data[2][0].params.stim_mode: expected 0 (cathodic) or 1 (anodic)",
        ),
        (
            lambda d: d["Pattern_Data"][1][0]["pattern"].__setitem__(2, 3),
            "Pattern_Data[1][0].pattern[2]: expected 0 (off), 1 (monophasic) or 2 (biphasic), got 3",
        ),
        (lambda d: d["Pattern_Data"][1][0]["pattern"].__setitem__(0, True), "Pattern_Data[1][0].pattern[0]"),
        (
            lambda d: d["Pattern_Data"][3][0]["pattern"].append(0),
            "Pattern_Data[3][0].pattern: has 5 value(s) but Pattern_Data[0][0].pattern has 4",
        ),
        (
            lambda d: d["Pattern_Data"].__setitem__(1, d["Pattern_Data"][1][0]),
            "Pattern_Data[1]: expected a list holding one object",
        ),
        (
            lambda d: d["Pattern_Data"].__setitem__(2, []),
            "Pattern_Data[2]: expected a non-empty list, got []",
        ),
        (lambda d: d.__setitem__("Pattern_Data", []), "Pattern_Data: expected a non-empty list"),
        (lambda d: d.pop("Pattern_Data"), "Pattern_Data: missing"),
        (lambda d: d.__setitem__("Execution", "yes"), 'Execution: expected true or false, got "yes"'),
        (lambda d: d["Pattern_Data"][0][0].pop("delay"), "Pattern_Data[0][0].delay: missing"),
        (
            lambda d: d["Pattern_Data"][0][0].__setitem__("delay", 5),
            "Pattern_Data[0][0].delay: expected an object, got 5",
        ),
        (
            lambda d: d["Pattern_Data"][0][0]["delay"].__setitem__("ON", float("inf")),
            "Pattern_Data[0][0].delay.ON",
        ),
    ],
)
def test_malformed_pattern_names_field_and_position(tmp_path: Path, mutate, expected: str) -> None:
    path = _pattern_with(tmp_path, mutate)
    with pytest.raises(ConfigurationError) as err:
        read_pattern_file(path)
    assert expected in str(err.value)


def test_pattern_optional_fields_and_extra_keys(tmp_path: Path) -> None:
    doc = {"Frequency": 60, "Pattern_Data": [step_doc([1, 0], on=12.5, off=3)]}
    seq = read_pattern_file(write_json(tmp_path / "p.json", doc))
    assert seq.execution and seq.simulation  # optional here, default true
    assert seq.steps[0].on_ms == 12.5 and seq.steps[0].off_ms == 3
    assert seq.extra == {"Frequency": 60}
    written = pattern_to_dict(seq)
    assert written["Frequency"] == 60 and written["Execution"] is True
    assert written["Pattern_Data"][0][0]["delay"] == {"OFF": 3, "ON": 12}  # the GUI reads whole ms


def test_group_with_several_entries_plays_the_first_and_says_so(tmp_path: Path) -> None:
    doc = {"Pattern_Data": [step_doc([1, 0]) + step_doc([0, 1])]}
    seq = read_pattern_file(write_json(tmp_path / "p.json", doc))
    assert [s.levels for s in seq.steps] == [(1, 0)]
    assert "Pattern_Data[0] holds 2 entries" in seq.notes[0]


def test_pattern_syntax_error_reports_line_and_column(tmp_path: Path) -> None:
    path = tmp_path / "broken.json"
    path.write_text('{\n  "Pattern_Data": [\n    [{"pattern": [1, 0}]\n  ]\n}\n')
    with pytest.raises(ConfigurationError, match=r"broken\.json: line 3 column 2\d: expected ',' or '\]'"):
        read_pattern_file(path)
    path.write_text('{"Pattern_Data": [')
    with pytest.raises(ConfigurationError, match="line 1 column 19: unexpected end"):
        read_pattern_file(path)
    with pytest.raises(ConfigurationError, match="cannot read"):
        read_pattern_file(tmp_path / "absent.json")


def test_tolerant_json_rules(tmp_path: Path) -> None:
    path = tmp_path / "array.json"
    path.write_text(
        "{\n outline: [{'x': -3, 'y': 3}, {x: 3, y: 3}, {x: 3, y: -3},],\n"
        ' "electrodes": [{"x": -1, "y": 0}, {"x": 1, "y": 0, },],\n'
        ' "Mapping_func": [1, 0], "electrode_radius": 0.5, "board": some_board,\n}\n'
    )
    af = read_array_file(path)
    assert af.electrodes == 2 and af.board == "some_board" and af.mapping_func == (1, 0)
    assert len(af.outline_mm) == 3 and af.notes


# --- malformed array files ----------------------------------------------------------------------------------


def _array_doc() -> dict:
    return {
        "outline": [{"x": -5, "y": 5}, {"x": 5, "y": 5}, {"x": 5, "y": -5}, {"x": -5, "y": 5}],
        "electrodes": [{"x": -2, "y": 2}, {"x": 2, "y": 2}, {"x": -2, "y": -2}, {"x": 2, "y": -2}],
        "Electrodes_Number": 4,
        "Mapping_func": [3, 2, 1, 0],
        "electrode_radius": 0.75,
    }


@pytest.mark.parametrize(
    ("mutate", "expected"),
    [
        (
            lambda d: d["Mapping_func"].__setitem__(2, 3),
            "Mapping_func[2]: hardware channel 3 is already used by electrode 0",
        ),
        (lambda d: d["Mapping_func"].pop(), "Mapping_func: has 3 entries but 'electrodes' lists 4"),
        (
            lambda d: d["Mapping_func"].__setitem__(1, -1),
            "Mapping_func[1]: expected a hardware channel from 0 to 254, got -1",
        ),
        (
            lambda d: d.__setitem__("Electrodes_Number", 5),
            "Electrodes_Number: says 5 but 'electrodes' lists 4",
        ),
        (lambda d: d["electrodes"][2].pop("y"), "electrodes[2].y: missing"),
        (
            lambda d: d["electrodes"][1].__setitem__("x", "left"),
            'electrodes[1].x: expected a number, got "left"',
        ),
        (lambda d: d["electrodes"][3].__setitem__("z", 4), "electrodes[3].z: the array is three-dimensional"),
        (
            lambda d: d.__setitem__("electrode_radius", 0),
            "electrode_radius: expected a positive number, got 0",
        ),
        (lambda d: d.pop("electrode_radius"), "electrode_radius: missing"),
        (lambda d: d.__setitem__("outline", [{"x": 0, "y": 0}]), "outline: expected at least 3 points"),
        (lambda d: d["outline"][1].__setitem__("y", None), "outline[1].y: expected a number, got null"),
        (lambda d: d.__setitem__("electrodes", {}), "electrodes: expected a non-empty list"),
        (
            lambda d: d["electrodes"][1].update(x=-2, y=2),
            "positions_mm[0] and positions_mm[1] are the same point",
        ),
    ],
)
def test_malformed_array_names_field_and_position(tmp_path: Path, mutate, expected: str) -> None:
    doc = _array_doc()
    mutate(doc)
    path = write_json(tmp_path / "a.json", doc)
    with pytest.raises(ConfigurationError) as err:
        read_array_file(path)
    assert expected in str(err.value)
    assert str(err.value).startswith("a.json: ")


def test_array_defaults_and_round_trip(tmp_path: Path) -> None:
    doc = _array_doc()
    del doc["Mapping_func"], doc["outline"], doc["Electrodes_Number"]
    af = read_array_file(write_json(tmp_path / "a.json", doc))
    assert af.mapping_func == (0, 1, 2, 3) and af.outline_mm.shape == (0, 2)

    pad = ElectrodeArray.tactdeform(mapping=list(range(31, -1, -1)))
    out = write_array_file(pad, tmp_path / "pad.json")
    back = read_array_file(out)
    np.testing.assert_allclose(back.array.positions_mm, pad.positions_mm)
    assert back.array.radius_mm == pytest.approx(pad.radius_mm)
    assert back.mapping_func == tuple(range(31, -1, -1))
    # The written outline encloses every electrode disc.
    lo, hi = back.outline_mm.min(axis=0), back.outline_mm.max(axis=0)
    assert np.all(pad.positions_mm - pad.radius_mm > lo) and np.all(pad.positions_mm + pad.radius_mm < hi)

    board = read_array_file(write_json(tmp_path / "b.json", {**_array_doc(), "board": "on_board"}))
    out = write_array_file(board.array, tmp_path / "b2.json", board.outline_mm, board.board)
    again = read_array_file(out)
    assert again.mapping_func == board.mapping_func == (3, 2, 1, 0)
    assert again.channel_mapping() == board.channel_mapping()


# --- frames → pattern ---------------------------------------------------------------------------------------


def _frames_file(path: Path, frames: list[dict]) -> Path:
    path.write_text("".join(json.dumps(f) + "\n" for f in frames))
    return path


def _frame(t: float, levels, sent: bool = True, **kw) -> dict:
    return {
        "t": t,
        "state": "approaching",
        "feature": "face",
        "texture": None,
        "electrodes": list(levels),
        "sent": sent,
        **kw,
    }


def test_frames_export_keeps_total_time_and_skips_unsent(tmp_path: Path) -> None:
    n = 32
    frames = []
    for k in range(73):  # a 72 Hz loop for one second, the pattern changing every frame
        levels = [1 if i == k % n else 0 for i in range(n)]
        frames.append(_frame(k / 72.0, levels))
    frames.insert(11, _frame(10.5 / 72.0, [2] * n, sent=False))
    path = _frames_file(tmp_path / "f.jsonl", frames)
    parsed = read_frames_file(path)
    assert len(parsed) == 74 and parsed[11].sent is False
    seq = sequence_from_frames(parsed, last_ms=0)
    assert len(seq.steps) == 72  # the last frame lasts 0 ms and is dropped
    assert all(2 not in s.levels for s in seq.steps)
    # Whole milliseconds, rounded on the cumulative line: the total is the record's length to the ms.
    assert all(float(s.on_ms).is_integer() for s in seq.steps)
    assert sum(s.on_ms for s in seq.steps) == 1000
    assert {s.on_ms for s in seq.steps} <= {13.0, 14.0}
    with_unsent = sequence_from_frames(parsed, sent_only=False, last_ms=0)
    assert any(s.levels == (2,) * n for s in with_unsent.steps)


def test_frames_export_merges_identical_frames(tmp_path: Path) -> None:
    a, b = [1, 0, 0, 0], [0, 1, 0, 0]
    frames = [Frame(t, tuple(lv)) for t, lv in [(0.0, a), (0.1, a), (0.2, a), (0.3, b), (0.4, a)]]
    seq = sequence_from_frames(frames, frequency_hz=100, stim_mode=0)
    assert [(s.levels, s.on_ms) for s in seq.steps] == [(tuple(a), 300), (tuple(b), 100), (tuple(a), 100)]
    assert {(s.frequency_hz, s.polarity) for s in seq.steps} == {(100, "cathodic")}
    unmerged = sequence_from_frames(frames, merge=False)
    assert len(unmerged.steps) == 5


@pytest.mark.parametrize(
    ("line", "expected"),
    [
        ({"t": "0", "electrodes": [0]}, "f.jsonl:2: t: expected a time in seconds"),
        ({"t": 1.0, "electrodes": [0, 7]}, "f.jsonl:2: electrodes[1]: expected 0, 1 or 2, got 7"),
        (
            {"t": 1.0, "electrodes": [0, 1, 0]},
            "f.jsonl:2: electrodes: has 3 level(s) but the first frame has 2",
        ),
        ({"t": -1.0, "electrodes": [0, 1]}, "f.jsonl:2: t: -1.0 goes back in time"),
        ({"t": 1.0, "electrodes": [0, 1], "sent": "yes"}, "f.jsonl:2: sent: expected true or false"),
    ],
)
def test_malformed_frames(tmp_path: Path, line: dict, expected: str) -> None:
    path = _frames_file(tmp_path / "f.jsonl", [{"t": 0.0, "electrodes": [1, 0]}, line])
    with pytest.raises(ConfigurationError) as err:
        read_frames_file(path)
    assert expected in str(err.value)


def test_export_cli_writes_a_pattern_the_player_accepts(tmp_path: Path, capsys) -> None:
    pad = ElectrodeArray.tactdeform()
    frames = [_frame(k * 0.05, [1 if i in (k, k + 1) else 0 for i in range(32)]) for k in range(6)]
    src = _frames_file(tmp_path / "run.jsonl", frames)
    out, arr = tmp_path / "run_pattern.json", tmp_path / "pad.json"
    assert main(["export", str(src), "-o", str(out), "--array-out", str(arr), "--json"]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["steps"] == 6 and summary["electrodes"] == 32
    seq = read_pattern_file(out)
    assert [s.levels for s in seq.steps] == [tuple(f["electrodes"]) for f in frames]
    assert [s.on_ms for s in seq.steps] == [50.0] * 6
    assert read_array_file(arr).array.positions_mm.tolist() == pad.positions_mm.tolist()
    assert main(["play", str(out), "--array", str(arr), "--dry-run"]) == 0

    short = _frames_file(tmp_path / "short.jsonl", [_frame(0.0, [1, 0, 0])])
    assert main(["export", str(short), "-o", str(tmp_path / "x.json")]) == 1
    assert "frames have 3 electrode level(s) but the array tactdeform-32 has 32" in capsys.readouterr().err


def test_export_last_step_default_is_what_the_help_says(tmp_path: Path, capsys) -> None:
    with pytest.raises(SystemExit):
        main(["export", "--help"])
    text = " ".join(capsys.readouterr().out.split())
    assert "median step" not in text
    assert (
        "--last-ms LAST_MS how long the last step lasts (default: to the end of the record plus one frame "
        "interval, the median time between frames)" in text
    )
    # steps of 100, 100 ms; the last sent frame at 0.2 s, the record ends at 0.25 s;
    # frames 100, 100, 50 ms apart
    levels = [[1 if i == k else 0 for i in range(32)] for k in range(4)]
    frames = [
        _frame(0.0, levels[0]),
        _frame(0.1, levels[1]),
        _frame(0.2, levels[2]),
        _frame(0.25, levels[3], sent=False),
    ]
    src, out = _frames_file(tmp_path / "run.jsonl", frames), tmp_path / "run_pattern.json"
    assert main(["export", str(src), "-o", str(out), "--json"]) == 0
    capsys.readouterr()
    assert [s.on_ms for s in read_pattern_file(out).steps] == [100.0, 100.0, 50.0 + 100.0]
    assert main(["export", str(src), "-o", str(out), "--json", "--last-ms", "20"]) == 0
    assert [s.on_ms for s in read_pattern_file(out).steps] == [100.0, 100.0, 20.0]


# --- play ---------------------------------------------------------------------------------------------------


def _pattern_file(tmp_path: Path, steps: list, name: str = "p.json", **top) -> Path:
    return write_json(tmp_path / name, {"Execution": True, "Simulation": True, "Pattern_Data": steps, **top})


def _play(argv: list[str], fake: FakeClock, record: list | None = None, monkeypatch=None) -> int:
    args = build_parser().parse_args(["play", *argv])
    return play_cli.run(args, clock=fake.clock, sleep=fake.sleep)


def test_play_follows_the_schedule_on_the_emulator(tmp_path: Path, monkeypatch, capsys) -> None:
    from tactdeform_hw.device.driver.base import Device

    steps = [step_doc([1, 0, 0, 0], 200, 0), step_doc([0, 2, 0, 0], 100, 50), step_doc([0, 0, 1, 1], 300, 0)]
    path = _pattern_file(tmp_path, steps)
    fake = FakeClock()
    events: list[tuple[str, float, object]] = []
    orig_send, orig_off = Device.send_pattern, Device.all_off

    def send(self, levels):
        orig_send(self, levels)
        emu = self.port.emulator
        events.append(("pattern", round(fake.now - 100.0, 6), tuple(emu.state().stim_pattern[:4])))

    def off(self):
        orig_off(self)
        events.append(("off", round(fake.now - 100.0, 6), self.current_ua))

    monkeypatch.setattr(Device, "send_pattern", send)
    monkeypatch.setattr(Device, "all_off", off)
    assert _play([str(path), "--current-ua", "1500", "--json", "--quiet"], fake) == 0
    summary = json.loads(capsys.readouterr().out)
    assert events[:4] == [
        ("pattern", 0.0, (1, 0, 0, 0)),
        ("pattern", 0.2, (0, 2, 0, 0)),
        ("off", 0.3, 0),  # OFF phase after the 100 ms ON of step 2
        ("pattern", 0.35, (0, 0, 1, 1)),
    ]
    assert events[4][:2] == ("off", 0.65)  # all off at the end of the file
    assert summary["steps_played"] == 3 and summary["configures"] == 1
    assert summary["scheduled_ms"] == 650 and summary["elapsed_ms"] == pytest.approx(650)
    assert summary["current_ua"] == 1500 and summary["device_electrodes"] == 4


def test_play_reconfigures_when_rate_or_polarity_changes(tmp_path: Path, capsys) -> None:
    steps = [step_doc([1, 0], 10, 0, 75, 1), step_doc([1, 0], 10, 0, 75, 1), step_doc([0, 1], 10, 0, 125, 0)]
    path = _pattern_file(tmp_path, steps)
    assert _play([str(path), "--json", "--quiet", "--repeat", "2"], FakeClock()) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["steps_played"] == 6
    assert summary["configures"] == 4  # 75 anodic, 125 cathodic, again 75 anodic, 125 cathodic
    assert summary["polarities"] == ["anodic", "cathodic"]


def test_play_maps_through_the_array_file(tmp_path: Path, monkeypatch, capsys) -> None:
    from tactdeform_hw.device.driver.base import Device

    arr = write_json(tmp_path / "a.json", {**_array_doc(), "board": "on_board"})
    path = _pattern_file(tmp_path, [step_doc([0] * 24 + [1, 0, 2, 0] + [0] * 4, 20)])
    seen: list[list[int]] = []
    orig = Device.send_pattern

    def send(self, levels):
        orig(self, levels)
        seen.append(list(self.port.emulator.state().stim_pattern[:32]))

    monkeypatch.setattr(Device, "send_pattern", send)
    assert _play([str(path), "--array", str(arr), "--quiet", "--json"], FakeClock()) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["device_electrodes"] == 32 and summary["mapping"] == [27, 26, 25, 24]
    # Electrode i goes to hardware channel 24 + Mapping_func[i] = 24 + (3 - i).
    expected = [0] * 32
    expected[27], expected[25] = 1, 2
    assert seen == [expected]


def test_play_refuses_what_does_not_fit(tmp_path: Path, capsys) -> None:
    path = _pattern_file(tmp_path, [step_doc([1, 0, 0, 0, 0, 0, 0, 0])])
    assert main(["play", str(path), "--electrodes", "32", "--dry-run"]) == 1
    err = capsys.readouterr().err
    assert "every step has 8 value(s) but --electrodes is 32" in err and "--array" in err
    arr = write_json(tmp_path / "a.json", _array_doc())
    assert main(["play", str(path), "--array", str(arr), "--dry-run"]) == 1
    assert "has 8 value(s) but the array a.json has 4 electrode(s)" in capsys.readouterr().err
    # A current over the ceiling is refused before any port is opened.
    with pytest.raises(LimitError, match="current_ua"):
        _play([str(path), "--device", str(tmp_path / "no-such-port"), "--current-ua", "20000"], FakeClock())
    visual_only = _pattern_file(tmp_path, [step_doc([1, 0])], name="v.json", Execution=False)
    assert main(["play", str(visual_only)]) == 1
    assert "Execution is false" in capsys.readouterr().err
    assert main(["play", str(visual_only), "--dry-run"]) == 0


def test_play_dry_run_plan(tmp_path: Path, capsys) -> None:
    path = _pattern_file(tmp_path, [step_doc([1, 1, 0], 40, 10), step_doc([0, 0, 1], 60, 0)])
    assert main(["play", str(path), "--dry-run", "--json", "--repeat", "3"]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["dry_run"] is True and summary["device"] is None
    assert summary["scheduled_ms"] == 3 * 110
    assert [p["active"] for p in summary["plan"]] == [2, 1] * 3


def test_pattern_sequence_checks_its_own_values() -> None:
    with pytest.raises(ConfigurationError, match="levels\\[1\\]: expected 0, 1 or 2"):
        PatternSequence((PatternStep((0, 5), 10),))
    with pytest.raises(ConfigurationError, match="stim_mode"):
        PatternSequence((PatternStep((0, 1), 10, stim_mode=2),))
    seq = PatternSequence((PatternStep((0, 1), 10.4), PatternStep((1, 1), 20, 5, 100, 0)))
    text = dumps_pattern(seq)
    assert '"pattern": [0, 1]' in text  # one line per pattern
    assert json.loads(text)["Pattern_Data"][1][0] == {
        "delay": {"OFF": 5, "ON": 20},
        "pattern": [1, 1],
        "params": {"frequency": 100, "stim_mode": 0},
    }


def test_frames_export_covers_the_time_before_the_first_send(tmp_path: Path) -> None:
    on = [1, 1, 0, 0]
    frames = [Frame(k * 0.1, (0, 0, 0, 0), "idle", sent=False) for k in range(5)]
    frames += [Frame(0.5, tuple(on), "approaching"), Frame(0.6, tuple(on), "approaching", sent=False)]
    seq = sequence_from_frames(frames)
    # All off until the first send at 0.5 s; the last pattern is held to the end of the record + a frame.
    assert [(s.levels, s.on_ms) for s in seq.steps] == [((0, 0, 0, 0), 500), (tuple(on), 200)]
    never = sequence_from_frames(frames[:5])
    assert [(s.levels, s.on_ms) for s in never.steps] == [((0, 0, 0, 0), 500)]
