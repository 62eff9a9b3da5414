"""Shared test fixtures and options."""

from __future__ import annotations

from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
SHARED = (REPO / ".." / "shared").resolve()
DATA = Path(__file__).resolve().parent / "data"


def pytest_addoption(parser: pytest.Parser) -> None:
    parser.addoption(
        "--device",
        action="store",
        default=None,
        help="conformance target: etactile:// (emulator, default), a serial path such as /dev/ttyACM0, "
        "or usb:303a:1001 for a real board",
    )


def shared_path(*parts: str) -> Path:
    """A file under ../shared/, or skip the test with the reason when it is absent."""
    path = SHARED.joinpath(*parts)
    if not path.exists():
        pytest.skip(f"{path} is not available (the shared reference data sits beside the repository in CI)")
    return path


@pytest.fixture
def shared() -> type:
    """Access to ../shared/ files: ``shared.path("meshes", "stanford_bunny.obj")`` (skips when absent)."""

    class _Shared:
        path = staticmethod(shared_path)

    return _Shared
