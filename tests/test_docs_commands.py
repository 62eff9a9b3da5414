"""Every command the README and ``docs/*.md`` show is checked here, so none can drift from the code.

Each command (read out of the documents by :mod:`tests.doc_commands`, which also states the convention for
output that varies between machines) is in exactly one of three lists:

* :data:`FAST` — run here, in a temporary directory on the in-process emulator, its printed lines compared
  with the shown ones and its exit status with the shown one;
* :data:`SLOW` — run by ``tests/test_docs_commands_slow.py`` (marked ``slow``: CI's own step), some at a
  reduced size;
* :data:`ALLOWED` — not run, each with the reason (real hardware, an upstream checkout, a downstream
  project's own files, a live tracker).

Whatever the list, every command is parsed by its own argument parser here: a documented flag that no
longer exists fails this file.  So is every command the prose names in backticks
(:func:`~tests.doc_commands.inline_commands`: synopses with placeholders aside), as a mention: the
options it gives must exist, the ones it leaves out are not asked for.
"""

from __future__ import annotations

import json
import shutil
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import pytest

from tactdeform_hw.emulator.serving.urlhandler.protocol_etactile import forget_shared

from .conftest import shared_path
from .doc_commands import (
    DocCommand,
    all_commands,
    inline_commands,
    matches,
    parse_check,
    parse_check_mention,
    run,
)

ROOT = Path(__file__).resolve().parents[1]
GUIDE = "docs/researcher-guide.md"


@dataclass(frozen=True)
class Case:
    """How to run one documented command: the files it reads (made by :data:`MAKERS` first) and the
    words that stand for a placeholder of the document (``<the 4 centre electrodes>``)."""

    needs: tuple[str, ...] = ()
    substitute: dict[str, str] = field(default_factory=dict)
    #: a check of what the command wrote, given the directory it ran in
    wrote: Callable[[Path], None] | None = None


# --- the files the documents' commands read, made as the documents describe them -----------------------


def _block_after(doc: str, opening: str) -> str:
    """The body of the code block that starts with ``opening`` (its first lines) in ``doc``."""
    text = (ROOT / doc).read_text(encoding="utf-8")
    return opening + text.split(opening, 1)[1].split("```", 1)[0]


def _centre_pattern() -> str:
    return ",".join("1" if i in (12, 13, 18, 19) else "0" for i in range(32))


def _profile(participant: str, cap_ua: int, regions_ua: list[int]) -> str:
    return json.dumps(
        {
            "version": 1,
            "participant": participant,
            "cap_ua": cap_ua,
            "regions_ua": regions_ua,
            "pulse_width_us": 200,
            "polarity": "anodic",
            "contact_mode": "orientation",
            "calibrated_on": "2025-03-14",
        }
    )


def _session_csv(bad: bool) -> Callable[[Path], None]:
    """The guide's synthetic recording (its own Python block, run), and with ``bad`` the same with a NaN
    in line 200's ``z_mm``."""

    def make(tmp: Path) -> None:
        code = _block_after(GUIDE, "# a recorded session would come from the tracker")
        exec(compile(code, GUIDE, "exec"), {})  # noqa: S102 — the guide's own code
        if bad:
            lines = (tmp / "session.csv").read_text().splitlines()
            cells = lines[199].split(",")
            cells[lines[0].split(",").index("z_mm")] = "nan"
            lines[199] = ",".join(cells)
            (tmp / "session.csv").write_text("\n".join(lines) + "\n")

    return make


def _reversed_array(tmp: Path) -> None:
    """safety.md's ``tactdeform_reversed.json``: the TactDeform electrodes listed in reverse order."""
    from tactdeform_hw.device.participant.regions import TACTDEFORM_POSITIONS_MM

    electrodes = [{"x": x, "y": y} for x, y in reversed(TACTDEFORM_POSITIONS_MM)]
    doc = {"outline": [], "electrodes": electrodes, "Electrodes_Number": 32, "Mapping_func": list(range(32))}
    (tmp / "tactdeform_reversed.json").write_text(json.dumps({**doc, "electrode_radius": 0.7}))


