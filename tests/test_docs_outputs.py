"""The documentation's example outputs are what the commands print: each example is run here and its
lines compared (a run's timing, ``median … µs per pose``, aside)."""

from __future__ import annotations

import re
import shlex
from pathlib import Path

import pytest

from tactdeform_hw.cli import main
from tactdeform_hw.emulator.serving.urlhandler.protocol_etactile import forget_shared

ROOT = Path(__file__).resolve().parents[1]
_TIMING = re.compile(r"median [0-9.]+ µs per pose")


@pytest.fixture(autouse=True)
def _fresh_emulators():
    forget_shared()
    yield
    forget_shared()


def example(doc: str, command: str) -> list[str]:
    """The lines a document shows after ``$ command``, up to the next command or the end of the block."""
    lines = (ROOT / doc).read_text(encoding="utf-8").splitlines()
    start = lines.index(f"$ {command}")
    out = []
    for line in lines[start + 1 :]:
        if line.startswith("$ ") or line.startswith("```"):
            break
        out.append(line)
    return out


def console(argv: list[str], capsys: pytest.CaptureFixture[str]) -> list[str]:
    main(argv)
    captured = capsys.readouterr()
    return [ln for ln in (captured.err + captured.out).splitlines() if ln.strip()]


def same(shown: list[str], printed: list[str]) -> None:
    assert [_TIMING.sub("median µs per pose", ln) for ln in shown] == [
        _TIMING.sub("median µs per pose", ln) for ln in printed
    ]


def _p07(tmp_path: Path) -> Path:
    """The guide's P07.toml, as the guide prints it."""
    text = (ROOT / "docs" / "researcher-guide.md").read_text(encoding="utf-8")
    body = text.split("```toml\n# P07.toml\n", 1)[1].split("```", 1)[0]
    path = tmp_path / "P07.toml"
    path.write_text(body)
    return path


def test_the_readme_render_line_and_its_strip(tmp_path, capsys, monkeypatch) -> None:
    pytest.importorskip("matplotlib")
    from PIL import Image

    monkeypatch.chdir(tmp_path)
    command = (
        "tactdeform-hw render --scene cube --trajectory approach-face --frames face.jsonl --gif face.gif "
        "--strip face.png"
    )
    printed = console(shlex.split(command)[1:], capsys)
    same(example("README.md", command), [ln for ln in printed if not ln.startswith("render: ")])
    shown = Image.open(ROOT / "docs" / "figures" / "face-approach-strip.png")
    assert shown.size == Image.open(tmp_path / "face.png").size  # as many frames side by side


def test_the_guides_participant_examples(tmp_path, capsys, monkeypatch) -> None:
    monkeypatch.chdir(tmp_path)
    _p07(tmp_path)
    for command in (
        "tactdeform-hw render --scene task1 --trajectory approach-face --participant P07.toml --quiet",
        "tactdeform-hw render --scene task1 --trajectory approach-face --participant P07.toml "
        "--current-ua 2000",
        "tactdeform-hw render --scene cube --trajectory approach-face --frames frames.jsonl",
    ):
        same(example("docs/researcher-guide.md", command), console(shlex.split(command)[1:], capsys))


def test_the_safety_guides_lowering_example(tmp_path, capsys, monkeypatch) -> None:
    monkeypatch.chdir(tmp_path)
    _p07(tmp_path)
    shown_command = (
        "tactdeform-hw send --participant P07.toml --current-ua 1600 --pattern <the 4 centre electrodes> "
        "--hold-ms 100"
    )
    centre = ",".join("1" if i in (12, 13, 18, 19) else "0" for i in range(32))
    argv = shlex.split(shown_command.replace("<the 4 centre electrodes>", centre))[1:]
    same(example("docs/safety.md", shown_command), console(argv, capsys))


def test_the_v2_timing_examples_use_the_current_flags(capsys) -> None:
    text = (ROOT / "docs" / "firmware-v2.md").read_text(encoding="utf-8")
    commands = [ln for ln in text.splitlines() if ln.startswith("tactdeform-hw timing ")]
    assert len(commands) == 2
    for command in commands:
        assert main(shlex.split(command)[1:]) == 0
        err = capsys.readouterr().err
        assert "deprecated" not in err, (command, err)


def test_the_firmware_guides_set_errors(capsys) -> None:
    for command in ("tactdeform-hw timing --set nosuch=1", "tactdeform-hw timing --set gpio_write_us=-1"):
        same(example("docs/firmware-guide.md", command), console(shlex.split(command)[1:], capsys))
