"""The firmware differential: a tree built on the host against another tree (or the Python model).

The small test firmware (``tests/data/firmware_tiny``) is compared with itself (no divergence) and with a
copy in which one constant changed (its ``'E'`` command answers its byte + 2 instead of + 1): the diff must
find it and shrink the stream to the two bytes that show it.  Built trees are cached by hash in the
package's cache (``$TACTDEFORM_HW_CACHE``), so only the first run of the suite compiles.
"""

from __future__ import annotations

import json
import os
import shutil
from pathlib import Path

import pytest

from tactdeform_hw.cli import main
from tactdeform_hw.emulator.hostbuild import find_compiler
from tactdeform_hw.emulator.hostbuild.diff import (
    CALL_WINDOW_US,
    Comparison,
    Differ,
    HostSide,
    ModelSideV1_2,
    ModelSideV2,
    Observation,
    Side,
    compare,
    diff_firmware,
)
from tactdeform_hw.emulator.hostbuild.statemap import StateMap
from tactdeform_hw.emulator.hostbuild.streams import Stream, off_tick, random_stream
from tactdeform_hw.errors import FirmwareBuildError, LimitError

TINY = Path(__file__).parent / "data" / "firmware_tiny"
MAP = StateMap.from_toml(TINY / "hostbuild_state.toml")

try:
    find_compiler()
    NO_CXX = ""
except FirmwareBuildError as exc:
    NO_CXX = str(exc)

needs_cxx = pytest.mark.skipif(bool(NO_CXX), reason=f"no C++ compiler: {NO_CXX}")


def _copy(tmp_path: Path, name: str, old: str = "", new: str = "") -> Path:
    tree = tmp_path / name
    shutil.copytree(TINY, tree)
    if old:
        unit = tree / "lib" / "Tiny" / "tiny.cpp"
        text = unit.read_text()
        assert text.count(old) == 1
        unit.write_text(text.replace(old, new))
    return tree


@pytest.fixture()
def planted(tmp_path: Path) -> Path:
    """The test firmware with one constant changed: 'E' answers its byte + 2."""
    return _copy(tmp_path, "tiny_plus2", "readByteBlocking() + 1)", "readByteBlocking() + 2)")


@needs_cxx
def test_two_identical_trees_never_diverge(tmp_path: Path) -> None:
    twin = _copy(tmp_path, "twin")
    report = diff_firmware(TINY, str(twin), streams=40, seed=3, state_map=MAP, edges=False)
    assert report.streams_run == 40
    assert report.divergence is None and report.minimal is None
    assert report.equivalences == ()  # two trees: compared exactly


@needs_cxx
def test_the_planted_change_is_found_and_shrunk_to_its_two_bytes(planted: Path) -> None:
    report = diff_firmware(TINY, str(planted), streams=200, seed=0, state_map=MAP, edges=False)
    d = report.divergence
    assert d is not None and report.stream is not None
    assert d.kind == "replies"
    assert 0x45 in d.delivered  # the 'E' that shows it reached both firmwares
    m, md = report.minimal, report.minimal_divergence
    assert m is not None and md is not None
    assert len(m.writes) == 1
    at, data = m.writes[0]
    assert len(data) == 2 and data[0] == ord("E")
    # both sides' values: the original answers byte + 1, the planted copy byte + 2
    assert (md.left, md.right) == (bytes([(data[1] + 1) & 0xFF]), bytes([(data[1] + 2) & 0xFF]))
    # the reproduction replays: the same divergence again, and none once the 'E' is gone
    differ = Differ(TINY, str(planted), state_map=MAP)
    again = differ.first_divergence(m)
    assert again is not None and again.signature == md.signature
    assert differ.first_divergence(Stream(((at, data[1:]),), m.end_us)) is None


@needs_cxx
def test_a_change_in_a_register_is_reported_by_its_name(tmp_path: Path) -> None:
    changed = _copy(tmp_path, "clamp", "constrain(v, 0, 4095)", "constrain(v, 0, 4000)")
    stream = Stream(((off_tick(2000.0), b"V" + (4095).to_bytes(2, "little")),), 12_000.0, "clamp")
    d = Differ(TINY, str(changed), state_map=MAP).first_divergence(stream)
    assert d is not None
    assert (d.kind, d.field, d.left, d.right) == ("state", "dac_code", 4095, 4000)
    assert d.delivered == b"V\xff\x0f"


@needs_cxx
def test_a_firmware_stuck_on_both_sides_is_no_divergence(tmp_path: Path) -> None:
    twin = _copy(tmp_path, "twin")
    stream = Stream(((2000.5, b"H"),), 8000.0, "hang")
    assert Differ(TINY, str(twin), state_map=MAP).first_divergence(stream) is None


@needs_cxx
@pytest.mark.slow  # worker processes
def test_any_number_of_jobs_gives_the_same_report(tmp_path: Path) -> None:
    """Two planted changes (a reply and a register clamp), every stream run: the streams shared by two worker
    processes give the report one process gives, divergence counts, kinds and minimal reproductions alike."""
    tree = _copy(tmp_path, "two_changes", "readByteBlocking() + 1)", "readByteBlocking() + 2)")
    unit = tree / "lib" / "Tiny" / "tiny.cpp"
    unit.write_text(unit.read_text().replace("constrain(v, 0, 4095)", "constrain(v, 0, 4000)"))
    kw: dict[str, object] = {"streams": 60, "seed": 5, "state_map": MAP, "edges": False, "keep_going": True}
    kw["shrink_runs"] = 60
    one = diff_firmware(TINY, str(tree), jobs=1, **kw).to_dict()  # type: ignore[arg-type]
    two = diff_firmware(TINY, str(tree), jobs=2, **kw).to_dict()  # type: ignore[arg-type]
    assert len(one["by_kind"]) >= 2 and one["divergences"] > 2
    for report in (one, two):
        del report["seconds"], report["streams_per_s"]
    assert two == one


def test_jobs_below_one_is_refused_before_anything_runs() -> None:
    with pytest.raises(LimitError, match="jobs=0"):
        diff_firmware(TINY, "v1.2", streams=1, jobs=0)


def test_random_streams_are_reproducible_and_off_the_tick_grid() -> None:
    a, b = random_stream(None, 11), random_stream(None, 11)
    assert a == b and a != random_stream(None, 12)
    for seed in range(200):
        for t, _ in random_stream(None, seed).writes:
            assert t % 1000.0 != 0.0


def test_pulses_compare_within_the_stated_tolerance_only() -> None:
    def obs(start: float, width: float) -> Observation:
        return Observation({}, b"", [(start, start + width, 100, (0,), 1, 0)])

    model = Comparison(exact=False, spec=None, pulse_tolerance_us=0.5)
    assert compare(obs(100.0, 196.8), obs(100.1, 196.6), model, False) is None
    found = compare(obs(100.0, 197.2), obs(100.0, 196.6), model, False)
    assert found is not None and found[0] == "pulses"
    exact = Comparison(exact=True, spec=None)
    assert compare(obs(100.0, 196.8), obs(100.0, 196.6), exact, False) is not None