def _fingertip_left(tmp: Path) -> None:
    """safety.md's ``fingertip_left.json``: one 100 ms step activating electrode 31 only."""
    step = {
        "delay": {"ON": 100, "OFF": 0},
        "pattern": [0] * 31 + [1],
        "params": {"frequency": 125, "stim_mode": 1},
    }
    (tmp / "fingertip_left.json").write_text(
        json.dumps({"Execution": True, "Simulation": True, "Pattern_Data": [[step]]})
    )


def _by_command(command: str) -> Callable[[Path], None]:
    def make(tmp: Path) -> None:
        status, lines = run(command)
        assert status == 0, (command, lines)

    return make


def _shared_sample(name: str) -> Callable[[Path], None]:
    def make(tmp: Path) -> None:
        shutil.copy(shared_path("etactilekit-formats", name), tmp / name)

    return make


MAKERS: dict[str, Callable[[Path], None]] = {
    "p01.json": lambda tmp: (tmp / "p01.json").write_text(_profile("P01", 2000, [2000] * 9)),
    "notes.txt": lambda tmp: (tmp / "notes.txt").write_text("not a board\n"),
    "P07.toml": lambda tmp: (tmp / "P07.toml").write_text(_block_after(GUIDE, "# P07.toml\n")),
    "P07bad.toml": lambda tmp: (tmp / "P07bad.toml").write_text(
        _block_after(GUIDE, "# P07.toml\n").replace("regions_ua = [1500,", "regions_ua = [1900,")
    ),
    "P09.toml": lambda tmp: (tmp / "P09.toml").write_text(
        "version = 1\nparticipant = 'P09'\ncap_ua = 2000\nregions_ua = [400, 2000, 2000, 2000, 2000, "
        "2000, 2000, 2000, 2000]\n"
        "pulse_width_us = 200\npolarity = 'anodic'\ncontact_mode = 'orientation'\ncalibrated_on = "
        "2025-03-14\n"
    ),
    "two-bars.toml": lambda tmp: (tmp / "two-bars.toml").write_text(_block_after(GUIDE, "# two-bars.toml\n")),
    "rehearsal.keys": lambda tmp: (tmp / "rehearsal.keys").write_text(
        _block_after(GUIDE, "# centre up: 15 jumps")
    ),
    "session.csv": _session_csv(bad=False),
    "bad session.csv": _session_csv(bad=True),
    "frames.jsonl": _by_command(
        "tactdeform-hw render --scene cube --trajectory approach-face --frames frames.jsonl"
    ),
    "approach.json": _by_command("tactdeform-hw export frames.jsonl -o approach.json"),
    "tactdeform_reversed.json": _reversed_array,
    "fingertip_left.json": _fingertip_left,
    "s2.jsonl": _by_command(
        "tactdeform-hw play fingertip_left.json --array tactdeform_reversed.json --current-ua 2000 --quiet "
        "--audit-log s2.jsonl"
    ),
    "test_pattern.json": _shared_sample("test_pattern.json"),
    "electrode_array_main_board.json": _shared_sample("electrode_array_main_board.json"),
}


def _strip_as_shown(tmp: Path) -> None:
    """The README's strip picture is what the command draws: as many frames side by side."""
    from PIL import Image

    shown = Image.open(ROOT / "docs" / "figures" / "face-approach-strip.png")
    assert shown.size == Image.open(tmp / "face.png").size


_SAFETY_FILES = ("P09.toml", "tactdeform_reversed.json", "fingertip_left.json")

