"""Every subcommand with bad input: one error line naming the flag typed, the documented exit status, and
nothing written to the device when the command refused.

The device is a named in-process emulator (``etactile://NAME``): a command that never opened its port
leaves no emulator under that name, so ``shared_emulator(NAME) is None`` proves no byte was sent.  Each
family of checks has a run that does open the device, so the proof can fail.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from tactdeform_hw.cli import EXIT_STATUS_HELP, build_parser, main
from tactdeform_hw.cli import timing as timing_cli
from tactdeform_hw.emulator.serving.urlhandler.protocol_etactile import shared_emulator
from tactdeform_hw.errors import install_command
from tactdeform_hw.formats import PatternSequence, PatternStep, write_pattern_file

from .cli_helpers import run

ROOT = Path(__file__).resolve().parents[1]
PROFILE = {
    "version": 1,
    "participant": "P01",
    "cap_ua": 2000,
    "regions_ua": [1500, 1400, 1500, 1300, 1200, 1300, 1500, 1400, 1500],
    "pulse_width_us": 200,
    "polarity": "anodic",
    "contact_mode": "orientation",
    "calibrated_on": "2024-05-01",
}


pytestmark = pytest.mark.usefixtures("fresh_emulators")


def usage_error(argv: list[str], capsys: pytest.CaptureFixture[str]) -> str:
    with pytest.raises(SystemExit) as exc:
        main(argv)
    assert exc.value.code == 2
    return capsys.readouterr().err


def error_line(err: str, command: str) -> str:
    """The last line of stderr, which must be the command's one error line (and no traceback)."""
    assert "Traceback" not in err, err
    lines = [ln for ln in err.splitlines() if ln.strip()]
    errors = [ln for ln in lines if ": error: " in ln]
    assert len(errors) == 1, err
    assert lines[-1] == errors[0] and lines[-1].startswith(f"tactdeform-hw {command}: error: "), err
    return lines[-1][len(f"tactdeform-hw {command}: error: ") :]


@pytest.fixture
def pattern_file(tmp_path: Path) -> Path:
    return write_pattern_file(PatternSequence((PatternStep((1,) + (0,) * 31, 5),)), tmp_path / "pattern.json")


@pytest.fixture
def frames_file(tmp_path: Path) -> Path:
    path = tmp_path / "frames.jsonl"
    lines = [
        {"t": 0.0, "state": "idle", "electrodes": [1] + [0] * 31, "sent": True},
        {"t": 0.1, "state": "idle", "electrodes": [0] * 32, "sent": True},
    ]
    path.write_text("".join(json.dumps(x) + "\n" for x in lines))
    return path


@pytest.fixture
def profile(tmp_path: Path) -> Path:
    path = tmp_path / "p01.json"
    path.write_text(json.dumps(PROFILE))
    return path


# --- 1. every output is checked before the device is opened ----------------------------------------------

DEVICE = "etactile://cli-errors"


def _argv(command: str, flag: str, path: str, pattern: Path, frames: Path, tmp: Path) -> list[str]:
    dev = ["--device", DEVICE]
    base = {
        "send": ["send", "--pattern", "all:1", *dev],
        "play": ["play", str(pattern), "--quiet", *dev],
        "export": ["export", str(frames), "-o", str(tmp / "x.json")],
        "render": ["render", "--scene", "cube", "--trajectory", "approach-face", "--quiet", *dev],
        "study": ["study", "task1", "--quick", "--quiet", "--out", str(tmp / "report"), *dev],
        "timing": ["timing"],
        "emulate": ["emulate", "--pty"],
        "calibrate": ["calibrate", "--participant", "P01", "--keys", os.devnull, *dev],
    }[command]
    if flag in base:  # replace the default value of an output the base command already names
        i = base.index(flag)
        return [*base[: i + 1], path, *base[i + 2 :]]
    return [*base, flag, path]


OUTPUT_FLAGS = [
    ("send", "--audit-log"),
    ("play", "--gif"),
    ("play", "--audit-log"),
    ("export", "-o"),
    ("export", "--array-out"),
    ("export", "--gif"),
    ("render", "--frames"),
    ("render", "--gif"),
    ("render", "--audit-log"),
    ("study", "--out"),
    ("study", "--audit-log"),
    ("timing", "--png"),
    ("timing", "--vcd"),
    ("timing", "--events"),
    ("emulate", "--trace"),
    ("calibrate", "--out"),
    ("calibrate", "--audit-log"),
]


