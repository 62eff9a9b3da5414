"""Running a ``tactdeform-hw`` command in this process, as the command-line tests do."""

from __future__ import annotations

import pytest

from tactdeform_hw.cli import main


def run(argv: list[str], capsys: pytest.CaptureFixture[str]) -> tuple[int, str, str]:
    """The exit status of ``tactdeform-hw ARGV`` and what it printed on stdout and on stderr."""
    code = main(argv)
    out = capsys.readouterr()
    return code, out.out, out.err
