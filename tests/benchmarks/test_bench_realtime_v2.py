"""The real-time v2 board's model cost (run: pytest tests/benchmarks/test_bench_realtime_v2.py
--benchmark-enable).

At the TactDeform setting (32 electrodes, mode 0, 200 µs, 45 µs discharge, 125 Hz): one second of a
72 Hz stream of per-electrode frames (every frame new heights, so no scan shape is reused from a cache
of patterns), with every wake-up the serving loop would make simulated on a fake clock (no sleeping) —
the CPU the real-time loop spends, without the scheduler's noise; on the serial build's USB link (pty,
``etactile://``) and on the Wi-Fi build's TCP stream.
"""

from __future__ import annotations

import pytest

from tactdeform_hw.emulator.serving.realtime import SERIAL_USB, WIFI_TCP, RealtimeEmulator
from tactdeform_hw.protocol.commands import V2_COMMANDS as v2

N = 32
SETUP = (
    v2.encode_electrode_num(N)
    + v2.encode_stim_mode(0)
    + v2.encode_pulse_width(200)
    + v2.encode_discharge(45)
    + v2.encode_frequency(125)
)


class _Clock:
    t = 0.0

    def __call__(self) -> float:
        return self.t


def _one_second_of_stream(build: str) -> int:
    clock = _Clock()
    rt = RealtimeEmulator(clock=clock, firmware="v2", rules=SERIAL_USB if build == "usb" else WIFI_TCP)
    rt.write(SETUP)
    clock.t = 0.05
    rt.catch_up()
    next_write = clock.t
    wakeups = k = 0
    end = clock.t + 1.0
    while clock.t < end:
        due = rt.t0 + rt.timed.next_event_us() / 1e6
        if next_write <= due:
            clock.t = next_write
            rt.write(v2.encode_pattern([(k * 37 + ch) % 4096 for ch in range(N)]))
            k += 1
            next_write += 1 / 72
        else:
            clock.t = due
            rt.catch_up()
            wakeups += 1
    return wakeups


@pytest.mark.parametrize("build", ["usb", "tcp"])
def test_realtime_v2_model_cost_per_second_of_72hz_stream(benchmark, build: str) -> None:  # type: ignore[no-untyped-def]
    benchmark.extra_info["device_s"] = 1.0
    wakeups = benchmark.pedantic(_one_second_of_stream, args=(build,), rounds=3, iterations=1)
    benchmark.extra_info["wakeups"] = wakeups
    assert wakeups > 125  # every scan and every frame's parser call
