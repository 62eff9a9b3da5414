"""The v1.2 conformance checks on the upstream v1.2 firmware's own code, built on this machine and served
in real time by the pyserial URL handler (``etactile://?firmware_src=DIR``): the checks cannot tell it from
the Python model (``TACTDEFORM_HW_UPSTREAM_V1_2``; skipped without it).  ``--device`` names one target for
the whole run instead, so this module then runs the checks on that target, like ``test_conformance.py``."""

from __future__ import annotations

import pytest

from tactdeform_hw.testing.conformance.checks_v1_2 import *  # noqa: F403 - the checks and their fixtures
from tactdeform_hw.testing.conformance.targets import chosen_device, target_params

from .host_build_targets import V1_2_ENV, host_build_target


def pytest_generate_tests(metafunc: pytest.Metafunc) -> None:
    if "target_name" in metafunc.fixturenames:
        chosen = chosen_device(metafunc.config)
        params = target_params(metafunc.config, "v1.2", ()) if chosen else [host_build_target(V1_2_ENV)]
        metafunc.parametrize("target_name", params)
