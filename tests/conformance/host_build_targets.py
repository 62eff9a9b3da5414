"""The upstream firmware trees built on this machine as conformance targets (``etactile://?firmware_src=``),
from ``TACTDEFORM_HW_UPSTREAM_V1_2`` / ``TACTDEFORM_HW_UPSTREAM_V2``; skipped with the reason when unset."""

from __future__ import annotations

import os
import urllib.parse as urlparse
from typing import Any

import pytest

from tactdeform_hw.emulator.hostbuild import find_compiler
from tactdeform_hw.errors import FirmwareBuildError

V1_2_ENV = "TACTDEFORM_HW_UPSTREAM_V1_2"
V2_ENV = "TACTDEFORM_HW_UPSTREAM_V2"


def host_build_target(env: str) -> Any:
    """The target serving the tree ``env`` names, or a skipped parameter saying what is missing."""
    raw = os.environ.get(env)
    why = None
    if not raw:
        why = f"set {env} to the upstream PlatformIO tree (platform_io_project)"
    else:
        try:
            find_compiler()
        except FirmwareBuildError as exc:
            why = str(exc)
    if why is not None:
        return pytest.param("", id=f"host-build-{env}", marks=pytest.mark.skip(reason=why))
    name = f"etactile://?firmware_src={urlparse.quote(str(raw))}"
    return pytest.param(name, id=f"host-build-{env}")
