"""What ``emulate`` prints while it serves: fall-behinds aggregated, hazards at once, one clock."""

from __future__ import annotations

import argparse
import re
from pathlib import Path

import pytest

from tactdeform_hw.cli.emulate import _Notices, _spy
from tactdeform_hw.emulator.serving.notices import QUIET_LAG_LIMIT_US
from tactdeform_hw.emulator.serving.realtime import LiveView, RealtimeEmulator
from tactdeform_hw.protocol import commands as c

CONFIG = (
    c.encode_electrode_num(32)
    + c.encode_pulse_height(100)
    + c.encode_pulse_width(200)
    + c.encode_discharge(45)
    + c.encode_frequency(125)
)
DESYNC = b"\xfb\xfc\x08"  # a cut command: its payload takes the next command byte (a hazard)


class FakeClock:
    def __init__(self) -> None:
        self.t = 100.0

    def __call__(self) -> float:
        return self.t


def _args(**kw: object) -> argparse.Namespace:
    return argparse.Namespace(**{"quiet": False, "untimed": False, "trace": None, **kw})


def _late_wakeups(
    quiet: bool, count: int, seconds: float, lag_s: float
) -> tuple[list[str], RealtimeEmulator]:
    """``count`` wake-ups each ``lag_s`` late, spread over ``seconds`` of wall time, with the serving
    loop's look every 50 ms; the lines it printed."""
    clock = FakeClock()
    rt = RealtimeEmulator(clock=clock)
    notices = _Notices(_args(quiet=quiet))
    notices.view = None  # the fall-behind lines alone
    rt.on_behind = notices.behind.add
    rt.write(CONFIG)
    lines: list[str] = []
    polls = round(seconds / 0.05)
    for k in range(count):
        due = rt.timed.next_event_us()
        clock.t = rt.t0 + due / 1e6 + lag_s
        rt.catch_up()
        now = k * seconds / count
        if int(now / 0.05) != int((k + 1) * seconds / count / 0.05):
            lines += notices.lines(rt, now)
    lines += notices.lines(rt, polls * 0.05 + 1)
    return lines, rt


def _counted(lines: list[str]) -> int:
    """The late wake-ups the lines account for."""
    return sum(int(x.split(" times")[0].rsplit(" ", 1)[1]) if " times " in x else 1 for x in lines)


def test_fall_behinds_print_at_most_one_line_a_second_with_count_and_worst_lag() -> None:
    lines, rt = _late_wakeups(False, 347, 12.0, 0.003)
    assert rt.lag.behind_count == 347
    assert 1 <= len(lines) <= 14  # the first at once, then one a second, then the rest at the end
    assert all("fell behind the wall clock" in x for x in lines)
    assert _counted(lines) == 347
    assert all("3.00 ms" in x for x in lines)
    stamps = [m for x in lines for m in re.findall(r"t=[0-9.]+(\S*)", x)]
    assert stamps and set(stamps) <= {"us", "us)"}  # the board's µs, as everywhere


def test_quiet_prints_no_fall_behind_unless_it_exceeds_the_safety_bound() -> None:
    lines, rt = _late_wakeups(True, 44, 2.5, 0.003)
    assert lines == [] and rt.lag.behind_count == 44  # still counted for the summary
    lines, _ = _late_wakeups(True, 3, 2.5, (QUIET_LAG_LIMIT_US + 50_000) / 1e6)
    assert lines and _counted(lines) == 3
    assert all("150 ms stop bound" in x and "150.00 ms" in x for x in lines)


@pytest.mark.parametrize("quiet", [False, True])
def test_a_hazard_prints_at_once_and_repeats_are_rate_limited_by_kind(quiet: bool) -> None:
    clock = FakeClock()
    rt = RealtimeEmulator(clock=clock)
    notices = _Notices(_args(quiet=quiet))
    rt.write(CONFIG)
    clock.t += 0.05
    first = notices.lines(rt, 0.0)  # the live view, no hazard yet
    assert not any(x.startswith("hazard:") for x in first)
    rt.write(DESYNC)
    clock.t += 0.05
    lines = notices.lines(rt, 0.1)  # the next look, within the live view's second
    hazards = [x for x in lines if x.startswith("hazard:")]
    assert len(hazards) == 1 and "payload_holds_command_byte" in hazards[0]
    assert not any(x.startswith("  hazard:") for x in lines)  # not again in the view
    kinds_before = len(rt.hazards)
    for k in range(5):  # the same again, five times within the second: held back
        rt.write(DESYNC)
        clock.t += 0.05
        assert not [x for x in notices.lines(rt, 0.2 + k * 0.05) if "payload_holds_command_byte" in x]
    held = len(rt.hazards) - kinds_before
    assert held >= 5
    later = [x for x in notices.lines(rt, 1.2) if "payload_holds_command_byte" in x]
    assert len(later) == 1 and "more payload_holds_command_byte held back" in later[0]


def test_spy_view_and_trace_count_the_board_clock_and_say_so(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    pytest.importorskip("vcd")
    from tactdeform_hw.emulator.records.trace import TIME_BASE, VcdSink

    clock = FakeClock()
    rt = RealtimeEmulator(clock=clock)
    sink = VcdSink(tmp_path / "t.vcd")
    rt.timed.attach(sink)
    clock.t = rt.t0 + 2.5
    _spy(_args(), rt, [0.0])("host->dev", CONFIG[:2], clock.t)
    rt.write(CONFIG)
    lines = LiveView().poll(rt, 0.0)
    rt.timed.detach(sink)
    sink.close()
    spied = capsys.readouterr().err
    assert spied.startswith("t=2500000.0us host->dev ")
    assert lines[0].startswith("t=2500000us ")
    assert f"$comment {TIME_BASE} $end" in (tmp_path / "t.vcd").read_text()
    assert "since serving began" in TIME_BASE
