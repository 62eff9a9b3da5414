"""The bounded exhaustive mode (``safety_campaign.py --exhaustive``, ``tools/exhaustive_campaign.py``):
every sequence of the domain is enumerated once; a slice passes on the driver as it is, and fails when an
unsafe guard or a pattern that reaches electrodes meant off is planted — the mode can fail."""

from __future__ import annotations

import itertools
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tools"))
import campaign_engine as engine  # noqa: E402
import exhaustive_campaign as ex  # noqa: E402
import safety_campaign as sc  # noqa: E402

from tactdeform_hw.device.driver.base import LinkState  # noqa: E402
from tactdeform_hw.device.safety.guard import SafetyGuard  # noqa: E402
from tactdeform_hw.emulator.firmware.scan import PulseKind  # noqa: E402

FW = ("v2",)
STIM_KINDS = (int(PulseKind.MONO), int(PulseKind.BI_ANODIC), int(PulseKind.BI_CATHODIC))


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


@pytest.mark.parametrize("firmware", ["v1.2", "v2"])
def test_raising_the_count_while_stimulating_loses_no_byte(firmware: str) -> None:
    """Depth-1 sequence 23: from 32 electrodes stimulating to 255.  Were the count read at the old, shorter
    period, the 255-channel scan would overrun it and starve the parser: the bytes behind the count would be
    lost in the device's queue."""
    assert ex.decode(23, 1, (firmware,)) == (firmware, "stimulating", (2,))
    assert ex.CALLS[2].name == "configure(255)"
    r = ex.run_sequence(23, 1, (firmware,))
    assert r.lost_bytes == 0 and r.losses == 0, r.hazard_counts
    assert "queue_overflow" not in r.hazards and "overrun" not in r.hazards, r.hazard_counts
    assert r.errors == [] and r.over_limit == 0 and r.meant_off == 0
    assert sc.main(["--exhaustive", "--depth", "1", "--firmware", firmware, "--only", "23"]) == 0


@pytest.mark.parametrize("firmware", ["v1.2", "v2"])
def test_the_raised_count_is_the_one_the_board_scans(firmware: str) -> None:
    """After the raise, the even electrodes up to 254 deliver at the cap and no odd one delivers: every
    byte of the configuration and of the pattern behind it was read (on the delivered pulses)."""
    s = ex.ExhaustiveSession(23, firmware, "stimulating")
    emu = s.port.emulator
    s.configure(255)
    s.pattern(1)
    since_s = s.port.now_s
    s.port.advance(3 * 1e6 / ex.config(255).rate_hz / 1e6)
    assert s.res.errors == []
    assert [h.kind.value for h in emu.hazards if h.kind.value in ("queue_overflow", "overrun")] == []
    assert sum(lo.count for lo in emu.losses) == 0
    table = emu.reports.pulse_table(t0_us=since_s * 1e6)
    stim = np.isin(table["kind"], STIM_KINDS) & (table["current_ua"] > 0)
    on = {int(c) for c in table["channel"][stim]}
    assert on == set(range(0, 255, 2))
    assert table["current_ua"].max() <= ex.CAP_UA


@pytest.mark.parametrize("firmware", ["v1.2", "v2"])
def test_a_program_that_opens_the_board_again_raises_the_count_without_loss(firmware: str) -> None:
    """Depth-2 sequence 707: a new device on the board a program left at 32 electrodes and 100 Hz
    configures 255.  Its first configuration raises the count from the identification's 0 at that rate:
    written before the new rate, the 255-channel scan would overrun it (v1.2 lost bytes, v2's sync proof
    failed)."""
    assert ex.describe(707, 2, (firmware,)) == f"{firmware} from stimulating: close+reopen, configure(255)"
    r = ex.run_sequence(707, 2, (firmware,))
    assert r.lost_bytes == 0 and r.errors == [], (r.hazard_counts, r.errors)
    assert "queue_overflow" not in r.hazards and "overrun" not in r.hazards, r.hazard_counts