#: Run here: fast and hardware-free (the in-process emulator), each well under a second.
FAST: dict[str, Case] = {
    "README.md | tactdeform-hw timing --electrodes 32 --pulse-width-us 200 --discharge-us 45 "
    "--frequency-hz 125": Case(),
    "README.md | tactdeform-hw timing --electrodes 32 --pulse-width-us 200 --discharge-us 50 "
    "--frequency-hz 125 --json": Case(),
    "README.md | tactdeform-hw render --scene cube --trajectory approach-face --frames face.jsonl --gif "
    "face.gif --strip face.png": Case(wrote=_strip_as_shown),
    'README.md | tactdeform-hw decode "fc 04 fe 01 02 00 01 fb dc"': Case(),
    "docs/firmware-guide.md | tactdeform-hw timing --electrodes 32 --pulse-width-us 200 --discharge-us 45 "
    "--frequency-hz 125": Case(),
    "docs/firmware-guide.md | tactdeform-hw timing --electrodes 32 --pulse-width-us 200 --discharge-us 50 "
    "--frequency-hz 125": Case(),
    "docs/firmware-guide.md | tactdeform-hw timing --pattern 1,2,0,1 --sense-current-ua 400 "
    "--sense-width-us 20": Case(),
    "docs/firmware-guide.md | tactdeform-hw timing --list-model": Case(),
    "docs/firmware-guide.md | tactdeform-hw timing --pattern 2 --electrodes 32 --set gpio_write_us=0.1 "
    "--set isr_entry_us=5": Case(),
    "docs/firmware-guide.md | tactdeform-hw timing --set nosuch=1": Case(),
    "docs/firmware-guide.md | tactdeform-hw timing --set gpio_write_us=-1": Case(),
    "docs/firmware-guide.md | tactdeform-hw timing --electrodes 32 --pulse-width-us 200 --discharge-us 50 "
    "--frequency-hz 125 --overrun-policy skip": Case(),
    "docs/firmware-guide.md | tactdeform-hw timing --electrodes 8 --pulse-width-us 65535 "
    "--frequency-hz 1": Case(),
    "docs/firmware-guide.md | tactdeform-hw timing --electrodes 32 --pulse-width-us 200 --discharge-us 45 "
    "--frequency-hz 125 --latency": Case(),
    "docs/firmware-guide.md | tactdeform-hw timing --electrodes 4 --vcd scan.vcd --events scan.csv --png "
    "scan.png --cycles 2": Case(),
    'docs/firmware-guide.md | tactdeform-hw decode "fc 04 fe 01 02 00 01 fb dc"': Case(),
    'docs/firmware-guide.md | tactdeform-hw decode "fe 01 01 f5 00"': Case(),
    "docs/firmware-v2.md | tactdeform-hw timing --firmware v2 --mode 0 --pattern 100 --electrodes 32 "
    "--pulse-width-us 200 --discharge-us 45 --frequency-hz 125": Case(),
    "docs/firmware-v2.md | tactdeform-hw timing --firmware v2 --mode 2 --pattern 0,0,0,0 "
    "--sense-current-ua 100 --sense-width-us 10": Case(),
    'docs/protocol.md | tactdeform-hw decode "fc 04 fe 01 02 00 01 fb dc"': Case(),
    f"{GUIDE} | tactdeform-hw render --scene cube --trajectory approach-face --frames frames.jsonl": Case(),
    f"{GUIDE} | tactdeform-hw send --pattern all:1 --frequency-hz 0": Case(),
    f"{GUIDE} | tactdeform-hw send --pattern all:1 --participant p01.json --current-ua 3000": Case(
        ("p01.json",)
    ),
    f"{GUIDE} | tactdeform-hw render --scene cube --trajectory approach-face "
    "--gif /nonexistent/f.gif": Case(),
    f"{GUIDE} | tactdeform-hw send --pattern all:1 --device ./notes.txt": Case(("notes.txt",)),
    f'{GUIDE} | tactdeform-hw decode "fc 0 fe"': Case(),
    f'{GUIDE} | python -c "from tactdeform_hw.render.scene import load_scene\ns = '
    "load_scene('two-bars.toml'); "
    'print([(o.name, s.approach_for(o.name)) for o in s.objects]); print(s.needs.as_dict())"': Case(
        ("two-bars.toml",)
    ),
    f"{GUIDE} | tactdeform-hw render --scene sphere --trajectory approach-edge-h": Case(),
    f"{GUIDE} | tactdeform-hw render --scene task1 --trajectory session.csv --quiet": Case(("session.csv",)),
    f"{GUIDE} | tactdeform-hw render --scene task1 --trajectory session.csv --quiet | 2": Case(
        ("bad session.csv",)
    ),
    f"{GUIDE} | tactdeform-hw render --scene sphere --trajectory explore --quiet --json": Case(),
    f"{GUIDE} | for a in tactdeform ua cam; do tactdeform-hw render --scene task1 --trajectory "
    "approach-corner "
    "--approach $a --quiet; done": Case(),
    f'{GUIDE} | python -c "from tactdeform_hw.device.participant.profiles import load_profile; '
    "p = load_profile('P07.toml'); print(p.stimulation_ua, p.charge_limit_nc)\"": Case(("P07.toml",)),
    f"{GUIDE} | tactdeform-hw render --scene task2 --trajectory contact-steep-left --participant "
    "P07bad.toml": Case(("P07bad.toml",)),
    f"{GUIDE} | tactdeform-hw render --scene task1 --trajectory approach-face --participant P07.toml "
    "--current-ua 2000": Case(("P07.toml",)),
    f"{GUIDE} | tactdeform-hw render --scene task1 --trajectory approach-face --participant P07.toml "
    "--quiet": Case(("P07.toml",)),
    f"{GUIDE} | tactdeform-hw calibrate --participant P08.toml --keys rehearsal.keys --ramp-ua 200 "
    "--contact-mode uniform": Case(("rehearsal.keys",)),
    f"{GUIDE} | tactdeform-hw export frames.jsonl -o approach.json --array-out tactdeform_array.json": Case(
        ("frames.jsonl",)
    ),
    f"{GUIDE} | tactdeform-hw play approach.json --dry-run": Case(("frames.jsonl", "approach.json")),
    "docs/safety.md | tactdeform-hw play fingertip_left.json --array tactdeform_reversed.json --participant "
    "P09.toml --current-ua 2000 --quiet --audit-log s1.jsonl": Case(_SAFETY_FILES),
    "docs/safety.md | tactdeform-hw play fingertip_left.json --array tactdeform_reversed.json "
    "--current-ua 2000 "
    "--quiet --audit-log s2.jsonl": Case(_SAFETY_FILES),
    "docs/safety.md | tactdeform-hw replay-log s2.jsonl --participant P09.toml": Case(
        (*_SAFETY_FILES, "s2.jsonl")
    ),
    "docs/safety.md | tactdeform-hw send --participant P07.toml --current-ua 1600 --pattern "
    "<the 4 centre electrodes> --hold-ms 100": Case(
        ("P07.toml",), {"<the 4 centre electrodes>": _centre_pattern()}
    ),
}