@pytest.mark.parametrize(("command", "flag"), OUTPUT_FLAGS)
@pytest.mark.parametrize("bad", ["missing-dir", "is-a-dir"])
def test_outputs_are_checked_before_the_device_is_opened(
    command, flag, bad, tmp_path, pattern_file, frames_file, capsys, monkeypatch
) -> None:
    monkeypatch.chdir(tmp_path)
    suffix = {"--png": ".png", "--gif": ".gif", "--vcd": ".vcd", "--events": ".csv", "--trace": ".csv"}.get(
        flag, ".json"
    )
    # created with its parents: a file in the way
    if bad == "missing-dir" and flag == "--out" and command == "study":
        (tmp_path / "a-file").write_text("")
        path, expect = (
            str(tmp_path / "a-file" / "report"),
            f"{tmp_path / 'a-file'} is a file, not a directory",
        )
    elif bad == "missing-dir":
        path = str(tmp_path / "no-such-dir" / f"out{suffix}")
        expect = f"the directory {tmp_path / 'no-such-dir'} does not exist"
    elif flag == "--out" and command == "study":
        (tmp_path / "a-file").write_text("")
        path, expect = str(tmp_path / "a-file"), "is a file, not a directory; give a directory for the report"
    else:
        (tmp_path / f"dir{suffix}").mkdir()
        path, expect = str(tmp_path / f"dir{suffix}"), "is a directory; give a file name"
    before = sorted(p.name for p in tmp_path.rglob("*"))
    code, _out, err = run(_argv(command, flag, path, pattern_file, frames_file, tmp_path), capsys)
    assert code == 1
    shown = "--out" if flag == "-o" else flag
    assert error_line(err, command) == f"{shown} {path}: {expect}"
    assert shared_emulator("cli-errors") is None  # the port was never opened: nothing was sent
    assert sorted(p.name for p in tmp_path.rglob("*")) == before  # the check left nothing behind


def test_the_same_commands_do_open_the_device_with_good_outputs(tmp_path, pattern_file, capsys) -> None:
    """The control: with writable outputs the device is opened and configured."""
    code, _, err = run(
        ["send", "--pattern", "all:1", "--device", DEVICE, "--audit-log", str(tmp_path / "a.jsonl")], capsys
    )
    assert code == 0, err
    assert shared_emulator("cli-errors").state().electrode_num == 32
    assert (tmp_path / "a.jsonl").stat().st_size > 0


def test_study_out_under_proc_is_refused_before_any_trial(capsys) -> None:
    if not Path("/proc").is_dir() or sys.platform != "linux":
        pytest.skip("needs Linux /proc")
    code, _, err = run(["study", "task1", "--quiet", "--out", "/proc/forbidden", "--device", DEVICE], capsys)
    assert code == 1
    assert error_line(err, "study").startswith("--out /proc/forbidden: cannot create a directory in /proc")
    assert shared_emulator("cli-errors") is None


@pytest.mark.skipif(
    not hasattr(os, "geteuid") or os.geteuid() == 0, reason="root writes into read-only directories"
)
def test_read_only_directory_is_refused(tmp_path, capsys) -> None:
    ro = tmp_path / "ro"
    ro.mkdir()
    ro.chmod(0o500)
    try:
        code, _, err = run(
            ["send", "--pattern", "all:1", "--device", DEVICE, "--audit-log", str(ro / "a.jsonl")], capsys
        )
    finally:
        ro.chmod(0o700)
    assert code == 1 and "cannot be created" in error_line(err, "send")
    assert shared_emulator("cli-errors") is None


def test_existing_output_is_kept_by_the_check(tmp_path, capsys) -> None:
    log = tmp_path / "a.jsonl"
    log.write_text('{"earlier": true}\n')
    assert (
        run(
            ["send", "--pattern", "all:1", "--electrodes", "0", "--device", DEVICE, "--audit-log", str(log)],
            capsys,
        )[0]
        == 1
    )
    assert log.read_text() == '{"earlier": true}\n'


# --- 2. no traceback; --debug shows one -------------------------------------------------------------------


