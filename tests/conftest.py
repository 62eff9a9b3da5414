"""Shared test fixtures and options."""

from __future__ import annotations

from collections.abc import Iterator
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
def fresh_emulators() -> Iterator[None]:
    """No named in-process board (``etactile://NAME``) left by another test, and none left to the next:
    a test that proves a command opened no port looks for the board by its name."""
    from tactdeform_hw.emulator.serving.urlhandler.protocol_etactile import forget_shared

    forget_shared()
    yield
    forget_shared()


@pytest.fixture
def shared() -> type:
    """Access to ../shared/ files: ``shared.path("meshes", "stanford_bunny.obj")`` (skips when absent)."""

    class _Shared:
        path = staticmethod(shared_path)

    return _Shared


#: What ``-m slow`` selects (and the README's test command leaves to CI's own step): the tests that run on
#: the wall clock — real-time boards behind a pty, TCP or USB, owners and guardians in processes of their
#: own, stop signals — the campaign runs, the tools run end to end, and the benchmarks.
SLOW = frozenset(
    {
        "benchmarks",
        "conformance",
        "test_byte_fault_campaign_run.py",
        "test_docs_commands_slow.py",
        "test_campaign_cluster.py",
        "test_hostbuild_campaign.py",
        "test_hostbuild_timed.py",
        "test_identification_seams.py",
        "test_live_lsl.py",
        "test_live_tools.py",
        "test_safety_campaign.py",
        "test_safety_failsafe.py",
        "test_safety_lock.py",
        "test_safety_pty_timed.py",
        "test_safety_stop.py",
        "test_safety_tcp_guardian.py",
        "test_tools.py",
        "test_usb_served.py",
        "test_usb_transport.py",
        "test_v2_safety_campaign.py",
        "test_virtual_serial.py",
        "test_wifi_board.py",
    }
)


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    """Mark :data:`SLOW` (and take tests marked ``slow`` one by one); leave them out of a run given
    neither paths nor ``-m`` (the README's test command), so that naming a file or folder (``pytest
    tests/conformance --device …``) or ``-m slow`` runs them."""
    tests = REPO / "tests"
    slow: list[pytest.Item] = []
    for item in items:
        if item.get_closest_marker("slow") is not None:  # one slow test in a fast file
            slow.append(item)
            continue
        try:
            first = Path(str(item.fspath)).resolve().relative_to(tests).parts[0]
        except ValueError:
            continue
        if first in SLOW:
            item.add_marker(pytest.mark.slow)
            slow.append(item)
    chosen = config.option.markexpr or config.args_source is not pytest.Config.ArgsSource.TESTPATHS
    if slow and not chosen:
        config.hook.pytest_deselected(items=slow)
        left = set(map(id, slow))
        items[:] = [item for item in items if id(item) not in left]