#: Run by ``tests/test_docs_commands_slow.py``: long runs, real-time boards, processes, tools.
SLOW: dict[str, Case] = {
    "README.md | pip install . && tactdeform-hw render --scene cube --trajectory approach-face --device "
    "emulator "
    "--frames frames.jsonl": Case(),
    "README.md | tactdeform-hw emulate --pty --spy": Case(),
    "README.md | tactdeform-hw emulate --tcp 8080 --firmware v2": Case(),
    "README.md | tactdeform-hw emulate --usb": Case(),
    "README.md | tactdeform-hw study task1 --device emulator --out study-task1": Case(),
    "docs/firmware-guide.md | tactdeform-hw emulate --pty": Case(),
    "docs/firmware-guide.md | tactdeform-hw emulate --tcp 8080": Case(),
    "docs/firmware-guide.md | tactdeform-hw emulate --pty | 2": Case(),
    "docs/firmware-guide.md | python tools/realtime_lag.py": Case(),
    "docs/firmware-guide.md | python tools/realtime_lag.py --idle 1 --stream 2": Case(),
    "docs/firmware-guide.md | python tools/timing_error.py --durations 1 10 --png timing_error.png": Case(),
    "docs/firmware-v2.md | tactdeform-hw emulate --pty --firmware v2": Case(),
    "docs/firmware-v2.md | tactdeform-hw emulate --tcp 8080 --firmware v2": Case(),
    "docs/firmware-v2.md | tactdeform-hw emulate --tcp 127.0.0.1:0 --firmware v2 --discovery-port 18888 "
    "--kit-id C0FFEE": Case(),
    f"{GUIDE} | python tools/scene_cost.py": Case(),
    f"{GUIDE} | tactdeform-hw render --scene task3 --trajectory slide-rough --quiet --gif slide.gif": Case(),
    f"{GUIDE} | tactdeform-hw study task1 --device emulator --out runs/task1 --quick": Case(),
    f"{GUIDE} | tactdeform-hw play approach.json --current-ua 1000 --quiet": Case(
        ("frames.jsonl", "approach.json")
    ),
    f"{GUIDE} | tactdeform-hw play test_pattern.json --array electrode_array_main_board.json --current-ua "
    "500 "
    "--quiet": Case(("test_pattern.json", "electrode_array_main_board.json")),
    f"{GUIDE} | python tools/render_fidelity.py": Case(),
    "docs/firmware-guide-conformance.md | pytest tests/conformance": Case(),
}

