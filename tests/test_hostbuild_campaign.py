"""The safety campaign's sessions on a host build (``tools/safety_campaign.py --firmware-src``), judged on
the pulses the firmware's own code delivered."""

from __future__ import annotations

import os
import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tools"))
import safety_campaign as sc  # noqa: E402

TINY = Path(__file__).parent / "data" / "firmware_tiny"


def _v1_2_tree() -> Path:
    raw = os.environ.get("TACTDEFORM_HW_UPSTREAM_V1_2")
    if not raw or not (Path(raw) / "src").is_dir():
        pytest.skip("set TACTDEFORM_HW_UPSTREAM_V1_2 to the v1.2 PlatformIO tree (platform_io_project)")
    return Path(raw)


def test_a_tree_that_declares_another_version_is_refused(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as stop:
        sc.main(["--firmware-src", str(TINY), "--sessions", "1", "--jobs", "1"])
    assert stop.value.code == 2
    err = capsys.readouterr().err
    assert "--firmware-src" in err and "declares firmware 'none'" in err and "'v1.2'" in err
    assert sc.FIRMWARE_SRC is None


def test_a_session_runs_on_the_host_build(monkeypatch: pytest.MonkeyPatch) -> None:
    """Session 0 of seed 100 on upstream v1.2: the driver's calls run on the built firmware and every
    delivered pulse is within its limits; the only defect such a session can meet is v1.2's torn pattern,
    which the host build records from the heights its scans ran on."""
    monkeypatch.setattr(sc, "FIRMWARE_SRC", str(_v1_2_tree()))
    res = sc.run_session(0, 100)
    assert res.errors == []
    assert res.pulses > 0
    assert res.over_limit == 0 and res.meant_off == 0 and res.lost_bytes == 0
    assert set(res.defect_counts) <= {"torn_pattern"}


def test_a_fault_session_runs_on_the_host_build(monkeypatch: pytest.MonkeyPatch) -> None:
    """``--faults`` on upstream v1.2: session 7 of seed 3 resets the board, hangs its main loop
    (``stop_reading``: the firmware's reads find nothing until the next power-up) and cuts the link; the
    fail-safe recovers and nothing delivered breaks a limit."""
    monkeypatch.setattr(sc, "FIRMWARE_SRC", str(_v1_2_tree()))
    res = sc.run_session(7, 3, True)
    assert {"reset", "stop_reading", "cut"} <= set(res.faults)
    assert "driver_crash" not in res.hazards
    assert res.pulses > 0
    assert res.over_limit == 0 and res.meant_off == 0
    assert res.ok
