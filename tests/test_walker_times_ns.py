"""The statement walker's trace in integer ns is its µs trace, each time multiplied back."""

from __future__ import annotations

import pytest

from tactdeform_hw.emulator.firmware.firmware_scan import FirmwareScanConfig, trace_scan


@pytest.mark.parametrize(("n", "mode"), [(0, 0), (3, 0), (9, 1), (32, 2)])
def test_a_trace_in_ns_is_the_trace_in_us_to_the_ns(n: int, mode: int) -> None:
    cfg = FirmwareScanConfig(
        electrode_num=n,
        stim_pattern=tuple((k * 37) % 5 * 900 for k in range(n)),
        pulse_width=200,
        discharge_time=45,
        hv513_num=2,
        sense_pulse_height=30,
        sense_pulse_width=20,
        stim_mode=mode,
        prior_scans=1,
    )
    us = trace_scan(cfg, "v2")
    ns = trace_scan(cfg, "v2", times_ns=True)
    assert [[round(e[0] * 1000), *e[1:]] for e in us.events] == ns.events
    assert all(isinstance(e[0], int) for e in ns.events) and ns.events
    assert round(us.isr_return_us * 1000) == ns.isr_return_us
    assert [round(t * 1000) for t in us.channel_start_us] == ns.channel_start_us
    assert round(us.clear_start_us * 1000) == ns.clear_start_us
    assert (us.voltage, us.chain_position, us.alarm_ticks) == (ns.voltage, ns.chain_position, ns.alarm_ticks)
