"""The v1.2 timed model's pulse table: a window of it is the whole table's rows in that window."""

from __future__ import annotations

import numpy as np
import pytest

from tactdeform_hw.emulator.firmware.scan import ScanConfig
from tactdeform_hw.emulator.timed.model_v1_2 import TimedEmulator
from tactdeform_hw.protocol import commands as c


def _board() -> TimedEmulator:
    """Scan runs of several templates, repeated and single, one cut short by the watchdog-free reboot."""
    emu = TimedEmulator(link="uart")
    emu.configure(ScanConfig.make(8, 1, pulse_width_us=100, discharge_us=20, rate_hz=500))
    emu.advance_to(30_000)
    emu.write(c.encode_pattern([2, 1, 0, 3, 1, 2, 2, 1]), 30_000)
    emu.advance_to(60_000)
    emu.write(c.encode_pulse_height(300) + c.encode_sense_height(10), 60_000)
    emu.advance_to(100_000)
    return emu


@pytest.mark.parametrize(("t0", "t1"), [(None, None), (0.0, None), (None, 45_000.0), (31_234.5, 77_001.0)])
def test_a_window_of_the_pulse_table_is_the_rows_in_it(t0: float | None, t1: float | None) -> None:
    emu = _board()
    whole = emu.reports.pulse_table()
    part = emu.reports.pulse_table(t0, t1)
    keep = np.ones(whole["start_us"].size, dtype=bool)
    if t0 is not None:
        keep &= whole["start_us"] >= t0
    if t1 is not None:
        keep &= whole["start_us"] < t1
    assert set(part) == set(whole)
    for name, col in whole.items():
        assert part[name].dtype == col.dtype, name
        assert np.array_equal(part[name], col[keep]), name
    # several runs, some repeated scans, and pulses of every column's kinds
    assert len(emu.runs) > 3 and any(r.count > 1 for r in emu.runs)
    assert np.array_equal(whole["charge_nc"], whole["current_ua"] * (whole["width_us"] * 1000) / 1e6)
    assert whole["cycle"].size > 100 and np.all(np.diff(whole["cycle"]) >= 0)
