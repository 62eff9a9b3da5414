"""The fail-safe's probe, timed: how long it can wait for its reply (:meth:`Device.probe_bound_s`, a term of
:meth:`FailSafe.recovery_bound_s`) and that an owner who never pauses between calls cannot keep it from
running (:attr:`Device.before_stimulating`).  Both firmware versions, on the timed board models, judged on
the simulated clock the board runs on."""

from __future__ import annotations

import pytest

from tactdeform_hw.device import EtactileKitDevice, StimConfig
from tactdeform_hw.device.safety.failsafe import FailSafe
from tactdeform_hw.emulator.faults import TimedPort
from tactdeform_hw.emulator.timed.model_v1_2 import TimedEmulator
from tactdeform_hw.emulator.timed.model_v2 import TimedEmulatorV2
from tactdeform_hw.errors import ShortReplyError, TactDeformError


def _device(fw: str, n: int, *, robust: bool = False) -> tuple[EtactileKitDevice, TimedPort]:
    boards = (n + 31) // 32
    emu = TimedEmulatorV2("compact", boards, link="uart") if fw == "v2" else TimedEmulator("compact", boards)
    port = TimedPort(emu, link="uart", robust_encoding=robust)
    dev = EtactileKitDevice(port, firmware=fw)
    return dev, port


def _frame(fw: str, n: int, i: int) -> list[int]:
    """Frames that differ from one call to the next (an unchanged v2 frame writes nothing); v2 frames
    carry one waveform (its stimulation mode is global)."""
    if fw == "v2":
        return [1 if (k + i) % 3 else 0 for k in range(n)]
    return [1 + (k + i) % 2 for k in range(n)]


@pytest.mark.parametrize(
    ("fw", "n", "rate_hz", "robust"),
    [
        ("v1.2", 32, 72, False),
        ("v1.2", 32, 7, True),
        ("v1.2", 255, 7, False),  # a pattern longer than the queue model's limit: it waits for the queue
        ("v1.2", 1, 300, True),
        ("v2", 32, 7, True),
        ("v2", 255, 7, False),
        ("v2", 1, 72, False),
    ],
)
def test_a_probe_behind_the_fullest_queue_gives_up_within_probe_bound_s(
    fw: str, n: int, rate_hz: int, robust: bool
) -> None:
    """Frames back to back fill the queue model as far as the pacer lets them; the board then stops
    reading, and the probe that follows waits until its deadline — no longer than the bound says."""
    dev, port = _device(fw, n, robust=robust)
    dev.configure(StimConfig(electrode_count=n, current_ua=800, rate_hz=rate_hz))
    for i in range(12):
        dev.send_pattern(_frame(fw, n, i))
    bound = dev.probe_bound_s()
    port.emulator.stop_reading()
    t0 = port.now_s
    with pytest.raises(ShortReplyError):
        dev.measure()
    waited = port.now_s - t0
    assert 0 < waited <= bound, (waited, bound)


def test_probe_bound_s_is_0_before_a_configuration() -> None:
    dev, _ = _device("v1.2", 32)
    assert dev.probe_bound_s() == 0.0


def _stream_after_a_stall(fw: str, *, hook: bool) -> tuple[float, list[float], float, FailSafe]:
    """The owner calls ``send_pattern`` back to back; 0.1 s in, the board's main loop hangs (nothing is read,
    nothing answered, the scans go on).  Returns when the stall began, when the fail-safe began a recovery,
    the longest owner call (without the probes run before it) and the fail-safe."""
    n = 32
    dev, port = _device(fw, n)
    dev.configure(StimConfig(electrode_count=n, current_ua=800, rate_hz=72))
    fs = FailSafe(dev, watchdog_s=None, probe_interval_s=0.02, thread=False, signals=False, at_exit=False)
    fs.start()
    port.hooks.append(lambda t: fs.poll(t))
    if not hook:
        dev.before_stimulating = None
    t_stall: float | None = None
    longest = 0.0
    for i in range(1000):
        if port.now_s >= 0.6:
            break
        if t_stall is None and port.now_s >= 0.1:
            port.emulator.stop_reading()
            t_stall = port.now_s
        t0, waited = port.now_s, fs.owner_wait_s
        try:
            dev.send_pattern(_frame(fw, n, i))
        except TactDeformError:
            assert t_stall is not None, "a frame failed before the stall"
        assert port.now_s > t0, "a call that took no time: the owner's loop would not be the test's"
        longest = max(longest, port.now_s - t0 - (fs.owner_wait_s - waited))
    fs.stop()
    assert t_stall is not None
    recoveries = [e.t for e in fs.events if e.kind == "recover"]
    return t_stall, recoveries, longest, fs


@pytest.mark.parametrize("fw", ["v1.2", "v2"])
def test_an_owner_that_never_pauses_cannot_starve_the_probe(fw: str) -> None:
    t_stall, recoveries, longest, fs = _stream_after_a_stall(fw, hook=True)
    assert recoveries, "the stalled board was never noticed"
    noticed = recoveries[0] - t_stall
    # due within an interval and a poll, run before the owner's next write, then its reply's deadline
    limit = fs.probe_interval_s + fs.poll_s + longest + fs.device.probe_bound_s()
    assert 0 < noticed <= limit, (noticed, limit)


@pytest.mark.parametrize("fw", ["v1.2", "v2"])
def test_without_the_turn_before_each_write_a_busy_owner_starves_the_probe(fw: str) -> None:
    """The control: with the hook taken away, the poll never finds the device free between the owner's
    calls, and the hung board goes unnoticed for as long as the owner keeps calling."""
    _, recoveries, _, fs = _stream_after_a_stall(fw, hook=False)
    assert recoveries == []
    assert fs.owner_wait_s == 0.0
