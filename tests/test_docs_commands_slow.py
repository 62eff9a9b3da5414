"""The documented commands too slow for the fast suite (``tests/test_docs_commands.py`` lists them in
``SLOW``): real-time plays and studies, the tools that measure, and the real-time ``emulate`` servers.
Marked ``slow`` (``tests/conftest.py``): CI runs them as their own step."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from .conftest import SLOW as SLOW_FILES
from .doc_commands import argv_of, matches
from .test_docs_commands import BY_KEY, SLOW, Case, run_documented

#: Run in a process of their own: they serve until stopped.  The first lines they print (the port to
#: open, what is emulated) are compared; a fixed TCP port becomes a free one (``:0``), the shown one too.
SERVERS = sorted(key for key in SLOW if " emulate " in key)

#: The same command at a reduced size: what the shown figures vary by (``~``) is time, not the size.
REDUCED: dict[str, dict[str, str]] = {
    "docs/firmware-guide.md | python tools/realtime_lag.py": {
        "realtime_lag.py": "realtime_lag.py --idle 1 --stream 2"
    },
}

IN_PROCESS = sorted(
    key for key in SLOW if key not in SERVERS and "pip install" not in key and "pytest " not in key
)


@pytest.mark.parametrize("key", IN_PROCESS)
def test_the_documented_slow_command_prints_what_is_shown(key: str, tmp_path: Path, monkeypatch) -> None:
    case = SLOW[key]
    if key in REDUCED:
        case = Case(case.needs, {**case.substitute, **REDUCED[key]}, case.wrote)
    run_documented(key, tmp_path, monkeypatch, case)


def test_the_install_line_renders_once_installed(tmp_path: Path, monkeypatch) -> None:
    """The README's first line: the install is CI's own first step; the render after it is run here."""
    key = next(k for k in SLOW if "pip install ." in k)
    render = BY_KEY[key].text.split(" && ", 1)[1]
    monkeypatch.chdir(tmp_path)
    from .doc_commands import run

    status, printed = run(render)
    assert status == 0, printed
    assert (tmp_path / "frames.jsonl").stat().st_size > 0


def test_the_conformance_line_is_run_by_the_slow_step() -> None:
    assert any(k.endswith("pytest tests/conformance") for k in SLOW)
    assert "conformance" in SLOW_FILES


def _served_lines(argv: list[str], count: int, timeout_s: float = 20.0) -> list[str]:
    """The first ``count`` lines a server prints, then it is stopped (SIGTERM, its normal stop)."""
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    proc = subprocess.Popen(
        [sys.executable, "-m", "tactdeform_hw.cli", *argv],
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        env=env,
    )
    lines: list[str] = []
    deadline = time.monotonic() + timeout_s
    try:
        assert proc.stdout is not None
        while len(lines) < count and time.monotonic() < deadline:
            line = proc.stdout.readline()
            if not line:
                break
            lines.append(line.rstrip("\n"))
    finally:
        proc.send_signal(signal.SIGTERM)
        try:
            proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
    return lines


@pytest.mark.parametrize("key", SERVERS)
def test_the_documented_server_starts_as_shown(key: str) -> None:
    command = BY_KEY[key]
    text = command.text.replace("--tcp 8080", "--tcp 127.0.0.1:0").replace(
        "--discovery-port 18888", "--discovery-port 0"
    )
    if "--tcp" in text and "--firmware v2" in text and "--discovery-port" not in text:
        text += " --discovery-port 0"  # the shown 8888 may be taken on a test machine
    # what a session of a host program adds (status lines, hazards, a reset) is not reproduced here: the
    # lines up to the first status line are compared
    shown = [ln.replace("127.0.0.1:8080", "127.0.0.1:…") for ln in command.output]
    head = next((i for i, ln in enumerate(shown) if ln.startswith("t=")), len(shown))
    shown = shown[:head]
    printed = _served_lines(argv_of(text)[1:], max(len(shown), 1))
    assert printed, text
    if shown:
        assert matches(shown, printed), (command.doc, command.line, shown, printed)
