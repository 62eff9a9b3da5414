"""The exhaustive byte-fault campaign end to end on its command line (``safety_campaign.py --exhaustive
--depth 0 --byte-faults``, v1.2: 524 runs, about 10 s of one core): the count printed before the runs, every
run judged, none failed on the driver as it is; and ``--help`` says what it enumerates."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tools"))
import safety_campaign as sc  # noqa: E402


def test_depth_0_on_v12_prints_its_count_and_passes(capsys: pytest.CaptureFixture[str]) -> None:
    argv = ["--exhaustive", "--depth", "0", "--firmware", "v1.2", "--byte-faults", "--jobs", "1", "--json"]
    assert sc.main(argv) == 0
    out = capsys.readouterr()
    assert "524 faulty runs = 3 x 131 UART bytes (lost, duplicated, corrupted) + 131 USB bytes" in out.err
    s = json.loads(out.out)
    assert s["faulty_runs"] == 524 and s["failed_runs"] == 0 and s["sequences"] == 3
    assert s["runs_by_link_and_kind"] == {
        "uart lose": 131,
        "uart duplicate": 131,
        "uart corrupt": 131,
        "usb tail_loss": 131,
    }
    assert s["wrong_deliveries_past_bound"] == 0 and s["bytes_lost_unreported"] == 0
    assert s["pulses"] > 0 and s["largest_pulse_ua"] > 0


def test_the_help_says_what_is_enumerated(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit):
        sc.main(["--help"])
    text = " ".join(capsys.readouterr().out.split())
    assert "each byte lost, duplicated and corrupted (XOR 0xFF)" in text
    assert "3 x (UART bytes) + (USB bytes) runs" in text
