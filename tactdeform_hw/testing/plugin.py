"""The pytest plugin (entry point ``etactile`` in the group ``pytest11``): a program's own test suite gets
a timed emulated eTactileKit board without a line of set-up.

* fixture ``etactile_board``: an :class:`~tactdeform_hw.testing.board.EmulatedBoard` — by default the
  emulator's defaults (firmware v1.2, the compact board, one switching board) on a pseudo-terminal;
  stopped after the test.
* marker ``@pytest.mark.etactile_board(firmware="v2", transport="tcp", board=..., switching_boards=...)``
  chooses the board (transport ``url``, ``pty``, ``tcp`` or ``usb``); so does indirect parametrization
  (``@pytest.mark.parametrize("etactile_board", [{"firmware": "v2"}], indirect=True)``; the parameter's
  keys win over the marker's).
* option ``--etactile-device NAME``: the device the conformance checks run against — a test module that
  star-imports :mod:`tactdeform_hw.testing.conformance.checks_v1_2` (or ``checks_v2``) runs them on it, or
  on every emulated target when none is named; the ``etactile_device`` fixture reads it.
"""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

import pytest

from tactdeform_hw.testing.board import BOARD_OPTIONS, EmulatedBoard

# the conformance checks a project star-imports report their failures with pytest's assertion rewriting
pytest.register_assert_rewrite("tactdeform_hw.testing.conformance")

MARKER = "etactile_board"


def pytest_addoption(parser: pytest.Parser) -> None:
    group = parser.getgroup("etactile", "eTactileKit emulated board")
    group.addoption(
        "--etactile-device",
        default=None,
        metavar="NAME",
        help="the device the eTactileKit conformance checks run against: etactile://[?options], pty, tcp, "
        "usb-emulator (with ?firmware=v2) or a real board's port (/dev/ttyACM0, COM3, usb:303a:1001)",
    )


def pytest_configure(config: pytest.Config) -> None:
    config.addinivalue_line(
        "markers",
        f"{MARKER}(firmware='v1.2', transport='pty', board='compact', switching_boards=1): the emulated "
        "eTactileKit board the etactile_board fixture serves (transport: url, pty, tcp or usb)",
    )


def board_options(request: pytest.FixtureRequest) -> dict[str, Any]:
    """The board a test asked for: the marker's keywords, then an indirect parameter's keys; an unknown
    one is a usage error naming it."""
    opts: dict[str, Any] = {}
    marker = request.node.get_closest_marker(MARKER)
    if marker is not None:
        if marker.args:
            raise pytest.UsageError(f"@pytest.mark.{MARKER} takes keywords only ({', '.join(BOARD_OPTIONS)})")
        opts.update(marker.kwargs)
    param = getattr(request, "param", None)
    if param is not None:
        if not isinstance(param, dict):
            raise pytest.UsageError(
                f"the indirect parameter of etactile_board must be a dict of {', '.join(BOARD_OPTIONS)}, "
                f"not {param!r}"
            )
        opts.update(param)
    unknown = sorted(set(opts) - set(BOARD_OPTIONS))
    if unknown:
        raise pytest.UsageError(
            f"etactile_board: unknown option(s) {unknown}; use {', '.join(BOARD_OPTIONS)}"
        )
    return opts


def pytest_terminal_summary(terminalreporter: Any, exitstatus: int, config: pytest.Config) -> None:
    """The conformance report, when conformance checks ran and measured figures."""
    from tactdeform_hw.testing.conformance.targets import write_report

    write_report(terminalreporter)


@pytest.fixture
def etactile_board(request: pytest.FixtureRequest) -> Iterator[EmulatedBoard]:
    """A timed emulated board for this test (see the module documentation)."""
    board = EmulatedBoard(**board_options(request))
    try:
        yield board
    finally:
        board.close()


@pytest.fixture
def etactile_device(request: pytest.FixtureRequest) -> str | None:
    """The ``--etactile-device`` given on the command line (None when none was)."""
    value: str | None = request.config.getoption("--etactile-device")
    return value
