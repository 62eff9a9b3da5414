"""What the command line says against what it does: a refusal that says "nothing was sent" sent nothing, an
output error names its option and file, a report counts what ran."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import serial

from tactdeform_hw.cli import main
from tactdeform_hw.emulator.serving.urlhandler.protocol_etactile import shared_emulator

from .cli_helpers import run

pytestmark = pytest.mark.usefixtures("fresh_emulators")


def _board(name: str, firmware: str = "v1.2") -> object:
    """A named untimed board, made before the command opens it, so its received bytes can be counted."""
    port = serial.serial_for_url(f"etactile://{name}?timed=0&firmware={firmware}")
    port.close()
    return shared_emulator(name)


@pytest.mark.parametrize(
    ("firmware", "pattern"),
    [
        ("auto", "all:2"),
        ("v1.2", "all:2"),
        ("v2", "all:2"),
        # on v2 every channel is pulsed: two active electrodes overrun there, not on v1.2
        ("auto", ",".join(["1"] + ["0"] * 30 + ["2"])),
    ],
)
def test_a_scan_overrun_refusal_sends_no_byte(firmware, pattern, tmp_path, capsys) -> None:
    board_fw = "v2" if firmware == "v2" else "v1.2"
    board = _board("overrun", board_fw)
    audit = tmp_path / "audit.jsonl"
    argv = ["send", "--pattern", pattern, "--current-ua", "1000", "--pulse-width-us", "300"]
    argv += ["--firmware", firmware, "--device", f"etactile://overrun?timed=0&firmware={board_fw}"]
    code, _, err = run([*argv, "--audit-log", str(audit)], capsys)
    assert code == 1
    assert "scan takes about" in err and err.rstrip().endswith("nothing was sent"), err
    assert board.received_bytes == 0
    assert not audit.exists()
    if "," in pattern:
        assert "on firmware v2, which --firmware auto may find" in err and "--firmware v1.2" in err


def test_a_frame_that_fits_is_still_sent(tmp_path, capsys) -> None:
    board = _board("fits")
    pattern = ",".join(["1"] + ["0"] * 30 + ["2"])
    argv = ["send", "--pattern", pattern, "--current-ua", "1000", "--pulse-width-us", "300"]
    code, out, err = run([*argv, "--firmware", "v1.2", "--device", "etactile://fits?timed=0"], capsys)
    assert code == 0, err
    assert board.received_bytes > 0 and "sent 2 active electrode(s)" in out


@pytest.fixture
def frames_file(tmp_path: Path) -> Path:
    path = tmp_path / "frames.jsonl"
    assert (
        main(["render", "--scene", "cube", "--trajectory", "approach-face", "--quiet", "--frames", str(path)])
        == 0
    )
    return path


@pytest.mark.skipif(not Path("/dev/full").exists(), reason="needs /dev/full (a file whose writes fail)")
@pytest.mark.parametrize(
    ("argv", "flag"),
    [
        (["render", "--scene", "cube", "--trajectory", "approach-face", "--quiet", "--frames"], "--frames"),
        (
            [
                "render",
                "--scene",
                "cube",
                "--trajectory",
                "approach-face",
                "--quiet",
                "--strip",
                "{tmp}/s.png",
                "--frames",
            ],
            "--frames",
        ),
        (["export", "{frames}", "-o"], "--out"),
        (["timing", "--vcd"], "--vcd"),
        (["timing", "--png"], "--png"),
        (["send", "--pattern", "all:1", "--audit-log"], "--audit-log"),
    ],
)
def test_a_write_error_names_the_option_and_the_file(argv, flag, frames_file, tmp_path, capsys) -> None:
    if "--png" in argv or "--strip" in argv:
        pytest.importorskip("matplotlib")
    if "--vcd" in argv:
        pytest.importorskip("vcd")
    argv = [a.format(tmp=tmp_path, frames=frames_file) for a in argv]
    # a file of the output's own suffix whose writes fail: a link to /dev/full
    full = tmp_path / f"out{ {'--png': '.png', '--vcd': '.vcd', '--out': '.json'}.get(flag, '.jsonl') }"
    full.symlink_to("/dev/full")
    code, _, err = run([*argv, str(full)], capsys)
    assert code == 1
    line = err.strip().splitlines()[-1]
    assert f"{flag} {full}: cannot be written (No space left on device)" in line, err


@pytest.mark.parametrize(
    ("argv", "flag", "written"),
    [
        (["timing", "--png", "{tmp}/out.jpg"], "--png", "PNG"),
        (
            ["render", "--scene", "cube", "--trajectory", "approach-face", "--strip", "{tmp}/s.svg"],
            "--strip",
            "PNG",
        ),
        (
            ["render", "--scene", "cube", "--trajectory", "approach-face", "--gif", "{tmp}/a.png"],
            "--gif",
            "GIF",
        ),
    ],
)
def test_a_picture_whose_suffix_names_another_format_is_refused(
    argv, flag, written, tmp_path, capsys
) -> None:
    argv = [a.format(tmp=tmp_path) for a in argv]
    code, _, err = run(argv, capsys)
    assert code == 1
    assert f"{flag} {argv[-1]}: writes {written}, but the suffix" in err, err
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize(
    ("firmware", "ua", "byte"),
    [("v2", 100, 10), ("v2", 2550, 255), ("v1.2", 10200, 255), ("v1.2", 40, 1), ("v1.2", 0, 0)],
)
def test_timing_takes_the_sense_current_each_version_stores(firmware, ua, byte) -> None:
    from tactdeform_hw.cli import build_parser
    from tactdeform_hw.cli.options import finish

    args = build_parser().parse_args(["timing", "--firmware", firmware, "--sense-current-ua", str(ua)])
    finish(args)
    assert args.sense_height == byte


@pytest.mark.parametrize(
    ("firmware", "ua", "limit"),
    [
        ("v2", 2560, "a multiple of 10 µA from 0 to 2550 µA (firmware v2 stores the byte sent, unshifted)"),
        ("v1.2", 100, "a multiple of 40 µA from 0 to 10200 µA (firmware v1.2 stores the byte sent << 2)"),
        ("v1.2", 10240, "a multiple of 40 µA from 0 to 10200 µA (firmware v1.2 stores the byte sent << 2)"),
    ],
)
def test_timing_refuses_a_sense_current_with_the_versions_rule(firmware, ua, limit, capsys) -> None:
    code, _, err = run(["timing", "--firmware", firmware, "--sense-current-ua", str(ua)], capsys)
    assert code == 1
    assert f"--sense-current-ua {ua} is out of range: {limit}" in err, err


@pytest.mark.parametrize("suffix", [".csv", ".json"])
def test_timing_events_have_one_format_on_both_versions(suffix, tmp_path, capsys) -> None:
    import csv
    import json

    columns = []
    for firmware in ("v1.2", "v2"):
        path = tmp_path / f"{firmware}{suffix}"
        code, _, err = run(["timing", "--firmware", firmware, "--events", str(path), "--cycles", "1"], capsys)
        assert code == 0, err
        if suffix == ".json":
            rows = json.loads(path.read_text())
            assert rows and all(isinstance(r, dict) for r in rows)
            columns.append(set(rows[0]))
        else:
            columns.append(tuple(next(csv.reader(path.open()))))
    assert columns[0] == columns[1]


CALIBRATION_KEYS = "+" * 20 + " a  - - a\n" + "+" * 12 + " a " + ("+" * 14 + " a ") * 7 + " + a"


def test_calibrate_refuses_to_replace_a_profile_without_force(tmp_path, capsys) -> None:
    keys = tmp_path / "keys.txt"
    keys.write_text(CALIBRATION_KEYS)
    out = tmp_path / "P09.json"
    old = '{"version": 1, "participant": "P09", "ramp_ua_per_frame": 50, "contact_mode": "uniform"}\n'
    out.write_text(old)
    board = _board("calibrate")
    argv = ["calibrate", "--participant", str(out), "--keys", str(keys), "--max-ua", "300"]
    code, _, err = run([*argv, "--device", "etactile://calibrate?timed=0"], capsys)
    assert code == 1
    assert f"--participant {out}: already exists" in err and "--force" in err, err
    assert out.read_text() == old and board.received_bytes == 0
    code, stdout, err = run([*argv, "--device", "etactile://calibrate?timed=0", "--force"], capsys)
    assert code == 0, err
    assert (tmp_path / "P09.json.bak").read_text() == old
    assert out.read_text() != old and f"kept the previous file as {out}.bak" in stdout


def test_study_refuses_an_out_with_an_earlier_report_and_force_clears_it(tmp_path, capsys) -> None:
    out = tmp_path / "r"
    (out / "frames").mkdir(parents=True)
    (out / "frames" / "task1-99-old.jsonl").write_text("{}\n")
    (out / "pictures").mkdir()
    (out / "report.json").write_text("{}\n")
    (out / "notes.txt").write_text("mine\n")
    argv = ["study", "task1", "--trials", "1", "--quiet", "--no-pictures", "--no-timed", "--out", str(out)]
    board = _board("reuse")
    code, _, err = run([*argv, "--device", "etactile://reuse?timed=0"], capsys)
    assert code == 1
    assert f"--out {out}: holds an earlier report (report.json, frames, pictures); give --force" in err, err
    assert board.received_bytes == 0 and (out / "frames" / "task1-99-old.jsonl").exists()
    code, _, err = run([*argv, "--device", "etactile://reuse?timed=0", "--force"], capsys)
    assert code == 0, err
    assert not (out / "frames" / "task1-99-old.jsonl").exists() and not (out / "pictures").exists()
    assert (out / "notes.txt").read_text() == "mine\n"  # not the report's: kept
    assert len(list((out / "frames").iterdir())) == 1


def test_an_interrupted_study_keeps_the_trials_that_ran(tmp_path, monkeypatch, capsys) -> None:
    import json

    from tactdeform_hw.study import runner

    real = runner._run_trial
    calls = []

    def stopped_on_the_third(live, run, *a, **k):
        calls.append(run.trial.id)
        if len(calls) == 3:
            raise KeyboardInterrupt
        return real(live, run, *a, **k)

    monkeypatch.setattr(runner, "_run_trial", stopped_on_the_third)
    out = tmp_path / "r"
    argv = ["study", "task1", "--trials", "1-4", "--quiet", "--no-pictures", "--no-timed", "--out", str(out)]
    code, _, _ = run(argv, capsys)
    assert code == 130
    lines = [json.loads(x) for x in (out / "trials.jsonl").read_text().splitlines()]
    assert [e["id"] for e in lines] == calls[:2]
    assert all((out / e["frames_file"]).stat().st_size > 0 for e in lines)
    report = json.loads((out / "report.json").read_text())
    assert report["complete"] is False and report["trials_run"] == calls[:2]
    assert len(report["trials_not_run"]) == 2 and calls[2] in report["trials_not_run"]
    assert "**INTERRUPTED**" in (out / "summary.md").read_text()


def _pose_csv(path: Path, scale: float) -> Path:
    from tactdeform_hw.render.tracking import Pose, write_pose_csv

    poses = [Pose(i / 72, np.array([0.0, 0.0, 40.0 - i]) * scale) for i in range(40)]
    write_pose_csv(path, poses)
    return path


def test_a_trajectory_in_metres_is_refused_naming_the_file_column_and_value(tmp_path, capsys) -> None:
    metres = _pose_csv(tmp_path / "m.csv", 0.001)
    code, out, err = run(["render", "--scene", "cube", "--trajectory", str(metres), "--quiet"], capsys)
    assert code == 1 and "frames sent" not in out
    assert (
        f"--trajectory {metres}: the positions look like metres" in err and "z_mm = 0.04 in pose row 1" in err
    )
    argv = ["render", "--scene", "cube", "--trajectory", str(metres), "--quiet", "--invalid-rows", "replay"]
    code, out, err = run(argv, capsys)  # the rows replayed as a live tracker gives them: refused alike
    assert code == 1 and "the positions look like metres" in err, err
    millimetres = _pose_csv(tmp_path / "mm.csv", 1.0)
    code, out, err = run(["render", "--scene", "cube", "--trajectory", str(millimetres), "--quiet"], capsys)
    assert code == 0, err


def test_the_extras_hint_installs_the_checkout_it_runs_from(monkeypatch) -> None:
    from tactdeform_hw.errors import MissingDependencyError, install_command

    root = Path(__file__).resolve().parents[1]
    assert (root / "pyproject.toml").is_file()  # the tests run from a checkout
    monkeypatch.chdir(root)
    assert install_command("plot") == "pip install -e '.[plot]'"
    assert "pip install -e '.[plot]'" in str(MissingDependencyError("matplotlib", "plot", "--png x.png"))
    monkeypatch.chdir(root / "tests")
    assert install_command("trace") == f"pip install -e '{root}[trace]'"


def test_decode_reads_standard_input_and_refuses_hex_text_read_as_bytes(
    tmp_path, monkeypatch, capsys
) -> None:
    import io

    monkeypatch.setattr("sys.stdin", io.TextIOWrapper(io.BytesIO(bytes([0xFC, 0x02, 0xFF]))))
    code, out, err = run(["decode", "--file", "-"], capsys)
    assert code == 0, err
    assert "ELECTRODE_NUM electrode_num=2" in out
    text = tmp_path / "hex.txt"
    text.write_text("fc 20 ff\n")
    code, out, err = run(["decode", "--file", str(text)], capsys)
    assert code == 1 and out == ""
    assert f"--file {text}: holds hex text ('fc 20 ff'…), not raw bytes; give --hex-file" in err
    code, out, _ = run(["decode", "--file", str(text), "--hex-file"], capsys)
    assert code == 0 and "electrode_num=32" in out


def test_device_errors_say_what_to_type(capsys) -> None:
    code, _, err = run(["send", "--pattern", "all:1", "--firmware", "v2"], capsys)
    assert code == 1 and "give --device 'etactile://?firmware=v2'" in err, err
    if Path("/dev/null").exists():
        code, _, err = run(["send", "--pattern", "all:1", "--device", "/dev/null"], capsys)
        assert code == 1 and "--device /dev/null opens but is not a serial port" in err, err


def test_replay_log_refuses_a_missing_array_file_without_participant(tmp_path, capsys) -> None:
    log = tmp_path / "a.jsonl"
    assert main(["send", "--pattern", "all:1", "--audit-log", str(log)]) == 0
    capsys.readouterr()
    code, _, err = run(["replay-log", str(log), "--array", str(tmp_path / "missing.json")], capsys)
    assert code == 1 and f"--array {tmp_path / 'missing.json'}" in err, err


def test_emulates_exit_on_ctrl_c_is_the_documented_one(capsys) -> None:
    """``emulate`` is stopped with Ctrl-C (its normal stop, exit 0, as the served-port tests check): the
    top-level help and the guide say so instead of promising 130 for it."""
    from tactdeform_hw.cli import EXIT_STATUS_HELP

    text = " ".join(EXIT_STATUS_HELP.split())
    assert "emulate, a server that runs until it is stopped, ends with 0 on Ctrl-C" in text
    guide = (Path(__file__).resolve().parents[1] / "docs" / "researcher-guide.md").read_text()
    assert "`emulate`, a server that runs until it is stopped, ends with 0 on Ctrl-C" in guide


def test_send_quiet_prints_nothing(capsys) -> None:
    code, out, err = run(["send", "--pattern", "all:1", "--quiet"], capsys)
    assert code == 0 and out == "" and err == ""


def test_one_pulse_height_is_shown_without_an_ellipsis() -> None:
    from tactdeform_hw.cli.delivered import delivered_lines

    rep = {
        "requested_ua": 1000,
        "max_delivered_ua": 1000,
        "lowered": [],
        "refused": [],
        "pulse_heights_ua": [1000],
        "pulse_height_changes": 9,  # on and off nine times: one height all along
        "electrodes": [],
    }
    assert "  pulse heights sent: 1000 µA" in delivered_lines(rep)
    rep["pulse_heights_ua"] = list(range(10, 180, 10))
    assert any(line.endswith(", … µA") for line in delivered_lines(rep))


def test_a_seeded_study_writes_the_same_summary_twice(tmp_path, capsys) -> None:
    texts = []
    for name in ("a", "b"):
        out = tmp_path / name
        argv = [
            "study",
            "task1",
            "--trials",
            "1",
            "--quiet",
            "--no-pictures",
            "--no-timed",
            "--out",
            str(out),
        ]
        assert main(argv) == 0
        texts.append((out / "summary.md").read_text().replace(str(out), "OUT"))
    assert "wall" not in texts[0]
    assert texts[0] == texts[1]


def test_timing_refuses_traces_above_the_limit_before_writing(tmp_path, capsys, monkeypatch) -> None:
    from tactdeform_hw.cli import timing

    monkeypatch.setattr(timing, "TRACE_LIMIT_BYTES", 50_000)  # the same rule as 100 MB, quicker to reach
    events = tmp_path / "e.csv"
    code, _, err = run(["timing", "--events", str(events), "--cycles", "40"], capsys)
    assert code == 1 and "--cycles 40: the traces would take about" in err and "--force" in err, err
    assert not events.exists()
    code, _, err = run(["timing", "--events", str(events), "--cycles", "40", "--force"], capsys)
    assert code == 0, err
    assert events.stat().st_size > 50_000


def test_timing_says_its_progress_on_a_long_trace(tmp_path, capsys) -> None:
    code, _, err = run(["timing", "--events", str(tmp_path / "e.csv"), "--cycles", "1000"], capsys)
    assert code == 0
    assert "timing: tracing 1000 scans, about" in err and "timing: 1000/1000 scans traced" in err