# --- the command line ------------------------------------------------------------------------------------


@needs_cxx
def test_cli_exit_0_on_identical_trees(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    twin = _copy(tmp_path, "twin")
    code = main(
        [
            "diff-firmware",
            "--firmware-src",
            str(TINY),
            "--against",
            str(twin),
            "--streams",
            "10",
            "--no-edges",
            "--json",
        ]
    )
    out = json.loads(capsys.readouterr().out)
    assert code == 0
    assert out["divergences"] == 0 and out["streams_run"] == 10


@needs_cxx
def test_cli_exit_1_on_a_divergence_with_its_reproduction(
    planted: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    code = main(
        [
            "diff-firmware",
            "--firmware-src",
            str(TINY),
            "--against",
            str(planted),
            "--streams",
            "200",
            "--no-edges",
            "--json",
        ]
    )
    out = json.loads(capsys.readouterr().out)
    assert code == 1
    assert out["divergences"] == 1
    assert out["divergence"]["kind"] == "replies"
    assert len(out["minimal"]["writes"]) == 1 and out["minimal"]["writes"][0]["hex"].startswith("45")


@needs_cxx
def test_cli_text_report_names_both_sides(planted: Path, capsys: pytest.CaptureFixture[str]) -> None:
    code = main(
        [
            "diff-firmware",
            "--firmware-src",
            str(TINY),
            "--against",
            str(planted),
            "--streams",
            "200",
            "--no-edges",
        ]
    )
    out = capsys.readouterr().out
    assert code == 1
    assert "DIVERGENCE" in out and "minimal reproduction (2 bytes" in out and "45 " in out


def test_cli_exit_2_on_a_missing_tree(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    code = main(["diff-firmware", "--firmware-src", str(tmp_path / "nope"), "--against", "v1.2"])
    err = capsys.readouterr().err
    assert code == 2
    assert "--firmware-src" in err and "does not exist" in err and "Traceback" not in err


def test_cli_exit_2_on_an_against_that_is_neither_model_nor_tree(
    capsys: pytest.CaptureFixture[str],
) -> None:
    code = main(["diff-firmware", "--firmware-src", str(TINY), "--against", "v3"])
    err = capsys.readouterr().err
    assert code == 2 and "--against 'v3' is neither v1.2, v2 nor a PlatformIO tree" in err


def test_cli_exit_2_on_no_worker_process(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exc:
        main(["diff-firmware", "--firmware-src", str(TINY), "--against", "v1.2", "--jobs", "0"])
    assert exc.value.code == 2
    assert "--jobs: 0 is out of range: jobs >= 1" in capsys.readouterr().err


def test_cli_exit_2_on_a_negative_stream_count(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exc:
        main(["diff-firmware", "--firmware-src", str(TINY), "--against", "v1.2", "--streams", "-1"])
    assert exc.value.code == 2
    assert "--streams" in capsys.readouterr().err


def test_cli_exit_3_without_a_compiler(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    twin = _copy(tmp_path, "twin")
    monkeypatch.setenv("PATH", str(tmp_path / "empty"))
    monkeypatch.delenv("CXX", raising=False)
    code = main(["diff-firmware", "--firmware-src", str(TINY), "--against", str(twin), "--streams", "1"])
    err = capsys.readouterr().err
    assert code == 3
    assert "needs a C++ compiler" in err and "Traceback" not in err


@needs_cxx
def test_cli_exit_3_names_the_file_and_line_of_a_build_error(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    broken = _copy(tmp_path, "broken", "isr_count++;", "isr_count++ +;")
    code = main(["diff-firmware", "--firmware-src", str(TINY), "--against", str(broken), "--streams", "1"])
    err = capsys.readouterr().err
    assert code == 3
    assert "lib/Tiny/tiny.cpp:" in err and "error:" in err and "Traceback" not in err


# --- upstream trees (not part of the repository) ----------------------------------------------------------


def _upstream(var: str) -> Path:
    if NO_CXX:
        pytest.skip(f"no C++ compiler: {NO_CXX}")
    raw = os.environ.get(var)
    if not raw:
        pytest.skip(f"{var} is not set (a checkout of eTactileKit's 2_Firmware/platform_io_project)")
    path = Path(raw)
    if (path / "2_Firmware" / "platform_io_project").is_dir():
        path = path / "2_Firmware" / "platform_io_project"
    if not (path / "src").is_dir():
        pytest.skip(f"{var}={raw} holds no PlatformIO tree (src/)")
    return path


def test_upstream_v1_2_against_itself_is_exact(tmp_path: Path) -> None:
    tree = _upstream("TACTDEFORM_HW_UPSTREAM_V1_2")
    twin = tmp_path / "twin"
    shutil.copytree(tree / "src", twin / "src")
    shutil.copytree(tree / "lib", twin / "lib")
    report = diff_firmware(tree, str(twin), streams=4, seed=1, edges=False)
    assert report.divergence is None and report.streams_run == 4


@needs_cxx
def test_cli_runs_recorded_streams_first(
    planted: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    vectors = tmp_path / "vectors.jsonl"
    vectors.write_text(
        json.dumps({"id": "quiet", "stream": "4300"})
        + "\n"
        + json.dumps({"id": "echo", "stream": "4507"})
        + "\n"
    )
    args = ["diff-firmware", "--firmware-src", str(TINY), "--against", str(planted)]
    code = main([*args, "--streams", "0", "--recorded", str(vectors), "--json"])
    out = json.loads(capsys.readouterr().out)
    assert code == 1
    assert out["streams_run"] == 2 and out["stream"]["label"] == "recorded echo"
    assert (out["divergence"]["left"], out["divergence"]["right"]) == ("08", "09")


def test_cli_exit_2_on_a_recorded_file_that_is_not_golden_vectors(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    bad = tmp_path / "bad.jsonl"
    bad.write_text('{"id": "x"}\n')
    code = main(["diff-firmware", "--firmware-src", str(TINY), "--against", "v1.2", "--recorded", str(bad)])
    err = capsys.readouterr().err
    assert code == 2 and "--recorded" in err and "bad.jsonl:1" in err


def test_upstream_v2_against_itself_is_exact(tmp_path: Path) -> None:
    tree = _upstream("TACTDEFORM_HW_UPSTREAM_V2")
    twin = tmp_path / "twin"
    shutil.copytree(tree / "src", twin / "src")
    shutil.copytree(tree / "lib", twin / "lib")
    report = diff_firmware(tree, str(twin), streams=4, seed=1, edges=False)
    assert report.divergence is None and report.streams_run == 4


def test_a_pulse_deep_in_a_run_of_back_to_back_scans_may_start_later_by_the_drift_allowance() -> None:
    """Overrun scans run back to back: the host build numbers a pulse within its run (49 here), the other
    side 0 here; the start tolerance takes the larger number (equivalence pulse-numbering)."""

    def obs(start: float, index: int) -> Observation:
        return Observation({}, b"", [(start, start + 6.6, 3, (0,), 1, index)])

    model = Comparison(exact=False, spec=None, pulse_tolerance_us=0.7)
    assert compare(obs(3966.45, 49), obs(3945.6, 0), model, False) is None
    found = compare(obs(3966.45, 0), obs(3945.6, 0), model, False)  # one scan of its own: too late
    assert found is not None and found[1] == "pulse 0 (start)"


class _Scripted:
    """A side showing, at each checkpoint, the state of the last script entry at or before it."""

    def __init__(self, name: str, script: list[tuple[float, dict[str, object]]]) -> None:
        self.name = name
        self.script = script

    def write(self, data: bytes, at_us: float) -> None:
        """Nothing to run: the script is the side."""

    def advance_to(self, t_us: float) -> None:
        """Nothing to run: the script is the side."""

    def observe(self, upto_us: float) -> Observation:
        state = [st for t, st in self.script if t <= upto_us][-1]
        return Observation(dict(state), b"", [])

    def close(self) -> None:
        """Nothing to release."""


class _ScriptedDiffer(Differ):
    """A differ whose two sides are scripted observations (no firmware is built)."""

    def __init__(self, left: _Scripted, right: _Scripted) -> None:
        super().__init__(Path("unused"), "v2")
        self.scripted = (left, right)

    def sides(self) -> tuple[Side, Side]:
        return self.scripted


def test_a_held_difference_gone_at_its_window_s_end_is_resolved_though_another_register_differs() -> None:
    """``electrode_num`` differs at 1000 µs (a call's effects seen at its start); at the end of its window it
    is the same on both sides and ``pulse_width`` differs instead -- a later call's own resolution, held with
    a window of its own and gone by its end: no divergence, two call resolutions (call-resolution)."""
    w = CALL_WINDOW_US
    left = _Scripted(
        "host",
        [
            (0, {"electrode_num": 0, "pulse_width": 0}),
            (1000 + w, {"electrode_num": 8, "pulse_width": 0}),
            (1000 + 2 * w, {"electrode_num": 8, "pulse_width": 5}),
        ],
    )
    right = _Scripted("model", [(0, {"electrode_num": 8, "pulse_width": 5})])
    differ = _ScriptedDiffer(left, right)
    stream = Stream(((1000.0, b"\x00"),), 1000 + 3 * w, "scripted")
    assert differ.first_divergence(stream) is None
    assert differ.call_resolved == 2


def test_a_held_difference_still_there_at_its_window_s_end_is_the_divergence() -> None:
    """The same, but ``electrode_num`` still differs at the window's end: it is reported as first seen."""
    w = CALL_WINDOW_US
    left = _Scripted("host", [(0, {"electrode_num": 0, "pulse_width": 0})])
    right = _Scripted("model", [(0, {"electrode_num": 8, "pulse_width": 5})])
    differ = _ScriptedDiffer(left, right)
    found = differ.first_divergence(Stream(((1000.0, b"\x00"),), 1000 + 3 * w, "scripted"))
    assert found is not None and (found.field, found.at_us, found.left, found.right) == (
        "electrode_num",
        1000.0,
        0,
        8,
    )


def test_an_element_of_an_array_register_is_held_on_its_own() -> None:
    """``stim_pattern[1]`` differs (a pattern's copy seen at its call's start); at the window's end element 1
    is the same and element 3 differs (the next pattern's copy under way): the held one is gone."""
    w = CALL_WINDOW_US
    left = _Scripted(
        "host",
        [
            (0, {"stim_pattern": [0, 0, 0, 0]}),
            (1000 + w, {"stim_pattern": [3, 3, 0, 0]}),
            (1000 + 2 * w, {"stim_pattern": [3, 3, 0, 4]}),
        ],
    )
    right = _Scripted("model", [(0, {"stim_pattern": [3, 3, 0, 4]})])
    differ = _ScriptedDiffer(left, right)
    assert differ.first_divergence(Stream(((1000.0, b"\x00"),), 1000 + 3 * w, "scripted")) is None


def test_a_held_difference_is_gone_once_the_firmware_holds_the_value_the_model_showed() -> None:
    """``electrode_num`` is 0 on the firmware, 8 in the model (a call seen at its start); at the window's end
    the firmware has 8 and the model already 16 (the next command, seen at its call's start): the first
    call is over on both, the second is held on its own and gone by its window's end."""
    w = CALL_WINDOW_US
    left = _Scripted(
        "host",
        [(0, {"electrode_num": 0}), (1000 + w, {"electrode_num": 8}), (1000 + 2 * w, {"electrode_num": 16})],
    )
    right = _Scripted("model", [(0, {"electrode_num": 8}), (1000 + w, {"electrode_num": 16})])
    differ = _ScriptedDiffer(left, right)
    assert differ.first_divergence(Stream(((1000.0, b"\x00"),), 1000 + 3 * w, "scripted")) is None
    assert differ.call_resolved == 2


def test_a_later_difference_that_outlasts_its_own_window_is_the_divergence() -> None:
    """The same, but the firmware never gets to 16: the second difference is reported as it was first seen."""
    w = CALL_WINDOW_US
    left = _Scripted("host", [(0, {"electrode_num": 0}), (1000 + w, {"electrode_num": 8})])
    right = _Scripted("model", [(0, {"electrode_num": 8}), (1000 + w, {"electrode_num": 16})])
    differ = _ScriptedDiffer(left, right)
    found = differ.first_divergence(Stream(((1000.0, b"\x00"),), 1000 + 3 * w, "scripted"))
    assert found is not None and (found.at_us, found.left, found.right) == (1000 + w, 8, 16)


# 1011 bytes at once: 10, then a 39-byte run of commands repeated
_BURST = (
    bytes.fromhex("000100ff00ff00ff00fa")
    + (bytes.fromhex("fffff801fe03000000020001000000ff000200ff00fe0200f5d3ff0002000100ff00ff00ff00fa") * 26)[
        :1001
    ]
)


def test_upstream_v2_a_drop_counted_when_the_model_lands_the_bytes_is_a_call_resolution() -> None:
    """A scan of 255 channels holds the loop while a 1011-byte burst fills the queue past its 1024 bytes: the
    firmware's serial driver drops the last byte as it arrives, the model when its next call lands the
    bytes (after the scan), one call resolution (the 'state rx_dropped' minimal reproduction; the pattern's
    copy under way at the window's end, once a second one, now leaves its unread bytes in the model's queue
    as in the firmware's: test_models_follow_firmware.py)."""
    tree = _upstream("TACTDEFORM_HW_UPSTREAM_V2")
    writes = [(2051.696, "fefcfffd00"), (11634.045, "fcb4f60000fc20fdfefb01"), (12685.187, "08f8fe")]
    stream = Stream(
        (
            *((t, bytes.fromhex(h)) for t, h in writes),
            (13866.204, _BURST),
            (14436.824, bytes.fromhex("fd02fb02")),
        ),
        634436.824,
        "drop while scanning",
    )
    differ = Differ(tree, "v2")
    assert differ.first_divergence(stream) is None
    assert differ.call_resolved == 1


def test_upstream_v1_2_a_register_mid_call_is_the_models_call_resolution() -> None:
    """0xFC 4 arrives at 2000.5 µs; the parser call at the 3000 µs tick stores it some µs into the call, the
    model at the call's start: a checkpoint at 3000.218 µs (the next write) sees 0 against 4, which is gone
    once the call is over (equivalence call-resolution, counted), so the stream does not diverge."""
    tree = _upstream("TACTDEFORM_HW_UPSTREAM_V1_2")
    stream = Stream(((2000.5, bytes.fromhex("fc04")), (3000.218, bytes.fromhex("17"))), 5001.0, "mid-call")
    differ = Differ(tree, "v1.2")
    assert differ.first_divergence(stream) is None
    assert differ.call_resolved == 1
    held = differ.first_divergence(stream, at_us=3000.218)  # a single checkpoint: nothing to wait for
    assert held is not None and (held.field, held.left, held.right) == ("electrode_num", 0, 4)


def test_upstream_v2_overrunning_scans_drift_within_the_run_allowance() -> None:
    """0xF6 65534 makes every scan overrun (an alarm of 15 µs, a scan of 19.2 µs): the firmware's 49th scan
    in a row starts 20.85 µs after the model's, within the run's allowance (equivalence pulse-numbering)."""
    tree = _upstream("TACTDEFORM_HW_UPSTREAM_V2")
    stream = Stream(((2000.5, bytes.fromhex("fc01fe0300f6feff")),), 5946.0, "overrun")
    assert Differ(tree, "v2").first_divergence(stream) is None


def test_upstream_v2_a_call_interrupted_by_an_overrunning_scan_never_answers() -> None:
    """0xF6 65535, then 228 electrodes and 0xFF: the scan that interrupts the 0xFF's call overruns, the
    scans run back to back and neither the firmware nor the model ever answers (the model-only twin is in
    test_models_follow_firmware.py)."""
    tree = _upstream("TACTDEFORM_HW_UPSTREAM_V2")
    writes = ((3901.495, "f6ff"), (3941.495, "ff"), (17119.009, "f8fefce4ff"))
    stream = Stream(tuple((t, bytes.fromhex(h)) for t, h in writes), 30000.0, "starved")
    assert Differ(tree, "v2").first_divergence(stream) is None


def test_v1_2_pulses_are_numbered_by_slot_across_a_run_of_back_to_back_scans() -> None:
    """172 electrodes on a 32-output chain with a discharge of 254 µs: each scan (45.45 ms) overruns the
    10 ms period and the next starts as it returns, 103.3 µs after its alarm would have been (the chip-select
    writes, 0.6 µs a channel under the host build's reading), after 172 channels of which only 32 delivered
    a pulse: the model numbers the second scan's first pulse 172 (its slot in the run), as the host build
    numbers it within its run (pulse-numbering)."""
    side = ModelSideV1_2(timer_origin_us=1010.25, hv513_count=4)
    side.write(bytes.fromhex("f901"), 2360.073)
    side.write(bytes.fromhex("f7fefcac"), 12448.198)
    side.advance_to(68469.0)
    pulses = side.observe(68469.0).pulses
    first_scan = [p for p in pulses if p[0] < 66469.0]
    assert [p[5] for p in first_scan] == list(range(32))  # outputs 0-31: slots 0-31 of the run
    second = [p for p in pulses if p[0] >= 66469.0]
    assert round(second[0][0], 3) == 66572.3 and second[0][3] == (0,) and second[0][5] == 172


# 0xFC 255, a pattern of 255 heights and 0xF6 65534 (a 15 µs alarm): one write, as the differential shrank it
START_RUN_HEX = (
    "fcfffe000003000300ff00ff0001009649ff00010001000000a1c4543bff00ff00020003006ba3ff0001003f130200ff"
    "00010003000200ff00ff00ff00000000000100020003000000e9786ff442b00000ff00030058930100f90dff00ff0002"
    "000300ff00030002000200010001000300ff00ff0002000100ff00ff0003000100ff00ff00867fff0001000300ff0002"
    "00020000000100ff000000ff0056930300dca0000000000100ff00020003000100e92d0d29ff00f9086fa9ff00000000"
    "00000064c8ff0002000100ff000100010003000100010001000100ff000200a0f59c400000ff000000010003000100ff"
    "00ff00010003001aa20100f98c0000030002000100ff0000000300ff00ff00e64601000200010002000200ff000200b0"
    "c7ff007140cb4d0200ff00010001000000ff000000e1ee0000010000000300ff00ff00010000000000ff00ff00ff0030"
    "ca318653f10200010001000100000001000300ff00588d030078a84c98ff000300ff000100030000000200ff0085bd00"
    "00020002000100ff0002d90300010000005993ff00ff000200ff00ff00020000000100ff0001000200ff00aa2bbcbb00"
    "00010000000300248582830100a579733e030000000100dc49ff00000002000200ff00ff000000010000000200048203"
    "0002000100ff0001000300000003002242eda901000000ebe30100020002000300f6feff"
)


# 0xF9 1, then mode 3 (stored as 2: sense pulses), 2 electrodes and 0xF6 64511 (a 15 µs alarm): every scan
# of the two channels (32.55 µs in the model) overruns and the next starts as it returns.
SENSE_RUN = ((2360.073, "f901"), (12448.198, "fb03fc02"), (12448.198, "f6fffb"))


def _v2_side(writes: tuple[tuple[float, str], ...], end_us: float) -> ModelSideV2:
    side = ModelSideV2(timer_origin_us=1010.25, hv513_count=4)
    for at_us, data in writes:
        side.write(bytes.fromhex(data), at_us)
    side.advance_to(end_us)
    return side


def test_v2_pulses_are_numbered_by_slot_across_a_run_of_back_to_back_scans() -> None:
    """The v2 model numbers a pulse as the v1.2 model does: by its slot within its run of back-to-back scans
    (one slot a channel; each costs the firmware two DAAD exchanges of chip-select writes the model does not
    count), so the start tolerance grows along the run as the firmware falls behind (pulse-numbering)."""
    side = _v2_side(SENSE_RUN, 14000.0)
    run = [s for s in side.emu.scans if s.electrode_num == 2]
    assert len(run) > 20
    assert all(b.start_ns == a.end_ns for a, b in zip(run, run[1:]))
    pulses = [p for p in side.observe(14000.0).pulses if p[0] * 1000 >= run[0].start_ns]
    assert [p[5] for p in pulses] == list(range(len(pulses)))  # 2 slots a scan, counted from the run's start
    assert [p[3] for p in pulses[:4]] == [(0,), (1,), (0,), (1,)]


def test_v2_a_channel_of_zero_height_and_one_past_the_chain_keep_their_slots() -> None:
    """255 electrodes on 32 outputs at a 15 µs alarm (0xF6 65534): channel 0 has height 0 and channels 32 to
    254 fall off the chain, so a scan delivers far fewer pulses than it has slots; the next scan's first
    pulse (channel 1) is numbered 255 + 1, its slot in the run, not its rank among the pulses delivered."""
    pattern = "0000" + "0300" * 254
    side = _v2_side(((2000.5, "fcff"), (2010.5, "fe" + pattern + "f6feff")), 12000.0)
    pulses = side.observe(12000.0).pulses
    scans = [s for s in side.emu.scans if s.electrode_num == 255]
    assert len(scans) >= 2 and scans[1].start_ns == scans[0].end_ns
    second = [p for p in pulses if p[0] * 1000 >= scans[1].start_ns]
    assert second[0][3] == (1,) and second[0][5] == 255 + 1


def test_v2_biphasic_scans_number_two_slots_a_channel() -> None:
    """In mode 1 ``biPhasicPulse`` makes two pulses a channel (four DAAD exchanges): each phase has a slot."""
    side = _v2_side(((2000.5, "fb01fc02fe03000300f6feff"),), 4000.0)
    scans = [s for s in side.emu.scans if s.electrode_num == 2]
    pulses = [p for p in side.observe(4000.0).pulses if p[0] * 1000 >= scans[0].start_ns]
    assert scans[1].start_ns == scans[0].end_ns
    slots = [(p[3][0], p[5]) for p in pulses[:6]]
    assert slots == [(0, 0), (0, 1), (1, 2), (1, 3), (0, 4), (0, 5)]  # (channel, slot)


def test_upstream_v2_a_long_run_of_sense_scans_falls_behind_within_its_allowance() -> None:
    """The run above against the firmware: each scan is 0.4 µs longer there (two channels of chip-select
    writes), so by 68448.198 µs it has delivered 42 pulses fewer, each within its slot's allowance (the
    minimal reproduction of the 'pulses count' divergence before the model numbered by slot)."""
    tree = _upstream("TACTDEFORM_HW_UPSTREAM_V2")
    writes = tuple((t, bytes.fromhex(h)) for t, h in SENSE_RUN)
    assert Differ(tree, "v2").first_divergence(Stream(writes, 68448.198, "sense run")) is None


def test_upstream_v2_channels_past_the_chain_drift_within_the_run_allowance() -> None:
    """255 electrodes on 32 outputs at a 15 µs alarm: the firmware's second scan starts 51 µs after the
    model's (255 channels of 0.2 µs of chip-select writes) though only 28 pulses were delivered before it
    (the minimal reproduction of the 'pulses start' divergence before the model numbered by slot)."""
    tree = _upstream("TACTDEFORM_HW_UPSTREAM_V2")
    writes = ((2000.5, bytes.fromhex(START_RUN_HEX)),)
    assert Differ(tree, "v2").first_divergence(Stream(writes, 548000.5, "past the chain")) is None


def test_upstream_v1_2_channels_past_the_chain_drift_within_the_run_allowance() -> None:
    """The stream above against the firmware: its second scan starts 103.2 µs after the model's (172
    channels of 0.6 µs of chip-select writes), within the run's allowance (equivalence pulse-numbering)."""
    tree = _upstream("TACTDEFORM_HW_UPSTREAM_V1_2")
    stream = Stream(
        ((2360.073, bytes.fromhex("f901")), (12448.198, bytes.fromhex("f7fefcac"))), 68469.0, "past the chain"
    )
    assert Differ(tree, "v1.2").first_divergence(stream) is None


def test_a_pulse_deep_in_a_run_is_required_of_the_other_side_only_past_its_drift_allowance() -> None:
    """A pulse numbered 2000 in its run may start 1400.7 µs later on the other side: 600 µs
    after its end its counterpart is not yet missing; numbered 0 (allowance under the 500 µs margin), it
    is (equivalence pulse-numbering)."""
    model = Comparison(exact=False, spec=None, pulse_tolerance_us=0.7)

    def pulse(index: int) -> Observation:
        return Observation({}, b"", [(1000.0, 1006.6, 4, (1,), 1, index)])

    none = Observation({}, b"", [])
    assert compare(none, pulse(2000), model, False, upto_us=1606.6) is None
    found = compare(none, pulse(0), model, False, upto_us=1606.6)
    assert found is not None and found[1] == "pulse 0 (count)"
    past = 1006.6 + 0.7 * 2002 + 0.01
    assert compare(none, pulse(2000), model, False, upto_us=past) is not None


def test_upstream_v1_2_a_long_run_of_overrunning_scans_falls_behind_within_its_allowance() -> None:
    """0xF6 62810 (a 15 µs alarm) and 2 channels of sense pulses: 50 ms of back-to-back scans, each 1.2 µs
    longer on the firmware (its chip-select writes): by 54020.5 µs the firmware has made 54 pulses fewer,
    all within their drift allowance (equivalence pulse-numbering)."""
    tree = _upstream("TACTDEFORM_HW_UPSTREAM_V1_2")
    writes = ((2000.5, bytes.fromhex("f901f65af5fbfe0f")), (2020.5, bytes.fromhex("fc02")))
    assert Differ(tree, "v1.2").first_divergence(Stream(writes, 54020.5, "long run")) is None


def test_upstream_v2_a_scan_inside_a_call_that_skips_an_unknown_byte_delays_both_loops() -> None:
    """0xF6 65534, four unknown bytes, 0xFC 2, 0xFF, 0x00: the scan inside the call that skips 0x39 delays
    the loop by its 2.15 µs on both sides, so the overrunning scans starve it with 0x00 unread on both (the
    model-only twin is in test_models_follow_firmware.py; the 'state rx_unread' minimal reproduction)."""
    tree = _upstream("TACTDEFORM_HW_UPSTREAM_V2")
    writes = tuple((2000.5, bytes.fromhex(h)) for h in ("f6feff", "d8459539", "fc02ff00"))
    assert Differ(tree, "v2").first_divergence(Stream(writes, 5013.0, "unknown bytes")) is None


def test_upstream_v2_a_scan_due_inside_a_frequency_call_runs_on_both_sides() -> None:
    """The alarm inside the second 0xF6's u16 read: both sides scan before setPeriodUs and store 0xFC 141 and
    0xF9 1 before the loop starves (the model-only twin is in test_models_follow_firmware.py)."""
    tree = _upstream("TACTDEFORM_HW_UPSTREAM_V2")
    writes = ((3303.434, bytes.fromhex("f6fffd01f6b291fc8d")), (3303.434, bytes.fromhex("f901")))
    assert Differ(tree, "v2").first_divergence(Stream(writes, 6037.0, "alarm in 0xF6")) is None


def test_upstream_v2_a_scan_inside_an_idle_poll_delays_its_sleep_on_both_sides() -> None:
    """The alarm of 49 001 µs inside the idle poll of the 49 000 µs tick: both sides sleep from the scan's end
    to the 51 000 µs tick, so neither has stored 0xF9 1 at 51 000 µs (a single checkpoint: the difference
    would last 1.7 ms, less than call-resolution's window; the model-only twin is in
    test_models_follow_firmware.py)."""
    tree = _upstream("TACTDEFORM_HW_UPSTREAM_V2")
    writes = ((2000.5, bytes.fromhex("fc08fa8200f64b02")), (49100.0, bytes.fromhex("f901")))
    stream = Stream(writes, 53000.0, "alarm in an idle poll")
    assert Differ(tree, "v2").first_divergence(stream, at_us=51000.0) is None


def test_upstream_v2_a_starved_loop_s_queue_overflows_on_both_sides() -> None:
    """Scans back to back (0xFC 32, 0xF6 28466), then 1176 bytes at once: the firmware's serial driver and
    the model both store them as they come and drop the 155 past the 1024-byte buffer (the model-only twin
    is in test_models_follow_firmware.py)."""
    tree = _upstream("TACTDEFORM_HW_UPSTREAM_V2")
    writes = ((2000.5, "fc20"), (4904.391, "f6326ff60100"), (9425.323, "00" * 1176))
    stream = Stream(tuple((t, bytes.fromhex(h)) for t, h in writes), 9425.5, "overflow")
    assert Differ(tree, "v2").first_divergence(stream) is None


def test_upstream_v2_a_scan_after_0xf5_and_a_new_frequency_starts_with_the_firmware_s() -> None:
    """Four payload commands, 0xF5, then 0xF6 65535: the scans start together, 0xF5's call counting
    hv513Init's pin writes after the detection (the model-only twins are in
    test_models_follow_firmware.py)."""
    tree = _upstream("TACTDEFORM_HW_UPSTREAM_V2")
    writes = ((2000.5, "f7d6fb01"), (2020.5, "fc04fe00008f910000cd8ef5"), (2580.973, "fc04f6fffff7"))
    stream = Stream(tuple((t, bytes.fromhex(h)) for t, h in writes), 64630.973, "after 0xF5")
    assert Differ(tree, "v2").first_divergence(stream) is None


def test_upstream_v2_a_run_of_0xf5_calls_keeps_the_scans_with_the_firmware_s() -> None:
    """Eight 0xF5 in a row, each call ending after hv513Init's 69 pin writes (3.45 µs): the next scan starts
    with the firmware's, not 27.6 µs before it (the 'pulses start' minimal reproduction left once the
    pulses were numbered by slot)."""
    tree = _upstream("TACTDEFORM_HW_UPSTREAM_V2")
    writes = ((2000.5, bytes.fromhex("fc04fe0100010001000100" + "f5" * 8)),)
    assert Differ(tree, "v2").first_divergence(Stream(writes, 30000.0, "0xF5 run")) is None


def test_upstream_v2_an_alarm_before_0xf5_disables_the_timer_runs_on_both_sides() -> None:
    """The alarm of 8017 µs falls inside the read of an 0xF5 byte, before its timerAlarmDisable: both sides
    scan there and re-enable the alarm 2.15 µs later, so the starving scans of 244 channels after 0xFC 244
    find the final 0xFE read on both (the 'state rx_unread' minimal reproduction left after the main-loop
    fix; the model-only twin is in test_models_follow_firmware.py)."""
    tree = _upstream("TACTDEFORM_HW_UPSTREAM_V2")
    writes = ((4369.366, "fefef6"), (4369.366, "ffff"), (7959.381, "f9f60000f5"), (9385.218, "52fc"))
    writes += ((9395.218, "f4fe"),)
    stream = Stream(tuple((t, bytes.fromhex(h)) for t, h in writes), 12012.0, "alarm before 0xF5's disable")
    assert Differ(tree, "v2").first_divergence(stream) is None


STARVED_AT_A_READ_POINT = {
    "before the command byte": (((11286.611, "f6fefffc010065f8"),), 75265.01),
    "inside a pattern copy": (((2000.5, "f6ffff"), (4000.5, "fc04feff0fff0fff0fff0f")), 7000.0),
    "in setPeriodUs": (((2000.5, "f6fff4"), (18040.402, "fc01f60100")), 21012.0),
    "after the last read": (((2010.5, "f6fff8"), (3115.983, "fc08fa09f8")), 127175.983),
}


@pytest.mark.parametrize("case", list(STARVED_AT_A_READ_POINT))
def test_upstream_v2_a_starved_call_stops_at_the_firmware_s_read_point(case: str) -> None:
    """An overrunning scan takes the processor at runEtactileKit's first call into the Arduino core at or
    after its alarm and never gives it back: the firmware leaves 0xF8 unread, a pattern torn after two
    elements, 0xF6's period without its alarm, 0xFA's width stored; the model leaves the same (the
    model-only twins are in test_models_follow_firmware.py)."""
    tree = _upstream("TACTDEFORM_HW_UPSTREAM_V2")
    writes, end_us = STARVED_AT_A_READ_POINT[case]
    stream = Stream(tuple((t, bytes.fromhex(h)) for t, h in writes), end_us, case)
    assert Differ(tree, "v2").first_divergence(stream) is None


UPSTREAM_V1_2_F5_CASES = {
    # sense height 4, widths 65535/65534, 221 electrodes, sense width 255, discharge 61, 0xF5 0xF5: the second
    # 0xF5's stackSense() is interrupted by a 69.9 ms scan, its byte already read
    "0xF5 read before its detection": (
        ((2000.5, "f901fafffffafefffcddf8"), (2970.199, "fff73d"), (7509.598, "f5f5")),
        12010.0,
    ),
    # sense height 552, sense width 2, 32 electrodes, 0xF5 0xF5: the first alarm pre-empts the second 0xF5's
    # hv513Init() with CLK high, and that scan lights no output
    "alarm inside hv513Init with CLK high": (((4817.812, "f98af800fc20f802"), (4867.812, "f5f5")), 32000.0),
}


@pytest.mark.parametrize("case", list(UPSTREAM_V1_2_F5_CASES))
def test_upstream_v1_2_an_interrupted_0xf5_matches_the_model(case: str) -> None:
    """runEtactileKit() reads the 0xF5 before stackSense(), and an alarm inside hv513Init() starts its scan
    from the chain hv513Init() left (the model-only twins are in test_models_follow_firmware.py)."""
    tree = _upstream("TACTDEFORM_HW_UPSTREAM_V1_2")
    writes, end_us = UPSTREAM_V1_2_F5_CASES[case]
    stream = Stream(tuple((t, bytes.fromhex(h)) for t, h in writes), end_us, case)
    assert Differ(tree, "v1.2").first_divergence(stream) is None


UPSTREAM_V1_2_MAIN_LOOP_CASES = {
    # 0xF6 11402 (an 87 us period), then 4 electrodes and discharge 22 (random seed 696, minimal): each scan
    # of the 4 channels is 88.45 us with the chip-select writes costed as the shim costs them, so the scans
    # run back to back and the loop never reads 0xF7 (under the model's default reading, 86.05 us: it did)
    "scans overrun by their chip-select writes": (
        ((2000.5, "f68a2c"), (2000.5, "fd"), (2000.5, "02fc04f716")),
        8489.0,
    ),
    # 125 x 0xF7 254 fill the receive queue to 250; 8 bytes arrive at 3002.5 us, while the call at the 3000 us
    # tick reads 0xF7 (its 254 not yet): one is lost on both sides
    "a byte arriving during a call": (((2000.5, "f7fe" * 125), (3002.5, "00" * 8)), 6000.0),
    # the same while calls skip unknown bytes: the call at 3012 us reads its byte from 3014 us, so the last
    # two bytes (04 00) are lost and 0xFC waits for its payload (one lost: 0xFC 4 would be stored)
    "a byte arriving during a call that skips a byte": (
        ((2990.5, "00" * 6), (3002.5, "00" * 248), (3012.5, "0000000000fc0400")),
        5000.0,
    ),
    # the 100 000-stream run's first `state rx_unread` (random seed 422, minimal): 12 bytes arrive at
    # 6002.839 us while the call at the 6000 us tick has read 0xFA but not its u16
    "a byte arriving during a call, seed 422": (
        (
            (
                2000.5,
                "f60200f5f7fefa91c7f801"
                + "f60200f5f7fefa91fe0200f5f7fefa91c7f801"
                + "f60200f5f7fefa91c7f801" * 20
                + "f602",
            ),
            (6002.839, "8f28f4fb025629110818a1cb"),
        ),
        8100.0,
    ),
    # the 100 000-stream run's first `state timer_alarm_ticks` (random seed 18387, minimal): 0xF6 1's u16 read
    # runs across the alarm, whose scan of 254 channels overruns the old period: the period is never stored
    # and setPeriodUs() never runs
    "a frequency whose scan overruns": (
        ((4876.87, "71"), (6206.937, "f7"), (6206.937, "fefc"), (23379.394, "fe"), (30450.161, "fff60100")),
        120000.0,
    ),
    # the same with 32 channels: the scan returns in time and setPeriodUs() writes the 1 s alarm after it
    "a frequency whose scan returns in time": (
        ((4876.87, "71"), (6206.937, "f7"), (6206.937, "fefc"), (23379.394, "20"), (30450.161, "fff60100")),
        1040000.0,
    ),
    # 0xF6 32158 (a 31 us alarm), 1 electrode, then 0xF5 (random seed 1484, minimal): the
    # scans pre-empt the stack detection's analogRead calls at their alarms, and stay on the timer's grid
    "0xF5's analogRead pre-empted at the alarm": (
        ((5127.734, "f920"), (5137.734, "fc01f69e7d"), (6609.525, "f5")),
        11100.0,
    ),
    # 0xF6 12721 (a 78 us alarm), 2 biphasic channels (74.35 us scans), 0xF5 0xF5 (random seed 13864,
    # minimal): the detection runs in the 3.65 us the scans leave; both answer the first at 38 500.05 us
    "0xF5 between scans that leave the loop 3.65 us": (
        ((13293.406, "f6b131fc02fe0202"), (13333.406, "f5"), (13333.406, "f5")),
        40576.0,
    ),
    # sense width 255, discharge 245, 4 electrodes (2 ms scans), 0xF5 arriving during the scan of 11 010.25 us
    # (random seed 17450, minimal): the idle loop's poll of the 12 000 us tick runs as the scan returns
    "the idle loop's poll after a scan": (
        ((2010.5, "f8fff7f5fc04"), (13010.214, "f5"), (13247.777, "4f")),
        15022.0,
    ),
    # the 100 000-stream run's first `pulses start` (random seed 619, minimal): 4 electrodes, sense width 255,
    # discharge 254 (2 ms scans), one command a tick; at the 21 000 us tick 0xF9 1's last Serial.available()
    # check runs across the alarm at 21 010.25 us, so vTaskDelay(1) is called after the scan and the next
    # command is read at 24 000 us, not as the scan returns: the scan at 31 010.25 us has the old sense
    # height 0 on both sides (the model had had the next one, 4)
    "alarm inside the last check, seed 619": (
        (
            (4127.656, "fc8df7fe"),
            (4388.984, "fc01f60000f802"),
            (4438.984, "fafffff5f8fffd24"),
            (4448.984, "f900fb0100fc04f902f901f900fb00fc04f901f900fb0100fc04f902f901fb0100fc04f900f901"),
        ),
        45000.0,
    ),
    # 0xF6 21027 (a 47 us alarm), 2 electrodes (46.95 us scans), discharge 2, then 0xF9 2 (random seed 29034,
    # minimal): the loop runs 50 ns between scans, so 0xFD's last check spans 40 of them and vTaskDelay(1)
    # sleeps to the 12 000 us tick; the first pulse of height 2 is at 18 618.7 us on both sides
    "a last check in the slivers between scans, seed 29034": (
        ((2000.5, "f62352fc02fd02"), (2010.5, "f902")),
        19000.0,
    ),
    # the same slivers while the loop is idle: each poll (Serial.available(), then vTaskDelay(1)) spans
    # scans, and a command written between ticks is read at the poll after it on both sides
    "idle polls in the slivers between scans": (((2000.5, "f62352fc02"), (21500.5, "f902")), 30000.0),
    # random seed 31686, minimal: 0xF6's u16 waits 2 s for its second byte; the spin's checks run in the
    # main loop's time between scans, and the one for two bytes after the arrival finds it on both sides
    "a spin on a half u16, seed 31686": (
        ((4136.06, "fc01f9"), (5173.543, "fef6ff"), (2073447.451, "ff")),
        2075000.0,
    ),
    # random seed 74129, minimal: an unknown byte waits for the rest of the check a 5 ms scan pre-empted
    # and the tick after it, on both sides
    "an unknown byte after a pre-empted check, seed 74129": (
        (
            (3249.849, "fdfff9c1"),
            (3299.849, "fdfffc1cf702fafffffc20"),
            (3299.849, "e6f8931e"),
            (10801.614, "f6fff8"),
        ),
        18000.0,
    ),
    # random seed 20543, minimal: the poll right after 0xF5's reply is pre-empted by a 7.2 ms scan, so the
    # bytes that arrived during it are read from the 19 000 us tick (the model had read them as it returned)
    "a poll the alarm pre-empts, seed 20543": (
        (
            (2000.5, "f9fffc20f5f8d6fa0000"),
            (2546.995, "fa0100"),
            (2546.995, "fafffffff5"),
            (12999.82, "fdfef8fffb96fffa"),
            (21879.248, "00"),
            (21879.248, "ffff"),
        ),
        23000.0,
    ),
}


@pytest.mark.parametrize("case", list(UPSTREAM_V1_2_MAIN_LOOP_CASES))
def test_upstream_v1_2_main_loop_matches_the_model(case: str) -> None:
    """runEtactileKit()'s calls around a scan, the scans' own length and the receive queue while a call
    reads, on the firmware and in the model (the model-only twins are in test_models_follow_firmware.py)."""
    tree = _upstream("TACTDEFORM_HW_UPSTREAM_V1_2")
    writes, end_us = UPSTREAM_V1_2_MAIN_LOOP_CASES[case]
    stream = Stream(tuple((t, bytes.fromhex(h)) for t, h in writes), end_us, case)
    assert Differ(tree, "v1.2").first_divergence(stream) is None


def test_upstream_v2_an_alarm_in_a_call_s_last_read_scans_the_registers_from_before_it() -> None:
    """0xFC 4 and 0xFC 0 back to back at a 15 µs alarm in mode 2: the alarm inside the second's last read is
    taken inside it, before the count 0 is stored, on both sides, so both run the scan of four channels
    that starves the loop (random seed 10111, on which the model used to loop; the model-only twin is in
    test_models_follow_firmware.py)."""
    tree = _upstream("TACTDEFORM_HW_UPSTREAM_V2")
    writes = tuple(
        (t, bytes.fromhex(h))
        for t, h in (
            (4881.184, "f4f5f60100fd00fb3f"),
            (12153.317, "f6fefffb02f8fefbccf4"),
            (12163.317, "91de64b3b1a8c39978e8"),
            (12163.317, "f5f762fdfefd01"),
            (12173.317, "f4fbfffc04fc00f4"),
        )
    )
    assert Differ(tree, "v2").first_divergence(Stream(writes, 15000.0, "count lowered")) is None


def test_upstream_v2_an_ignored_rate_calls_no_set_period() -> None:
    """0xF6 0's call ends on the alarm: both take that scan as the loop's own, after the call (random seed
    3392; the model-only twin is in test_models_follow_firmware.py)."""
    tree = _upstream("TACTDEFORM_HW_UPSTREAM_V2")
    writes = ((4823.451, "fefef6fefff8b2"), (5853.361, "f600"), (5853.361, "00fb00fd01"))
    stream = Stream(tuple((t, bytes.fromhex(h)) for t, h in writes), 8000.0, "ignored rate")
    assert Differ(tree, "v2").first_divergence(stream) is None


@pytest.mark.parametrize(
    "writes",
    [
        # random seed 87056, minimal: the payload of 0xF6 arrives as the call reads its command byte
        ((4992.748, "fc01fdfffeff00fd01fd01"), (4992.748, "f6"), (5032.748, "88d0")),
        # random seed 41964, minimal: the same for 0xF6 0, ignored, before 255 electrodes whose scans then
        # starve the loop at a 15.3 us period before 0xF6 1 is stored (the model had stored it)
        (
            (3928.188, "67ae9d117d8ddd81f05628d5"),
            (3939.568, "f6feff"),
            (12972.299, "f802f902f6"),
            (13012.299, "0000fcfff60100"),
        ),
    ],
    ids=["seed 87056", "seed 41964"],
)
def test_upstream_v2_a_payload_arriving_while_its_command_byte_is_read_is_read_by_the_same_call(
    writes: tuple[tuple[float, str], ...],
) -> None:
    """The call's second isDataAvailable() counts the payload that arrived while it read the command byte,
    on the firmware and in the model (the model-only twin is in test_models_follow_firmware.py)."""
    tree = _upstream("TACTDEFORM_HW_UPSTREAM_V2")
    stream = Stream(tuple((t, bytes.fromhex(h)) for t, h in writes), 60000.0, "payload during its call")
    assert Differ(tree, "v2").first_divergence(stream) is None


def test_upstream_v2_a_call_pre_empted_by_a_long_scan_resolves_after_the_scan() -> None:
    """0xFC 255, then 0xFB 0xFD at the tick before the alarm: the scan of 255 channels (3.5 ms) takes the
    processor before the firmware reads 0xFB's payload, so the call stores mode 2 only after the scan; the
    model shows it from the call's start.  The call-resolution window runs in main-loop time and waits for
    that scan, which the firmware enters at its alarm (11010.25 µs), inside the call's isDataAvailable (the
    scans agree exactly; random seed 51369's minimal reproduction)."""
    tree = _upstream("TACTDEFORM_HW_UPSTREAM_V2")
    writes = ((10101.773, "fcff"), (10111.773, "fbfd"), (12506.575, "00"))
    stream = Stream(tuple((t, bytes.fromhex(h)) for t, h in writes), 13007.0, "pre-empted call")
    differ = Differ(tree, "v2")
    assert differ.first_divergence(stream) is None
    assert differ.call_resolved == 1
    left, right = differ.sides()
    try:
        for t, h in writes[:2]:
            left.write(bytes.fromhex(h), t)
            right.write(bytes.fromhex(h), t)
        for side in (left, right):
            side.advance_to(12506.0)
        assert (left.observe(12506.0).state["stim_mode"], right.observe(12506.0).state["stim_mode"]) == (0, 2)
        assert isinstance(left, HostSide) and left.scanning_us(11000.0, 12506.0) == (12506.0 - 11010.25, 1)
    finally:
        left.close()
        right.close()


@pytest.mark.parametrize(
    "writes",
    [
        ((2000.5, "f801fb01"), (3002.5, "f4"), (3004.0, "f4"), (3008.5, "f4"), (3011.5, "f4")),
        ((2000.5, "f801" * 512), (3003.0, "f801"), (3100.0, "f4")),
    ],
    ids=["read-one-at-a-time", "arrival-mid-call"],
)
def test_upstream_v2_a_call_s_unread_bytes_stay_in_the_queue(writes: tuple[tuple[float, str], ...]) -> None:
    """runEtactileKit() reads a call's bytes one at a time: the queue keeps each until its read, and an
    arrival meanwhile finds them there (the model-only twins are in test_models_follow_firmware.py)."""
    tree = _upstream("TACTDEFORM_HW_UPSTREAM_V2")
    stream = Stream(tuple((t, bytes.fromhex(h)) for t, h in writes), 3200.0, "unread")
    differ = Differ(tree, "v2")
    assert differ.first_divergence(stream) is None
    left, right = differ.sides()
    try:
        for t, h in writes:
            seen = []
            for side in (left, right):
                side.advance_to(t)
                st = side.observe(t).state
                seen.append((st["rx_unread"], st["rx_dropped"]))
                side.write(bytes.fromhex(h), t)
            assert seen[0] == seen[1], t
    finally:
        left.close()
        right.close()


def test_upstream_v2_a_later_alarm_inside_a_call_s_last_read_scans_what_was_stored_before_it() -> None:
    """The 0xFC 0 call pre-empted by one scan, then the next alarm inside its last read: the firmware and
    the model both run that scan on the one channel stored before it (the model-only twin is in
    test_models_follow_firmware.py; the 'pulses count' minimal reproduction of random seed 5426)."""
    tree = _upstream("TACTDEFORM_HW_UPSTREAM_V2")
    writes = ((2761.842, "fc01"), (3049.205, "f9fffb02f6eaaafc00"))
    stream = Stream(tuple((t, bytes.fromhex(h)) for t, h in writes), 6069.0, "later alarm in last read")
    assert Differ(tree, "v2").first_divergence(stream) is None


def test_upstream_v2_a_pattern_element_whose_read_the_alarm_falls_in_is_stored_after_the_scan() -> None:
    """The scan that interrupts a pattern's copy inside element 2's read runs elements 0 and 1 new on the
    firmware and in the model (the model-only twin is in test_models_follow_firmware.py; the 'pulses
    outputs' minimal reproduction of random seed 8958)."""
    tree = _upstream("TACTDEFORM_HW_UPSTREAM_V2")
    writes = (
        (2242.218, "fc20"),
        (
            10172.698,
            "fe03000100fcdec4180000010001000100ff00ff00cb8c020003004dad030001000000c5a103000200010002000100ff00"
            "ffd6ff00030000000100327b01000100",
        ),
    )
    stream = Stream(tuple((t, bytes.fromhex(h)) for t, h in writes), 120172.698, "torn at an element")
    assert Differ(tree, "v2").first_divergence(stream) is None
