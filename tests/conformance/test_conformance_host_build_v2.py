"""The v2 conformance checks and the upstream-style host's vector replay on the upstream v2 firmware's own
code, built on this machine and served in real time by the pyserial URL handler
(``etactile://?firmware_src=DIR``; ``TACTDEFORM_HW_UPSTREAM_V2``, skipped without it).  The 2 s command
timeout check runs on ``TIMEOUT_TARGET`` only in a default run, as in ``test_conformance_v2.py``."""

from __future__ import annotations

from typing import Any

import pytest

from tactdeform_hw.testing.conformance.checks_v2 import *  # noqa: F403 - the checks and their fixtures
from tactdeform_hw.testing.conformance.targets import chosen_device, target_params

from .host_build_targets import V2_ENV, host_build_target
from .test_conformance_v2 import UPSTREAM_VECTORS
from .test_conformance_v2 import test_v2_upstream_host_in_8_byte_chunks_reaches_the_vectors_state as replay


@pytest.mark.parametrize("vector_id", UPSTREAM_VECTORS)
def test_v2_upstream_host_in_8_byte_chunks_reaches_the_vectors_state(v2_target: Any, vector_id: str) -> None:
    """The upstream-style host's replay (``test_conformance_v2.py``) on the host build."""
    replay(v2_target, vector_id)


def pytest_generate_tests(metafunc: pytest.Metafunc) -> None:
    if "v2_target_name" in metafunc.fixturenames:
        chosen = chosen_device(metafunc.config)
        params = target_params(metafunc.config, "v2", ()) if chosen else [host_build_target(V2_ENV)]
        metafunc.parametrize("v2_target_name", params)