@pytest.mark.parametrize(
    "argv",
    [
        [
            "render",
            "--scene",
            "cube",
            "--trajectory",
            "approach-face",
            "--quiet",
            "--gif",
            "/nonexistent/f.gif",
        ],
        ["timing", "--png", "/nonexistent/x.png"],
        ["send", "--pattern", "all:1", "--frequency-hz", "0"],
        ["decode", "fc0"],
    ],
)
def test_a_real_process_prints_one_line_and_no_traceback(argv: list[str]) -> None:
    proc = subprocess.run(
        [sys.executable, "-m", "tactdeform_hw.cli", *argv],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert proc.returncode == 1
    assert "Traceback" not in proc.stderr
    assert proc.stderr.strip().splitlines()[-1].startswith(f"tactdeform-hw {argv[0]}: error: ")


def test_a_usage_error_in_a_real_process_exits_2() -> None:
    proc = subprocess.run(
        [sys.executable, "-m", "tactdeform_hw.cli", "send", "--pattern", "all:1", "--hold-ms", "-1"],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert proc.returncode == 2 and "Traceback" not in proc.stderr
    assert proc.stderr.strip().splitlines()[-1] == (
        "tactdeform-hw send: error: argument --hold-ms: -1 is out of range: a duration ≥ 0 ms"
    )


@pytest.mark.parametrize(
    ("argv", "last_line"),
    [
        (
            ["send", "--pattern", "all:1", "--hold-ms", "soon"],
            "tactdeform-hw send: error: argument --hold-ms: 'soon' is not a number of ms",
        ),
        (
            ["send", "--pattern", "all:1", "--timeout-s", "soon"],
            "tactdeform-hw send: error: argument --timeout-s: 'soon' is not a number of s",
        ),
        (
            ["send", "--pattern", "all:1", "--timeout-s", "0"],
            "tactdeform-hw send: error: argument --timeout-s: 0 is out of range: a number > 0 s",
        ),
    ],
)
def test_a_duration_or_a_positive_number_that_is_not_one_names_the_text_and_unit(
    argv: list[str], last_line: str, capsys: pytest.CaptureFixture[str]
) -> None:
    with pytest.raises(SystemExit) as exit_info:
        run(argv, capsys)
    assert exit_info.value.code == 2
    assert capsys.readouterr().err.strip().splitlines()[-1] == last_line


def test_an_os_error_while_writing_is_one_line(tmp_path, capsys, monkeypatch) -> None:
    import tactdeform_hw.formats as formats

    def full(*_a, **_k):
        raise OSError(28, "No space left on device", str(tmp_path / "x.json"))

    frames = tmp_path / "f.jsonl"
    frames.write_text(
        json.dumps({"t": 0.0, "state": "idle", "electrodes": [1] + [0] * 31, "sent": True}) + "\n"
    )
    monkeypatch.setattr(formats, "write_pattern_file", full)
    code, _, err = run(["export", str(frames), "-o", str(tmp_path / "x.json")], capsys)
    assert code == 1
    assert error_line(err, "export") == f"{tmp_path / 'x.json'}: No space left on device"


def test_an_unexpected_error_is_one_line_and_debug_shows_the_traceback(capsys, monkeypatch) -> None:
    from tactdeform_hw.cli import decode

    def broken(_args):
        raise RuntimeError("boom")

    monkeypatch.setattr(decode, "run", broken)
    code, _, err = run(["decode", "fc 20"], capsys)
    assert code == 1
    assert error_line(err, "decode") == (
        "unexpected RuntimeError: boom; run 'tactdeform-hw --debug ...' for the traceback"
    )
    code, _, err = run(["--debug", "decode", "fc 20"], capsys)
    assert code == 1
    assert "Traceback (most recent call last)" in err and 'raise RuntimeError("boom")' in err
    assert err.strip().splitlines()[-1] == "tactdeform-hw decode: error: unexpected RuntimeError: boom"
    code, _, err = run(["decode", "fc 20", "--debug"], capsys)  # where a user adds it after seeing the error
    assert code == 1 and "Traceback (most recent call last)" in err


# --- 3. messages name the flag typed; a safety refusal is said once --------------------------------------


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (
            ["send", "--pattern", "all:1", "--frequency-hz", "0"],
            "--frequency-hz 0 is out of range: 1 to 65535 Hz",
        ),
        (["send", "--pattern", "all:1", "--frequency", "0"], "--frequency 0 is out of range: 1 to 65535 Hz"),
        (["send", "--pattern", "all:1", "--electrodes", "0"], "--electrodes 0 is out of range: 1 to 255"),
        (
            ["send", "--pattern", "all:1", "--pulse-width-us", "0"],
            "--pulse-width-us 0 is out of range: 1 to 65535 µs",
        ),
        (
            ["send", "--pattern", "all:1", "--discharge", "300"],
            "--discharge 300 is out of range: 0 to 255 µs",
        ),
        (
            ["send", "--pattern", "all:1", "--current-ua", "20000"],
            "--current-ua 20000 is out of range: 0 to 10000 µA",
        ),
        (
            ["send", "--pattern", "all:1", "--current-ua", "15"],
            "--current-ua 15 is out of range: a multiple of 10 µA",
        ),
        (["timing", "--electrodes", "256"], "--electrodes 256 is out of range: 0 to 255"),
        (["timing", "--pulse-width-us", "70000"], "--pulse-width-us 70000 is out of range: 1 to 65535 µs"),
        (["timing", "--current-ua", "20000"], "--current-ua 20000 is out of range: 0 to 10000 µA"),
        (["timing", "--pulse-height", "5000"], "--pulse-height 5000 is out of range: 0 to 4095"),
        (["timing", "--frequency", "0"], "--frequency 0 is out of range: 1 to 65535 Hz"),
        (["decode", "fc", "--electrodes", "300"], "--electrodes 300 is out of range: 0 to 255"),
        (
            ["render", "--scene", "cube", "--trajectory", "approach-face", "--rate-hz", "0"],
            "--rate-hz 0.0 is out of range: > 0 Hz",
        ),
        (
            ["render", "--scene", "cube", "--trajectory", "approach-face", "--rate", "0"],
            "--rate 0.0 is out of range: > 0 Hz",
        ),
        (
            ["study", "task1", "--out", "never", "--rate-hz", "0"],
            "--rate-hz 0.0 is out of range: a finite rate > 0 Hz",
        ),
        (
            ["send", "--pattern", "all:3"],
            "--pattern value 0 (3) is out of range: 0 (off), 1 (monophasic) or 2 (biphasic)",
        ),
        (
            ["send", "--pattern", "1,0,2", "--electrodes", "4"],
            "--pattern has 3 level(s) but --electrodes is 4; give one level per electrode, or all:LEVEL",
        ),
        (["timing", "--pattern", "1,2,300"], "--pattern value 2 (300) is out of range: 0 to 255"),
        (
            ["timing", "--set", "gpio_write_us=-1"],
            "--set gpio_write_us=-1 is out of range: a finite number >= 0",
        ),
        (
            ["timing", "--sense-current-ua", "50"],
            "--sense-current-ua 50 is out of range: a multiple of 40 µA from 0 to 10200 µA (firmware v1.2 "
            "stores the byte sent << 2)",
        ),
        (
            ["calibrate", "--participant", "P01", "--max-ua", "20000", "--keys", os.devnull],
            "--max-ua 20000 is out of range: 1 to 10000 µA",
        ),
        (
            ["calibrate", "--participant", "P01", "--ramp-ua", "-5", "--keys", os.devnull],
            "--ramp-ua -5 is out of range: 10 to 10000 µA",
        ),
        (
            ["export", "FRAMES", "-o", "x.json", "--frequency", "0"],
            "--frequency 0 is out of range: 1 to 65535 Hz",
        ),
        (["play", "PATTERN", "--repeat", "0"], "--repeat 0 is out of range: at least 1"),
    ],
)
def test_errors_name_the_flag_typed(
    argv, message, capsys, tmp_path, monkeypatch, pattern_file, frames_file
) -> None:
    monkeypatch.chdir(tmp_path)
    argv = [str(pattern_file) if a == "PATTERN" else str(frames_file) if a == "FRAMES" else a for a in argv]
    argv = (
        [*argv, "--device", DEVICE] if argv[0] in ("send", "render", "study", "play", "calibrate") else argv
    )
    code, _, err = run(argv, capsys)
    assert code == 1
    assert error_line(err, argv[0]) == message
    for internal in ("rate_hz", "electrode_count", "electrodes=", "pulse_width_us", "current_ua="):
        assert internal not in err
    assert shared_emulator("cli-errors") is None
    assert not (tmp_path / "never").exists() and not (tmp_path / "x.json").exists()
    assert not (tmp_path / "P01.json").exists()


