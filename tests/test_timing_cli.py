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
def test_json_has_the_required_keys(
    discharge: int, overrun: bool, capsys: pytest.CaptureFixture[str]
) -> None:
    code, out, _ = run_cli([*TACTDEFORM, "--discharge", str(discharge), "--json"], capsys)
    d = json.loads(out)
    assert code == (timing.EXIT_OVERRUN if overrun else 0)
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
    code, out, _ = run_cli(
        ["--pattern", "1,2,0,1", "--vcd", str(vcd), "--events", str(ev), "--cycles", "3"], capsys
    )
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
    # 9 GPIO writes a channel, 5 in the clear
    assert d["model"]["gpio_write_us"] == 0.1 and d["scan_us"] == pytest.approx(7850.25 + (32 * 9 + 5) * 0.05)
    _, out, _ = run_cli(["--list-model"], capsys)
    assert "spi_exchange_us" in out and "assumption" in out and "firmware comment" in out


def test_list_model_says_which_chip_select_reading_is_default(capsys: pytest.CaptureFixture[str]) -> None:
    rows = {r["name"]: r for r in json.loads(run_cli(["--list-model", "--json"], capsys)[1])}
    assert (
        rows["chip_select_writes"]["value"] == "inside"
        and "default inside" in rows["chip_select_writes"]["doc"]
    )
    assert rows["dac_load"]["value"] == "mid_exchange"
    _, out, _ = run_cli(["--list-model", "--cs-writes", "costed"], capsys)
    assert "chip_select_writes" in out and "costed" in out


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


def test_latency_on_a_starved_main_loop_still_reports_the_wire(capsys: pytest.CaptureFixture[str]) -> None:
    # discharge 50: the scans run back to back, the parser never reads the pattern — but its bytes arrive
    code, out, _ = run_cli([*TACTDEFORM, "--discharge", "50", "--latency", "--phases", "3", "--json"], capsys)
    assert code == timing.EXIT_OVERRUN
    lat = json.loads(out)["latency"]
    assert lat["uart"]["wire_us"]["min"] == pytest.approx(33 * 10 * 1e6 / 921600, abs=0.01)
    assert 0 < lat["usb"]["wire_us"]["min"] <= lat["usb"]["wire_us"]["max"] <= 1000 + 60
    for link in ("usb", "uart"):
        assert lat[link]["felt"] == 0
        for key in ("loop_wait_us", "scan_wait_us", "first_channel_us", "last_channel_us"):
            assert lat[link][key] == {"min": None, "mean": None, "max": None}
    code, out, _ = run_cli([*TACTDEFORM, "--discharge", "50", "--latency", "--phases", "3"], capsys)
    lines = out.splitlines()
    head = next(i for i, line in enumerate(lines) if line.startswith("link "))
    rows = [line.split() for line in lines[head + 1 : head + 11]]
    wire = [r for r in rows if "wire" in r]
    assert len(wire) == 2 and all(r[-1] != "never" and float(r[-1]) > 0 for r in wire), wire
    assert sum(r[-1] == "never" for r in rows) == 8  # loop tick, scan wait, first and last channel, per link


def test_events_with_an_unknown_suffix_names_the_option_and_the_suffixes(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    from tactdeform_hw.cli import main

    vcd, ev = tmp_path / "s.vcd", tmp_path / "ev.txt"
    assert main(["timing", "--vcd", str(vcd), "--events", str(ev)]) == 1
    err = capsys.readouterr().err
    assert "out of range" not in err
    assert f"--events {str(ev)!r}: unknown file suffix '.txt'; use .csv or .json" in err, err
    assert not vcd.exists() and not ev.exists()  # refused before any trace was started
    assert main(["timing", "--events", str(tmp_path / "noext")]) == 1
    assert "unknown file suffix ''; use .csv or .json" in capsys.readouterr().err


def test_output_into_a_closed_pipe_ends_quietly() -> None:
    """``tactdeform-hw timing --json | head -3``: the reader goes away; no traceback, exit status 141."""
    import os
    import subprocess
    import sys

    from tactdeform_hw.cli import EXIT_BROKEN_PIPE

    read_fd, write_fd = os.pipe()
    os.close(read_fd)  # the reader is gone before the command writes a byte
    try:
        proc = subprocess.run(
            [sys.executable, "-m", "tactdeform_hw.cli", "timing", "--json"],
            stdout=write_fd,
            stderr=subprocess.PIPE,
            text=True,
            timeout=120,
            cwd=Path(__file__).resolve().parents[1],
        )
    finally:
        os.close(write_fd)
    assert proc.stderr == ""
    assert proc.returncode == EXIT_BROKEN_PIPE == 141


@pytest.mark.parametrize(
    "engine",
    [["--firmware", "v2"], ["--cs-writes", "costed"], ["--dac-load", "cs_rise"]],
    ids=["v2", "v1.2-cs-writes", "v1.2-dac-load"],
)
@pytest.mark.parametrize("json_out", [False, True], ids=["table", "json"])
def test_every_scan_engine_exits_with_its_verdict(
    engine: list[str], json_out: bool, capsys: pytest.CaptureFixture[str]
) -> None:
    """The exit status the help promises (0 fits, 3 overrun, 4 watchdog) on the paths that print the
    firmware's scan-log budget, as on the default one: a script can branch on it."""
    extra = ["--json"] if json_out else []
    cases = [
        (["--electrodes", "32", "--pulse-width", "200", "--frequency", "100"], 0, "fits"),
        (
            ["--electrodes", "32", "--pulse-width", "200", "--frequency", "250"],
            timing.EXIT_OVERRUN,
            "overrun",
        ),
        (
            ["--electrodes", "255", "--pulse-width", "60000", "--frequency", "1"],
            timing.EXIT_WATCHDOG,
            "watchdog",
        ),
    ]
    for argv, status, verdict in cases:
        code, out, _ = run_cli([*argv, *engine, *extra], capsys)
        assert code == status, (argv, out[-300:])
        assert verdict in (json.loads(out)["verdict"] if json_out else out.lower())
