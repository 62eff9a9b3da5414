"""What one safety-campaign session costs, against its baseline in the same run: the event-exact emulator
alone, replaying the very writes, advances and resets the session made (no driver, no guard, no judging).
The difference is the host side's share; the baseline is the floor the emulator sets.

    pytest tests/benchmarks/test_bench_campaign.py --benchmark-enable
"""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Any

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "tools"))
import safety_campaign as sc  # noqa: E402

from tactdeform_hw.emulator.timed.model_v1_2 import TimedEmulator  # noqa: E402
from tactdeform_hw.emulator.timed.model_v2 import TimedEmulatorV2  # noqa: E402

SEED = {"v1.2": 100, "v2": 7}
SESSIONS = range(4)  # a few sessions: their mix of links, counts and calls is the campaign's


def run_sessions(firmware: str) -> int:
    return sum(sc.run_session(i, SEED[firmware], firmware=firmware).pulses for i in SESSIONS)


def record(firmware: str, monkeypatch: pytest.MonkeyPatch) -> list[tuple[tuple[Any, ...], list[Any]]]:
    """Each session's emulator construction and every write, advance and reset made on it."""
    model: Any = TimedEmulatorV2 if firmware == "v2" else TimedEmulator
    runs: list[tuple[tuple[Any, ...], list[Any]]] = []
    init, write, advance, reset = model.__init__, model.write, model.advance_to, model.reset

    def rec_init(self: Any, *args: Any, **kw: Any) -> None:
        init(self, *args, **kw)
        runs.append(((args, kw), []))

    def rec_write(self: Any, data: bytes, at_us: float | None = None) -> int:
        runs[-1][1].append(("write", bytes(data), self.now_us if at_us is None else at_us))
        return int(write(self, data, at_us))

    def rec_advance(self: Any, t_us: float) -> None:
        runs[-1][1].append(("advance", t_us))
        advance(self, t_us)

    def rec_reset(self: Any, *args: Any) -> None:
        runs[-1][1].append(("reset", args))
        reset(self, *args)

    with monkeypatch.context() as m:
        m.setattr(model, "__init__", rec_init)
        m.setattr(model, "write", rec_write)
        m.setattr(model, "advance_to", rec_advance)
        m.setattr(model, "reset", rec_reset)
        run_sessions(firmware)
    return runs


def replay(firmware: str, runs: list[tuple[tuple[Any, ...], list[Any]]]) -> float:
    model: Any = TimedEmulatorV2 if firmware == "v2" else TimedEmulator
    end = 0.0
    for (args, kw), ops in runs:
        emu = model(*args, **kw)
        for op in ops:
            if op[0] == "write":
                emu.write(op[1], max(op[2], emu.now_us))
            elif op[0] == "advance":
                if op[1] >= emu.now_us:
                    emu.advance_to(op[1])
            else:
                emu.reset(*op[1])
        end += emu.now_us
    return end


@pytest.mark.parametrize("firmware", ["v1.2", "v2"])
def test_bench_campaign_sessions(benchmark, firmware: str) -> None:  # type: ignore[no-untyped-def]
    pulses = benchmark(run_sessions, firmware)
    assert pulses > 0


@pytest.mark.parametrize("firmware", ["v1.2", "v2"])
def test_bench_campaign_sessions_emulator_only(  # type: ignore[no-untyped-def]
    benchmark, firmware: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    runs = record(firmware, monkeypatch)
    assert len(runs) >= len(SESSIONS) and all(ops for _, ops in runs)
    simulated_us = benchmark(replay, firmware, runs)
    assert simulated_us > 0


@pytest.mark.parametrize("firmware", ["v1.2", "v2"])
def test_bench_uart_flush(benchmark, firmware: str) -> None:  # type: ignore[no-untyped-def]
    """A recovery's probe over a UART (512 zeros, the safe tail, the sync check), run for 200 ms: a byte
    per 10.85 µs on the link and a main-loop call per zero -- the traffic that made most of a session's
    cost when each byte was an event of its own."""
    from tactdeform_hw.device.driver.firmware_probe import PROBE

    model: Any = TimedEmulatorV2 if firmware == "v2" else TimedEmulator

    def flush() -> bytes:
        emu = model(link="uart")
        emu.write(PROBE, 1000.0)
        emu.advance_to(200_000.0)
        return bytes(emu.read_tx())

    reply = benchmark(flush)
    assert reply == (b"\x00" if firmware == "v2" else b"")  # v2 answers the sync check; v1.2 skips it
