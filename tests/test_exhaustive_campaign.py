"""The bounded exhaustive mode (``safety_campaign.py --exhaustive``, ``tools/exhaustive_campaign.py``):
every sequence of the domain is enumerated once; a slice passes on the driver as it is, and fails when an
unsafe guard or a pattern that reaches electrodes meant off is planted — the mode can fail."""

from __future__ import annotations

import itertools
import sys
from pathlib import Path
from typing import Any

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tools"))
import campaign_engine as engine  # noqa: E402
import exhaustive_campaign as ex  # noqa: E402
import safety_campaign as sc  # noqa: E402

from tactdeform_hw.device.driver.base import LinkState  # noqa: E402
from tactdeform_hw.device.safety.guard import SafetyGuard  # noqa: E402

FW = ("v2",)


def slice_after(first_call: str, start: str = "stimulating", depth: int = 2) -> tuple[int, int]:
    """(first index, count) of the sequences of exactly ``depth`` calls from ``start`` on v2 whose first
    call is ``first_call``: a contiguous run of indices."""
    c = [call.name for call in ex.CALLS].index(first_call)
    per = ex.per_start(depth)
    shorter = ex.per_start(depth - 1)
    run = len(ex.CALLS) ** (depth - 1)
    first = list(ex.STARTS).index(start) * per + shorter + c * run
    return first, run


def run_slice(first_call: str, chunk: int = 7) -> dict[str, Any]:
    first, n = slice_after(first_call)
    c = [call.name for call in ex.CALLS].index(first_call)
    assert ex.decode(first, 2, FW)[2][0] == c and ex.decode(first + n - 1, 2, FW)[2][0] == c
    result: dict[str, Any] = engine.run(ex.job(2, FW, chunk, first=first, total=n), jobs=1).summary()
    return result


def test_every_sequence_is_enumerated_once() -> None:
    depth = 2
    seen = [ex.decode(i, depth, FW) for i in range(ex.count(depth, FW))]
    expected = {
        ("v2", start, calls)
        for start in ex.STARTS
        for n in range(depth + 1)
        for calls in itertools.product(range(len(ex.CALLS)), repeat=n)
    }
    assert len(seen) == len(set(seen)) == len(expected) and set(seen) == expected
    assert ex.count(3) == 2 * 3 * (1 + 19 + 19**2 + 19**3) == 43440
    with pytest.raises(IndexError, match="0 to 1142 at depth 2"):
        ex.decode(ex.count(depth, FW), depth, FW)


def test_the_domain_holds_its_edges() -> None:
    names = [c.name for c in ex.CALLS]
    assert {"configure(1)", "configure(32)", "configure(255)"} <= set(names)
    assert {"set_current(0)", "set_current(cap)", "set_current(cap+step)"} <= set(names)
    assert {"send_pattern(even mono)", "send_pattern(even biphasic)", "send_pattern(off)"} <= set(names)
    assert {"wait(scan)", "wait(watchdog)", "close+reopen", "hardware_reset"} <= set(names)
    assert ex.ABOVE_CAP_UA == ex.CAP_UA + 10  # one DAC step
    assert set(ex.STARTS.values()) == {LinkState.IN_STEP, LinkState.SUSPECT}


def test_a_slice_passes_and_the_step_above_the_cap_is_refused() -> None:
    s = run_slice("set_current(cap+step)")
    assert s["sequences"] == 19 and s["failed_sequences"] == 0
    assert s["pulses"] > 0 and s["largest_pulse_ua"] <= ex.CAP_UA
    assert s["refused_calls"] >= 19  # the step above the cap, in every sequence of the slice


def test_a_limit_raised_behind_the_guards_check_fails_the_slice(monkeypatch: pytest.MonkeyPatch) -> None:
    def raised() -> SafetyGuard:
        guard = SafetyGuard(ex.CAP_UA)
        guard.cap_ua = ex.CAP_UA + 500  # past the constructor's check: the guard lets 1510 µA through
        return guard

    monkeypatch.setattr(ex, "make_guard", raised)
    s = run_slice("set_current(cap+step)")
    assert s["failed_sequences"] > 0 and s["over_limit_pulses"] > 0
    assert s["largest_pulse_ua"] == ex.ABOVE_CAP_UA
    f = s["failures"][0]
    assert "pulses above the limit" in f["why"]
    assert f["sequence"].startswith("v2 from stimulating: set_current")
    replay = "python tools/safety_campaign.py --exhaustive --depth 2 --firmware v2 --only"
    assert f["reproduce"] == f"{replay} {f['index']}"


def test_a_pattern_that_reaches_electrodes_meant_off_fails_the_slice(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    opened = ex.ExhaustiveSession._new_device

    def every_electrode_on(session: ex.ExhaustiveSession) -> Any:
        dev = opened(session)
        send = dev.send_pattern
        monkeypatch.setattr(dev, "send_pattern", lambda levels: send([1 if any(levels) else 0] * len(levels)))
        return dev

    monkeypatch.setattr(ex.ExhaustiveSession, "_new_device", every_electrode_on)
    s = run_slice("send_pattern(even mono)")
    assert s["failed_sequences"] > 0 and s["meant_off_pulses"] > 0 and s["over_limit_pulses"] == 0


def test_the_command_line_prints_the_count_and_replays_one_sequence(
    capsys: pytest.CaptureFixture[str],
) -> None:
    assert sc.main(["--exhaustive", "--depth", "0", "--firmware", "v1.2", "--jobs", "1", "--json"]) == 0
    out = capsys.readouterr()
    assert '"sequences": 3' in out.out and "exhaustive: 3 sequences of up to 0 calls" in out.err
    assert sc.main(["--exhaustive", "--depth", "1", "--firmware", "v1.2", "--only", "29"]) == 0
    assert '"sequence": "v1.2 from stimulating: set_current(cap+step)"' in capsys.readouterr().out