def test_play_names_the_file_field_for_a_rate_from_the_file(tmp_path, pattern_file, capsys) -> None:
    doc = json.loads(pattern_file.read_text())
    doc["Pattern_Data"][0][0]["params"]["frequency"] = 0
    pattern_file.write_text(json.dumps(doc))
    code, _, err = run(["play", str(pattern_file), "--quiet", "--device", DEVICE], capsys)
    assert code == 1
    assert error_line(err, "play") == (
        "pattern.json: Pattern_Data[0][0].params.frequency: expected a stimulation "
        "frequency in Hz from 1 to 65535, got 0"
    )
    assert shared_emulator("cli-errors") is None


def test_play_names_its_own_flags(pattern_file, capsys) -> None:
    code, _, err = run(
        ["play", str(pattern_file), "--quiet", "--device", DEVICE, "--pulse-width", "0"], capsys
    )
    assert code == 1
    assert error_line(err, "play") == "--pulse-width 0 is out of range: 1 to 65535 µs"
    assert shared_emulator("cli-errors") is None


@pytest.mark.parametrize("command", ["send", "render", "study"])
def test_a_safety_refusal_is_said_once(command, profile, tmp_path, capsys) -> None:
    argv = {
        "send": ["send", "--pattern", "all:1"],
        "render": ["render", "--scene", "cube", "--trajectory", "approach-face", "--quiet"],
        "study": ["study", "task1", "--quick", "--quiet", "--out", str(tmp_path / "r")],
    }[command]
    code, _, err = run(
        [*argv, "--participant", str(profile), "--current-ua", "3000", "--device", DEVICE], capsys
    )
    assert code == 1
    assert err.count("exceeds the cap of 2000 µA") == 1, err
    assert error_line(err, command).startswith(
        "--current-ua 3000 µA exceeds the cap of 2000 µA for participant P01"
    )
    assert shared_emulator("cli-errors") is None


