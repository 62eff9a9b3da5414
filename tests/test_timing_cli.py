"""``tactdeform-hw timing``: the budget table, ``--json``, traces, latency, model overrides, bad input."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import pytest

from tactdeform_hw.cli import timing


def run_cli(argv: list[str], capsys: pytest.CaptureFixture[str]) -> tuple[int, str, str]:
    parser = argparse.ArgumentParser(prog="tactdeform-hw")
    sub = parser.add_subparsers(dest="command")
    timing.register(sub)
    args = parser.parse_args(["timing", *argv])
    code = args.func(args)
    out = capsys.readouterr()
    return code, out.out, out.err


TACTDEFORM = ["--electrodes", "32", "--pulse-width", "200", "--frequency", "125"]


def test_budget_table_for_the_tactdeform_setting(capsys: pytest.CaptureFixture[str]) -> None:
    code, out, _ = run_cli([*TACTDEFORM, "--discharge", "45"], capsys)
    assert code == 0
    assert "monophasic (pattern 1)" in out and "245.25" in out
    assert "7850.25" in out and "8000.00" in out and "149.75" in out
    assert "verdict: FITS" in out


@pytest.mark.parametrize(("discharge", "overrun"), [(45, False), (50, True)])
def test_json_has_the_required_keys(discharge: int, overrun: bool, capsys: pytest.CaptureFixture[str]) -> None:
    code, out, _ = run_cli([*TACTDEFORM, "--discharge", str(discharge), "--json"], capsys)
    d = json.loads(out)
    assert code == 0
    assert d["overrun"] is overrun
    assert d["period_us"] == 8000.0
    assert d["scan_us"] == pytest.approx(7850.25 if not overrun else 8010.25)
    assert d["margin_us"] == pytest.approx(d["period_us"] - d["scan_us"])
    assert d["actual_rate_hz"] == pytest.approx(1e6 / max(d["scan_us"], d["period_us"]))
    assert d["verdict"] == ("overrun" if overrun else "fits")
    assert "gpio_write_us" in d["assumptions"]


def test_vcd_and_event_list(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    pytest.importorskip("vcd")
    vcd, ev = tmp_path / "s.vcd", tmp_path / "s.json"
    code, out, _ = run_cli(["--pattern", "1,2,0,1", "--vcd", str(vcd), "--events", str(ev), "--cycles", "3"], capsys)
    assert code == 0 and f"wrote {vcd}" in out
    events = json.loads(ev.read_text())
    le_rises = [e for e in events if e["name"] == "LE" and e["value"] == 1 and e["t_ns"] > 0]
    assert len(le_rises) == 3 * 5  # 4 channels + the clear, per scan
    assert "$var wire 12" in vcd.read_text()


def test_latency_section(capsys: pytest.CaptureFixture[str]) -> None:
    code, out, _ = run_cli(["--electrodes", "8", "--latency", "--phases", "3", "--json"], capsys)
    d = json.loads(out)
    for link in ("usb", "uart"):
        lat = d["latency"][link]
        assert lat["felt"] == 3 and lat["first_channel_us"]["min"] > 0


def test_model_overrides_and_listing(capsys: pytest.CaptureFixture[str]) -> None:
    _, out, _ = run_cli([*TACTDEFORM, "--set", "gpio_write_us=0.1", "--json"], capsys)
    d = json.loads(out)
    assert d["model"]["gpio_write_us"] == 0.1 and d["scan_us"] == pytest.approx(7850.25 + (32 * 9 + 5) * 0.05)  # 9 GPIO writes a channel, 5 in the clear
    _, out, _ = run_cli(["--list-model"], capsys)
    assert "spi_exchange_us" in out and "assumption" in out and "firmware comment" in out


def test_bad_input_names_field_value_and_limit(capsys: pytest.CaptureFixture[str]) -> None:
    from tactdeform_hw.errors import ConfigurationError, LimitError

    with pytest.raises(LimitError, match="pulse_width_us=70000"):
        run_cli(["--pulse-width", "70000"], capsys)
    with pytest.raises(LimitError, match="pattern length"):
        run_cli(["--electrodes", "3", "--pattern", "1,2"], capsys)
    with pytest.raises(ConfigurationError):
        run_cli(["--set", "nonsense=1"], capsys)


def test_registered_in_the_console_script() -> None:
    from tactdeform_hw.cli import COMMANDS, main

    assert "timing" in COMMANDS
    assert main(["timing", "--electrodes", "2", "--json"]) == 0
    assert main(["timing", "--frequency", "0"]) == 1  # a clear error, not a traceback
