"""``tactdeform-hw timing --firmware v2``: v2's budget, modes, every value v2 holds, the scan options."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from tactdeform_hw.cli import timing
from tactdeform_hw.errors import LimitError

from .test_timing_cli import TACTDEFORM, run_cli


def _json(argv: list[str], capsys: pytest.CaptureFixture[str], status: int = 0) -> dict:
    code, out, _ = run_cli([*argv, "--json"], capsys)
    assert code == status
    return json.loads(out)


def test_tactdeform_setting_on_both_versions(capsys: pytest.CaptureFixture[str]) -> None:
    """v2's discharge has no exchange: 6.6 µs per channel shorter, 32 channels."""
    v12 = _json([*TACTDEFORM, "--discharge", "45"], capsys)
    v2 = _json([*TACTDEFORM, "--discharge", "45", "--firmware", "v2", "--pattern", "100"], capsys)
    assert v12["scan_us"] == 7850.25 and v2["scan_us"] == 7639.05
    assert round((v12["scan_us"] - v2["scan_us"]) / 32, 3) == 6.6
    costed = _json([*TACTDEFORM, "--discharge", "45", "--firmware", "v2", "--cs-writes", "costed"], capsys)
    assert costed["scan_us"] == 7645.45
    assert _json([*TACTDEFORM, "--discharge", "45", "--cs-writes", "costed"], capsys)["scan_us"] == 7869.45


def test_discharge_50_fits_on_v2(capsys: pytest.CaptureFixture[str]) -> None:
    d = _json([*TACTDEFORM, "--discharge", "50", "--firmware", "v2"], capsys)
    assert d["verdict"] == "fits" and d["margin_us"] > 0


def test_modes_and_per_electrode_codes(capsys: pytest.CaptureFixture[str]) -> None:
    mono = _json(["--firmware", "v2", "--pattern", "100,200,0,4095", "--discharge", "45"], capsys)
    bi = _json(
        ["--firmware", "v2", "--mode", "1", "--pattern", "100,200,0,4095", "--discharge", "45"], capsys
    )
    imp = _json(
        [
            "--firmware",
            "v2",
            "--mode",
            "2",
            "--pattern",
            "0,0,0,0",
            "--sense-height",
            "10",
            "--sense-width",
            "10",
            "--discharge",
            "45",
        ],
        capsys,
    )
    assert mono["scan_us"] == 959.65  # the golden trace (960.45) less 2 exchanges x 2 CS writes x 4 channels
    assert bi["scan_us"] > mono["scan_us"] and imp["electrodes"] == 4
    assert any("zero pattern does not stop current" in n for n in imp["notes"])


def test_every_value_v2_holds_is_accepted(capsys: pytest.CaptureFixture[str]) -> None:
    d = _json(
        [
            "--firmware",
            "v2",
            "--pulse-width",
            "0",
            "--pattern",
            "4095",
            "--electrodes",
            "255",
            "--sense-height",
            "255",
            "--discharge",
            "255",
            "--frequency",
            "65535",
        ],
        capsys,
        status=timing.EXIT_OVERRUN,  # accepted, and its verdict in the exit status
    )
    assert d["effective_width_us"] == 6.6 and d["electrodes"] == 255 and d["verdict"] == "overrun"
    assert any("one SPI exchange" in n for n in d["notes"])
    assert _json(["--firmware", "v2", "--electrodes", "0"], capsys)["electrodes"] == 0


@pytest.mark.parametrize(
    ("argv", "match"),
    [
        (["--pattern", "1,4096"], r"--pattern\[1\]=4096.*0 to 4095"),
        (["--mode", "3"], r"--mode=3.*0 to 2"),
        (["--pattern", "1,2,3", "--electrodes", "4"], "exactly --electrodes = 4"),
        (["--pulse-width-us", "65536"], "--pulse-width-us=65536"),
        (["--pattern", "a"], "--pattern"),
    ],
)
def test_bad_v2_values_name_the_flag(argv: list[str], match: str, capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(LimitError, match=match):
        run_cli(["--firmware", "v2", *argv], capsys)


def test_mode_is_refused_on_v12(capsys: pytest.CaptureFixture[str]) -> None:
    from tactdeform_hw.errors import ConfigurationError

    for readings in ([], ["--cs-writes", "costed"], ["--dac-load", "cs_rise"]):
        with pytest.raises(ConfigurationError, match="--mode 1: v1.2 has no stimulation mode"):
            run_cli(["--mode", "1", *readings], capsys)


def test_events_of_a_v2_scan(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    path = tmp_path / "v2.json"
    code, out, _ = run_cli(
        ["--firmware", "v2", "--pattern", "100,0", "--cs-writes", "costed", "--events", str(path)], capsys
    )
    assert code == 0 and f"wrote {path}" in out
    events = json.loads(path.read_text())
    assert [e["value"] for e in events if e["kind"] == "dac"] == [100, 0, 0, 0]
    assert any(e["name"] == "GPIO44" for e in events)