# --- 4. one vocabulary; earlier spellings work with a warning --------------------------------------------


def _parsed(argv: list[str]):
    from tactdeform_hw.cli.options import finish

    args = build_parser().parse_args(argv)
    finish(args)
    return args


@pytest.mark.parametrize(
    ("old", "new", "attr", "value"),
    [
        (
            ["send", "--pattern", "1", "--pulse-width", "250"],
            ["send", "--pattern", "1", "--pulse-width-us", "250"],
            "pulse_width",
            250,
        ),
        (
            ["send", "--pattern", "1", "--discharge", "40"],
            ["send", "--pattern", "1", "--discharge-us", "40"],
            "discharge",
            40,
        ),
        (
            ["send", "--pattern", "1", "--frequency", "200"],
            ["send", "--pattern", "1", "--frequency-hz", "200"],
            "frequency",
            200,
        ),
        (
            ["send", "--pattern", "1", "--hold", "0.25"],
            ["send", "--pattern", "1", "--hold-ms", "250"],
            "hold",
            0.25,
        ),
        (
            ["send", "--pattern", "1", "--timeout", "2"],
            ["send", "--pattern", "1", "--timeout-s", "2"],
            "timeout",
            2.0,
        ),
        (
            ["play", "f.json", "--pulse-width", "150"],
            ["play", "f.json", "--pulse-width-us", "150"],
            "pulse_width",
            150,
        ),
        (
            ["calibrate", "--participant", "P", "--pulse-width", "150"],
            ["calibrate", "--participant", "P", "--pulse-width-us", "150"],
            "pulse_width",
            150,
        ),
        (
            ["render", "--scene", "cube", "--trajectory", "approach-face", "--rate", "90"],
            ["render", "--scene", "cube", "--trajectory", "approach-face", "--rate-hz", "90"],
            "rate",
            90.0,
        ),
        (
            ["render", "--scene", "cube", "--trajectory", "approach-face", "--speed", "40"],
            ["render", "--scene", "cube", "--trajectory", "approach-face", "--speed-mm-s", "40"],
            "speed",
            40.0,
        ),
        (
            ["study", "task1", "--out", "x", "--rate", "90"],
            ["study", "task1", "--out", "x", "--rate-hz", "90"],
            "rate",
            90.0,
        ),
        (
            ["export", "f", "-o", "x", "--frequency", "100"],
            ["export", "f", "-o", "x", "--frequency-hz", "100"],
            "frequency",
            100,
        ),
        (
            ["export", "f", "-o", "x", "--stim-mode", "0"],
            ["export", "f", "-o", "x", "--polarity", "cathodic"],
            "stim_mode",
            0,
        ),
        (["timing", "--pulse-height", "150"], ["timing", "--current-ua", "1500"], "pulse_height", 150),
        (["timing", "--sense-height", "25"], ["timing", "--sense-current-ua", "1000"], "sense_height", 25),
        (["timing", "--sense-width", "20"], ["timing", "--sense-width-us", "20"], "sense_width", 20),
        (["timing", "--polarity", "0"], ["timing", "--polarity", "cathodic"], "polarity", 0),
    ],
)
def test_earlier_spellings_still_work_and_warn(old, new, attr, value, capsys) -> None:
    a_new = _parsed(new)
    assert capsys.readouterr().err == ""
    a_old = _parsed(old)
    err = capsys.readouterr().err
    assert getattr(a_new, attr) == getattr(a_old, attr) == value
    assert f"tactdeform-hw {old[0]}: warning: " in err and "deprecated" in err and "next release" in err


