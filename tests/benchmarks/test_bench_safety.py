"""What the safety layer costs per frame on the untimed in-process emulator (guard, interlock, pacing
books, no real waiting), against the same frames with the plain hardware-ceiling guard.

    pytest tests/benchmarks/test_bench_safety.py --benchmark-enable
"""

from __future__ import annotations

import datetime as dt

import pytest

from tactdeform_hw.device import EtactileKitDevice, StimConfig
from tactdeform_hw.device.participant.profiles import ParticipantProfile
from tactdeform_hw.device.safety.guard import TACTDEFORM_REGION_OF, SafetyGuard
from tactdeform_hw.emulator.serving.in_process import EmulatorPort

PROFILE = ParticipantProfile(
    "B01", 2000, (1500, 1400, 1500, 1300, 1200, 1300, 1500, 1400, 1500), dt.date(2024, 5, 1)
)
FRAMES = [[1 if r == region else 0 for r in TACTDEFORM_REGION_OF] for region in (4, 0, 3, 8, 1)]


def run_frames(dev: EtactileKitDevice, n: int = 100) -> None:
    for i in range(n):
        dev.send_pattern(FRAMES[i % len(FRAMES)])


@pytest.mark.parametrize("guard", ["ceiling", "participant"])
def test_bench_frames_through_the_guard(benchmark, guard: str) -> None:  # type: ignore[no-untyped-def]
    g = SafetyGuard() if guard == "ceiling" else SafetyGuard.from_profile(PROFILE)
    dev = EtactileKitDevice(EmulatorPort(), guard=g)
    dev.configure(StimConfig(current_ua=1500))
    benchmark(run_frames, dev)
    assert dev.frames_sent >= 100
    dev.close()
