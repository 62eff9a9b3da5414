"""The real-time emulator against the wall clock (run: pytest tests/benchmarks/test_bench_realtime.py
--benchmark-enable).

Two figures per scenario, both at the TactDeform setting (32 electrodes, 125 Hz) on a real pty:

* the serving loop's *lag* — how late each wake-up came after the event it was for (median / p99 / max
  in ``extra_info``, with the count beyond 1 ms) and the serving thread's CPU per second of wall time;
  idle, and with a pyserial client streaming a pattern 72 times a second.  The benchmark's own time is
  the wall time of the session (the baseline: the session's length);
* the model's *cost* for one second of that stream when every wake-up the loop would make is simulated
  on a fake clock (no sleeping): the CPU the real-time loop spends, without the scheduler's noise.
"""

from __future__ import annotations

import importlib.util
from pathlib import Path
from typing import Any

import pytest

from tactdeform_hw.emulator.firmware.scan import ScanConfig
from tactdeform_hw.emulator.serving.realtime import RealtimeEmulator
from tactdeform_hw.emulator.timed.model_v1_2 import configuration_bytes
from tactdeform_hw.protocol import encode_pattern

CFG = ScanConfig.make(32, 1, pulse_width_us=200, discharge_us=45, rate_hz=125)
SESSION_S = 2.0


def _tool() -> Any:
    path = Path(__file__).resolve().parents[2] / "tools" / "realtime_lag.py"
    spec = importlib.util.spec_from_file_location("realtime_lag", path)
    assert spec is not None and spec.loader is not None
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def _session(stream_hz: float | None, seconds: float) -> dict[str, Any]:
    import serial

    from tactdeform_hw.emulator.serving.pty_server import PtyServer

    tool = _tool()
    server = PtyServer(RealtimeEmulator()).start()
    try:
        port = serial.Serial(server.path, 921600, timeout=0.5)
        tool.configure(port, CFG, 125)
        stream = None if stream_hz is None else (port, encode_pattern(CFG.pattern), stream_hz)
        out: dict[str, Any] = tool.phase(server, seconds, stream)
        out.pop("writes")
        port.close()
    finally:
        server.stop()
    return out


@pytest.mark.parametrize("stream_hz", [None, 72.0], ids=["idle", "72hz"])
def test_realtime_lag_on_a_pty(benchmark, stream_hz: float | None) -> None:  # type: ignore[no-untyped-def]
    seconds = 0.5 if benchmark.disabled else SESSION_S  # a smoke run inside the ordinary test suite
    result = benchmark.pedantic(_session, args=(stream_hz, seconds), rounds=1, iterations=1)
    benchmark.extra_info.update(result)
    assert result["wakeups"] > 0 and result["cpu_percent"] >= 0


class _Clock:
    t = 0.0

    def __call__(self) -> float:
        return self.t


def _one_second_of_stream() -> int:
    """Every wake-up the serving loop makes in 1 s of a 72 Hz stream, on a fake clock."""
    clock = _Clock()
    rt = RealtimeEmulator(clock=clock)
    rt.write(configuration_bytes(CFG, 125))
    clock.t = 0.05
    rt.catch_up()
    data = encode_pattern(CFG.pattern)
    next_write = clock.t
    wakeups = 0
    end = clock.t + 1.0
    while clock.t < end:
        due = rt.t0 + rt.timed.next_event_us() / 1e6
        if next_write <= due:
            clock.t = next_write
            rt.write(data)
            next_write += 1 / 72
        else:
            clock.t = due
            rt.catch_up()
            wakeups += 1
    return wakeups


def test_realtime_model_cost_per_second_of_72hz_stream(benchmark) -> None:  # type: ignore[no-untyped-def]
    benchmark.extra_info["device_s"] = 1.0
    wakeups = benchmark.pedantic(_one_second_of_stream, rounds=5, iterations=1)
    benchmark.extra_info["wakeups"] = wakeups
    assert wakeups > 125