def test_help_lists_only_the_new_spellings_with_units(capsys) -> None:
    """Every option whose help gives a unit carries it in its name; earlier spellings are not listed."""
    parser = build_parser()
    sub = next(a for a in parser._actions if isinstance(a, type(parser._subparsers._group_actions[0])))
    units = {"µs": "-us", "Hz": "-hz", "ms": "-ms", "seconds": "-s", "mm/s": "-mm-s", "µA": "-ua"}
    checked = 0
    for name, p in sub.choices.items():
        for action in p._actions:
            if not action.option_strings or action.help in (None, "==SUPPRESS=="):
                continue
            flag = action.option_strings[-1]
            for unit, suffix in units.items():
                if (
                    action.help.startswith(
                        (
                            "pulse",
                            "stimulation",
                            "channel",
                            "sense",
                            "hold",
                            "read/write",
                            "finger",
                            "tracking",
                            "params.frequency",
                            "calibration",
                        )
                    )
                    and f" in {unit}" in action.help
                ):
                    assert flag.endswith(suffix), f"{name} {flag}: {action.help}"
                    checked += 1
        text = p.format_help()
        for old in (
            "--pulse-width ",
            "--discharge ",
            "--frequency ",
            "--hold ",
            "--pulse-height ",
            "--stim-mode",
        ):
            assert old not in text, f"{name} lists {old}"
    assert checked >= 20


def test_polarity_is_a_name_everywhere() -> None:
    parser = build_parser()
    sub = parser._subparsers._group_actions[0]
    for name, p in sub.choices.items():
        for action in p._actions:
            if "--polarity" in action.option_strings:
                assert "anodic" in (action.metavar or "") + str(action.choices), name


def test_timing_output_is_in_microseconds(capsys) -> None:
    code, out, _ = run(["timing", "--latency", "--phases", "2"], capsys)
    assert code == 0
    assert "µs" in out
    assert " us" not in out and "us:" not in out and "(us" not in out


# --- 5. exit statuses a script can use --------------------------------------------------------------------


@pytest.mark.parametrize(
    ("argv", "status", "verdict"),
    [
        (["--discharge-us", "45"], 0, "FITS"),
        (["--discharge-us", "50"], timing_cli.EXIT_OVERRUN, "OVERRUN"),
        (["--electrodes", "200", "--pulse-width-us", "2000"], timing_cli.EXIT_WATCHDOG, "WATCHDOG RESET"),
    ],
)
def test_timing_exit_status_follows_the_verdict(argv, status, verdict, capsys) -> None:
    code, out, _ = run(["timing", *argv], capsys)
    assert code == status
    assert f"verdict: {verdict}" in out
    code, out, _ = run(["timing", *argv, "--json"], capsys)
    assert code == status and json.loads(out)["verdict"] == verdict.lower()


def test_exit_statuses_are_documented(capsys) -> None:
    assert (timing_cli.EXIT_OVERRUN, timing_cli.EXIT_WATCHDOG) == (3, 4)
    with pytest.raises(SystemExit):
        main(["timing", "--help"])
    text = " ".join(capsys.readouterr().out.split())
    assert "3 when it OVERRUNs" in text and "4 when it trips the interrupt WATCHDOG" in text
    with pytest.raises(SystemExit):
        main(["--help"])
    top = capsys.readouterr().out
    assert "exit status:" in top and top.count("\n  ") >= 7
    assert EXIT_STATUS_HELP.splitlines()[0] in top
    guide = (ROOT / "docs" / "researcher-guide.md").read_text()
    assert "| 3 |" in guide and "| 4 |" in guide and "OVERRUN" in guide and "WATCHDOG" in guide


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("fc0", "odd number of hex digits at position 2"),
        ("fc 0 fe", "odd number of hex digits at position 3"),
        ("f c", "odd number of hex digits at position 0"),
        ("fc zz", "'z' at position 3 is not a hex digit"),
    ],
)
def test_decode_refuses_bad_hex(text, message, capsys) -> None:
    code, out, err = run(["decode", text], capsys)
    assert code == 1 and out == ""
    assert message in error_line(err, "decode")