#: Not run: each needs what a test machine does not have.  Every one is still parsed.
ALLOWED: dict[str, str] = {
    "README.md | pip install -e '.[test]' && python -m pytest -q": "CI's own install and test command "
    "(.ci/run runs exactly it)",
    "docs/firmware-host-build.md | tactdeform-hw emulate --pty --firmware-src "
    "eTactileKit/2_Firmware/platform_io_project": "an upstream eTactileKit checkout and a C compiler",
    "docs/firmware-host-build.md | tactdeform-hw emulate --tcp 5000 --firmware-src DIR "
    "[--state-map FILE]": "an upstream firmware checkout (DIR) and a C compiler",
    "docs/firmware-host-build.md | python -c 'from tactdeform_hw.device import open_device; "
    'open_device("etactile://?firmware_src=DIR")\'': "an upstream firmware checkout (DIR) and a C compiler",
    "docs/firmware-host-build.md | tactdeform-hw diff-firmware --firmware-src fw/ --against "
    "fw-before-my-change/ "
    "--streams 500": "two upstream firmware checkouts (a change and its base) and a C compiler",
    f"{GUIDE} | tactdeform-hw render --scene cube --tracking udp://0.0.0.0:9870 --participant p01.json "
    "--latency-report latency.jsonl --json": "a live tracker streaming to the port (it serves until stopped)",
    f"{GUIDE} | python tools/send_tracking.py hand.csv --to 127.0.0.1:9870": "a recorded hand-tracking file "
    "and a renderer listening on the port",
    "docs/testing-downstream.md | pytest tests/test_etactile_conformance.py": "a downstream project's own "
    "test file",
    "docs/testing-downstream.md | pytest tests/test_etactile_conformance.py "
    "--etactile-device pty": "a downstream project's own test file",
    "docs/testing-downstream.md | pytest tests/test_etactile_conformance.py "
    "--etactile-device /dev/ttyACM0": "real hardware: a board on the bench's serial port",
}

#: Placeholders of the allowed and slow commands, for parsing only.
PARSE_SUBSTITUTE: dict[str, str] = {"[--state-map FILE]": "--state-map FILE"}

COMMANDS = all_commands()
BY_KEY = {c.key: c for c in COMMANDS}


pytestmark = pytest.mark.usefixtures("fresh_emulators")


def test_every_documented_command_is_listed_once() -> None:
    lists = [set(FAST), set(SLOW), set(ALLOWED)]
    assert not (lists[0] & lists[1] or lists[0] & lists[2] or lists[1] & lists[2])
    listed = set().union(*lists)
    assert sorted(set(BY_KEY) - listed) == [], "documented commands no list names"
    assert sorted(listed - set(BY_KEY)) == [], "listed commands no document shows"


