"""The conformance suite on this repository: every check of :mod:`tactdeform_hw.testing.conformance` on
the emulated targets (CI), or on the one ``--device`` names (a real board at the bench; see
:mod:`tactdeform_hw.testing.conformance.targets` for the names).  A downstream project runs the same checks
through the pytest plugin with ``--etactile-device`` (``docs/testing-downstream.md``).

The ``--device`` option itself is registered in ``tests/conftest.py`` (pytest accepts new options only
from the root conftest).  At the end of the run the terminal summary prints an "eTactileKit conformance
report" with the figures each check measured; ``--junitxml`` carries the same figures as test properties.
"""

from __future__ import annotations

from typing import Any

import pytest

pytest.register_assert_rewrite("tactdeform_hw.testing.conformance")

from tactdeform_hw.testing.conformance.targets import (  # noqa: E402 - after the rewrite is registered
    EMULATED_TARGETS,
    REPLY_TIMEOUT_S,
    V2_TARGETS,
    Target,
    build_target,
    name_firmware,
    write_report,
)

__all__ = ["EMULATED_TARGETS", "REPLY_TIMEOUT_S", "V2_TARGETS", "Target", "build_target", "name_firmware"]


def pytest_terminal_summary(terminalreporter: Any, exitstatus: int, config: pytest.Config) -> None:
    write_report(terminalreporter)