def test_decode_accepts_what_it_always_did(capsys) -> None:
    code, out, _ = run(["decode", "0xfc,0x20:FE 01"], capsys)
    assert code == 0 and "ELECTRODE_NUM" in out


@pytest.mark.parametrize("argv", [["decode", ""], ["decode", "  "], ["decode", "--file", "EMPTY"]])
def test_decode_refuses_an_empty_capture(argv, tmp_path, capsys) -> None:
    (tmp_path / "empty.bin").write_bytes(b"")
    argv = [str(tmp_path / "empty.bin") if a == "EMPTY" else a for a in argv]
    code, _, err = run(argv, capsys)
    assert code == 1 and error_line(err, "decode") == "the capture is empty: no bytes to decode"


@pytest.mark.parametrize("command", ["send", "play", "render", "study", "calibrate"])
def test_a_regular_file_is_not_a_serial_port(command, tmp_path, pattern_file, frames_file, capsys) -> None:
    fake = tmp_path / "ttyFAKE"
    fake.write_bytes(b"")
    argv = _argv(command, "--device", str(fake), pattern_file, frames_file, tmp_path)
    code, _, err = run(argv, capsys)
    assert code == 1
    assert error_line(err, command).startswith(f"--device {fake} is not a serial port (a regular file)")
    assert fake.read_bytes() == b""
    assert not (tmp_path / "report").exists()


def test_a_missing_port_is_said_plainly(tmp_path, capsys) -> None:
    code, _, err = run(["send", "--pattern", "1", "--device", str(tmp_path / "ttyACM9")], capsys)
    assert code == 1 and error_line(err, "send").startswith(
        f"--device {tmp_path / 'ttyACM9'}: no such device"
    )


# --- 6. missing extras are said on the console -----------------------------------------------------------


def test_study_without_plot_says_so_on_the_console(tmp_path, capsys, monkeypatch) -> None:
    for name in [m for m in sys.modules if m.startswith("matplotlib.")]:  # as on a machine without it
        monkeypatch.delitem(sys.modules, name)
    monkeypatch.setitem(sys.modules, "matplotlib", None)
    code, _, err = run(["study", "task1", "--quick", "--quiet", "--out", str(tmp_path / "r")], capsys)
    assert code == 0, err
    assert (
        "tactdeform-hw study: warning: the report will have no pictures: they need matplotlib and Pillow, "
        f"{install_command('plot')}"
    ) in err
    assert "pictures skipped" in (tmp_path / "r" / "summary.md").read_text()


@pytest.mark.parametrize(
    ("module", "argv", "package"),
    [
        (
            "matplotlib",
            ["render", "--scene", "cube", "--trajectory", "approach-face", "--quiet", "--gif", "OUT.gif"],
            "matplotlib",
        ),
        ("matplotlib", ["timing", "--png", "OUT.png"], "matplotlib"),
        ("vcd", ["timing", "--vcd", "OUT.vcd"], "pyvcd"),
    ],
)
def test_an_output_needing_a_missing_extra_is_refused_first(
    module, argv, package, tmp_path, capsys, monkeypatch
):
    monkeypatch.setitem(sys.modules, module, None)
    argv = [str(tmp_path / a) if a.startswith("OUT.") else a for a in argv]
    if argv[0] == "render":
        argv += ["--device", DEVICE]
    code, _, err = run(argv, capsys)
    assert code == 1
    assert f"needs the optional package {package!r}" in error_line(err, argv[0])
    assert shared_emulator("cli-errors") is None
    assert list(tmp_path.iterdir()) == []


# --- 7. negative durations --------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("argv", "flag", "unit"),
    [
        (["send", "--pattern", "1", "--hold", "-1"], "--hold", "s"),
        (["send", "--pattern", "1", "--hold-ms", "-1"], "--hold-ms", "ms"),
        (["calibrate", "--participant", "P", "--hold-ms", "-5"], "--hold-ms", "ms"),
        (["export", "f", "-o", "x", "--last-ms", "-1"], "--last-ms", "ms"),
        (["replay-log", "f", "--tail-ms", "-1"], "--tail-ms", "ms"),
    ],
)
def test_negative_durations_are_refused(argv, flag, unit, capsys) -> None:
    err = usage_error(
        [*argv[:1], "--device", DEVICE, *argv[1:]] if argv[0] in ("send", "calibrate") else argv, capsys
    )
    value = argv[-1]
    assert err.strip().splitlines()[-1] == (
        f"tactdeform-hw {argv[0]}: error: argument {flag}: {value} is out of range: a duration ≥ 0 {unit}"
    )
    assert shared_emulator("cli-errors") is None