def test_the_allowlist_stays_small_and_says_why() -> None:
    assert len(ALLOWED) <= 10
    assert all(len(reason) > 20 for reason in ALLOWED.values())


def _text(command: DocCommand, case: Case | None, substitute: dict[str, str]) -> str:
    text = command.text
    for old, new in {**substitute, **(case.substitute if case else {})}.items():
        text = text.replace(old, new)
    return text


@pytest.mark.parametrize("key", sorted(BY_KEY))
def test_every_documented_command_parses(key: str) -> None:
    command = BY_KEY[key]
    case = FAST.get(key) or SLOW.get(key)
    problem = parse_check(_text(command, case, PARSE_SUBSTITUTE))
    assert problem is None, f"{command.doc}:{command.line}: {command.text}\n{problem}"


@pytest.mark.parametrize("command", inline_commands(), ids=lambda c: f"{c.doc}:{c.line}: {c.text}")
def test_every_command_in_the_prose_parses(command: DocCommand) -> None:
    problem = parse_check_mention(command.text)
    assert problem is None, f"{command.doc}:{command.line}: {command.text}\n{problem}"


def run_documented(key: str, tmp_path: Path, monkeypatch: pytest.MonkeyPatch, case: Case) -> None:
    """Run the command ``key`` in ``tmp_path`` after making the files it reads; compare with the shown."""
    command = BY_KEY[key]
    monkeypatch.chdir(tmp_path)
    for name in case.needs:
        MAKERS[name](tmp_path)
        forget_shared()
    status, printed = run(_text(command, case, {}))
    where = f"{command.doc}:{command.line}: {command.text}"
    if command.shown is not None:
        assert matches(command.output, printed), (
            f"{where}\nshown:\n" + "\n".join(command.output) + ("\nprinted:\n" + "\n".join(printed))
        )
    assert command.shown is not None or not any("deprecated" in ln for ln in printed), (where, printed)
    expected = command.expected_status
    if expected is not None:
        assert status == expected, (where, status, printed)
    elif command.shows_error:
        assert status != 0, (where, printed)
    else:
        assert status == 0, (where, status, printed)
    if case.wrote:
        case.wrote(tmp_path)


@pytest.mark.parametrize("key", sorted(FAST))
def test_the_documented_command_prints_what_is_shown(key: str, tmp_path: Path, monkeypatch) -> None:
    run_documented(key, tmp_path, monkeypatch, FAST[key])


def test_a_flag_that_no_longer_exists_fails_the_parse() -> None:
    assert parse_check("tactdeform-hw timing --electrodes 32 --pulse-width-us 200") is None
    assert "unrecognized arguments: --pulse-widthness" in (
        parse_check("tactdeform-hw timing --electrodes 32 --pulse-widthness 200") or ""
    )
    assert "unrecognized arguments: --no-such" in (parse_check("python tools/scene_cost.py --no-such") or "")
    assert "no option --etactile-nothing" in (parse_check("pytest t.py --etactile-nothing x") or "")
    assert "no extra" in (parse_check("pip install -e '.[nothing]'") or "")
    assert parse_check_mention("tactdeform-hw decode") is None  # a command named, its input left out
    assert "unrecognized arguments: --nothing" in (
        parse_check_mention("tactdeform-hw decode --nothing") or ""
    )


def test_the_output_convention() -> None:
    assert matches(["a ~1.5 b", "...", "end …"], ["a 27 b", "x", "y", "end /tmp/z"])
    assert matches(["...", "last"], ["last"])
    assert matches(["idle   ~0.5 ms     ~625"], ["idle    0.155 ms  12345"])
    assert not matches(["idle   ~0.5 ms"], ["idle 0.155  ms"])
    assert not matches(["a ~1.5 b"], ["a x b"])
    assert not matches(["exact"], ["exact", "more"])
    assert not matches(["a 1.5 b"], ["a 1.6 b"])