def test_a_zero_timeout_is_refused(capsys) -> None:
    err = usage_error(["send", "--pattern", "1", "--timeout-s", "0"], capsys)
    assert "argument --timeout-s: 0 is out of range: a number > 0 s" in err


# --- 8. the study overview fits a screen ------------------------------------------------------------------


@pytest.mark.slow  # a whole quick study with its pictures
def test_study_overview_fits_a_screen(tmp_path, capsys) -> None:
    pytest.importorskip("matplotlib")
    from PIL import Image

    code, _, _ = run(
        ["study", "task1", "--quick", "--no-timed", "--quiet", "--out", str(tmp_path / "r")], capsys
    )
    assert code == 0
    report = json.loads((tmp_path / "r" / "report.json").read_text())
    with Image.open(tmp_path / "r" / report["pictures"]["overview"]) as im:
        w, h = im.size
    assert w <= 1920 and h <= 1200 and [w, h] == report["pictures"]["overview_size_px"]
    assert w > h  # a grid, not the column of strips it replaced (660 × 3885 px for the full task1)


def test_overview_grid_for_every_study_size() -> None:
    from tactdeform_hw.viz.study_overview import grid_for

    for n in range(1, 25):
        cols, rows, thumb = grid_for(n, 4)
        assert cols * rows >= n and thumb >= 80, (n, cols, rows, thumb)


def test_overview_labels_are_at_least_10_pt(tmp_path) -> None:
    pytest.importorskip("matplotlib")
    from tactdeform_hw.render.array import ElectrodeArray
    from tactdeform_hw.viz.study_overview import OverviewFrame, OverviewTrial, draw_study_overview

    array = ElectrodeArray.tactdeform()
    trials = [
        OverviewTrial(
            f"t{i}",
            i % 5 != 0,
            tuple(OverviewFrame((1,) * (i % 32) + (0,) * (32 - i % 32), f"{i} s") for _ in range(4)),
        )
        for i in range(24)
    ]
    info = draw_study_overview(array.positions_mm, array.radius_mm, trials, tmp_path / "o.png", title="t")
    assert info.min_font_pt >= 10
    assert info.size_px[0] <= 1920 and info.size_px[1] <= 1200


# --- 9. .gitignore covers what the README's commands write ------------------------------------------------


def test_gitignore_covers_the_readme_outputs() -> None:
    if not (ROOT / ".git").exists():
        pytest.skip("not a git checkout")

    def ignored(path: str) -> bool:
        proc = subprocess.run(["git", "check-ignore", "-q", "--no-index", path], cwd=ROOT)
        return proc.returncode == 0

    for path in ("frames.jsonl", "face.jsonl", "face.gif", "study-task1/report.json", "trace.vcd"):
        assert ignored(path), path
    assert not ignored("tests/data/protocol_vectors.jsonl")
    assert not ignored("tactdeform_hw/cli/__init__.py")


# --- every command: usage errors and unreadable inputs ----------------------------------------------------


@pytest.mark.parametrize(
    "command",
    [
        "emulate",
        "ports",
        "decode",
        "send",
        "play",
        "export",
        "render",
        "study",
        "timing",
        "calibrate",
        "replay-log",
    ],
)
def test_an_unknown_option_is_a_usage_error_for_every_command(command, capsys) -> None:
    err = usage_error([command, "--no-such-option"], capsys)
    assert "Traceback" not in err
    assert err.strip().splitlines()[-1].startswith(f"tactdeform-hw {command}: error: ")
    assert shared_emulator("cli-errors") is None


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["replay-log", "MISSING"], "audit log MISSING: cannot be read (No such file or directory)"),
        (["play", "MISSING", "--device", DEVICE], "MISSING: cannot read: No such file or directory"),
        (["export", "MISSING", "-o", "OUT"], "MISSING: cannot read: No such file or directory"),
        (
            ["send", "--pattern", "1", "--participant", "MISSING", "--device", DEVICE],
            "participant profile MISSING",
        ),
    ],
)
def test_a_missing_input_file_is_one_line(argv, message, tmp_path, capsys) -> None:
    missing, out = str(tmp_path / "missing.json"), str(tmp_path / "out.json")
    argv = [missing if a == "MISSING" else out if a == "OUT" else a for a in argv]
    code, _, err = run(argv, capsys)
    assert code == 1
    assert error_line(err, argv[0]).startswith(message.replace("MISSING", missing))
    assert shared_emulator("cli-errors") is None and not Path(out).exists()
