"""Pacing: the driver never overflows the firmware's receive queue (v1.2's 256 bytes, v2's 1024) nor
outruns its parser (v1.2's 1 ms per command)."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

from tactdeform_hw.clock import InstantClock, MonotonicClock, SimulatedClock
from tactdeform_hw.device import EtactileKitDevice, StimConfig, open_device
from tactdeform_hw.device.driver.dialect import count_raise_timing, scan_of, timing_before_count, worst_scan_s
from tactdeform_hw.device.driver.pacing import Pacer, PacingPolicy, default_pacer, padding_for
from tactdeform_hw.device.driver.v2 import buffer_levels
from tactdeform_hw.device.safety.guard import TACTDEFORM_REGION_OF, SafetyGuard
from tactdeform_hw.emulator.faults import TimedPort
from tactdeform_hw.emulator.firmware.hazards import HazardKind
from tactdeform_hw.emulator.serving.in_process import EmulatorPort
from tactdeform_hw.emulator.timed.model_v1_2 import TimedEmulator, timed_emulator
from tactdeform_hw.emulator.timed.model_v2 import TimedEmulatorV2
from tactdeform_hw.errors import ShortReplyError
from tactdeform_hw.protocol.constants import PAYLOAD_KIND, Opcode
from tactdeform_hw.protocol.firmware import FIRMWARES
from tactdeform_hw.protocol.firmware_math import firmware_period_us

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tools"))
import safety_scenarios as ss  # noqa: E402

RATE_HZ = ss.RENDERER_MAX_RATE_HZ


def frames(n: int, electrodes: int = 32) -> list[list[int]]:
    """Every frame different, alternating low- and high-limit regions so the height moves every frame."""
    out = []
    for i in range(n):
        if electrodes == 32:
            region = (4, 0, 3, 8, 1)[i % 5]
            out.append([1 if r == region else 0 for r in TACTDEFORM_REGION_OF])
        else:
            out.append([(i + k) % 3 for k in range(electrodes)])
    return out


def session(link: str, robust: bool, guard: SafetyGuard | None = None) -> tuple[TimedPort, EtactileKitDevice]:
    port = TimedPort(link=link, robust_encoding=robust)
    dev = EtactileKitDevice(port, guard=guard or SafetyGuard.from_profile(ss.PROFILE))
    return port, dev


def assert_nothing_lost(port: TimedPort) -> None:
    emu = port.emulator
    emu.run_until_idle()
    assert emu.losses == [], [lo.describe() for lo in emu.losses[:3]]
    assert not [h for h in emu.hazards if h.kind is HazardKind.QUEUE_OVERFLOW]
    bad = [c for c in emu.commands if not c.in_sync]
    assert bad == [], bad[:3]
    assert emu.queue.high_water <= emu.queue.capacity


@pytest.mark.parametrize(("link", "robust"), [("usb", False), ("usb", True), ("uart", False), ("uart", True)])
def test_zero_losses_at_the_renderers_highest_rate(link: str, robust: bool) -> None:
    port, dev = session(link, robust)
    dev.configure(StimConfig(current_ua=1500))
    sent = 0
    heights = set()
    for i, levels in enumerate(frames(int(RATE_HZ * 1.0))):
        port.advance_to(0.05 + i / RATE_HZ)
        dev.send_pattern(levels)
        heights.add(dev.current_ua)
        sent += 1
    assert len(heights) >= 3  # the height really moved with the frames
    assert_nothing_lost(port)
    patterns = [c for c in port.emulator.commands if c.name == "PATTERN"]
    copies = 2 if robust else 1
    # every frame reached the parser (all-off patterns of configure too)
    assert len(patterns) >= sent * copies
    assert patterns[-1].value == bytes(frames(int(RATE_HZ * 1.0))[-1])
    # the frames kept to the renderer's schedule: pacing never pushed a frame past the next one
    assert port.now_s < 0.05 + sent / RATE_HZ + 0.02
    dev.close()


@pytest.mark.parametrize("link", ["usb", "uart"])
@pytest.mark.parametrize("firmware", list(FIRMWARES))
def test_zero_losses_on_full_reconfigurations_and_resyncs(firmware: str, link: str) -> None:
    """Back to back on every version's timed model: nothing waits between the calls but the pacer, and
    the firmware's queue never drops a byte."""
    port = TimedPort(timed_emulator(firmware=firmware, link=link), link=link, robust_encoding=True)
    dev = EtactileKitDevice(port, guard=SafetyGuard())
    for i in range(6):
        n = 32 if i % 2 else 64  # 64 channels need a longer period: 60 Hz
        dev.configure(
            StimConfig(electrode_count=n, current_ua=500 + 100 * i, rate_hz=125 - i if n == 32 else 60)
        )
        dev.send_pattern([1] * dev.electrodes)
        dev.all_off()
        dev.resync()
    emu = port.emulator
    emu.run_until_idle()
    assert emu.losses == [], [lo.describe() for lo in emu.losses[:3]]
    assert not [h for h in emu.hazards if h.kind is HazardKind.QUEUE_OVERFLOW]
    s = emu.state()
    assert s.electrode_num == 32 and set(buffer_levels(s)[:32]) == {0} and not s.rx_dropped
    dev.close()


def test_zero_losses_with_whole_queue_patterns() -> None:
    """255 electrodes: each pattern command is 256 bytes, the whole queue."""
    port, dev = session("usb", False, SafetyGuard())
    dev.configure(
        StimConfig(electrode_count=255, current_ua=100, pulse_width_us=20, discharge_us=10, rate_hz=100)
    )
    for i, levels in enumerate(frames(40, 255)):
        port.advance_to(0.02 + i * 0.004)
        dev.send_pattern(levels)
    assert_nothing_lost(port)
    dev.close()


def test_without_pacing_the_same_traffic_loses_bytes() -> None:
    """The control: the checks above can fail.  An unpaced burst overflows the queue."""
    port, _ = session("usb", False, SafetyGuard())
    unpaced = Pacer(
        clock=port.pacing_clock,
        policy=PacingPolicy(command_interval_s=0, queue_bytes=10**9, link_latency_s=0, tick_s=0),
    )
    dev = EtactileKitDevice(port, guard=SafetyGuard(), pacer=unpaced)
    for call in [lambda: dev.configure(StimConfig(current_ua=500))] + [
        lambda lv=lv: dev.send_pattern(lv) for lv in frames(12)
    ]:
        try:
            call()
        except ShortReplyError:
            pass  # the closed loop notices: a proof that the queue was read fails after a burst
    port.emulator.run_until_idle()
    assert port.emulator.losses, "an unpaced burst should have overflowed the 256-byte queue"
    assert any(h.kind is HazardKind.QUEUE_OVERFLOW for h in port.emulator.hazards)


def test_pacer_spacing_and_queue_model() -> None:
    clock = SimulatedClock()
    pacer = Pacer(clock=clock)
    times: list[tuple[float, bytes]] = []
    cmds = [b"\xfb\x10\x00", b"\xfe" + bytes(32), b"\xff", b"\xfe" + bytes(32), bytes(256), b"\xfa\xc8\x00"]
    for c in cmds:
        pacer.write(lambda d: times.append((clock.now(), d)), c)
        assert pacer.queue_estimate() <= 256
    payload_times = [t for t, d in times if d[0] >= 0xF5 and PAYLOAD_KIND.get(d[0]) is not None]
    gaps = [b - a for a, b in zip(payload_times, payload_times[1:])]
    assert min(gaps) >= pacer.policy.command_interval_s - 1e-12
    zeros = [d for _, d in times if d[:1] == b"\x00"]
    assert b"".join(zeros) == bytes(256) and max(len(z) for z in zeros) <= 64
    assert pacer.stats.commands == 5 and pacer.stats.waits > 0
    # with scans filling 7.9 of 8 ms, the parser takes one payload command per period, not per ms
    pacer.set_timing(0.008, 0.0079)
    assert pacer.payload_interval_s() > 0.008
    pacer.set_timing(0.008, 0.0018)  # a 6 ms gap: six ticks, six commands per period
    assert 0.0012 <= pacer.payload_interval_s() < 0.002


def test_robust_padding() -> None:
    assert padding_for(b"\xfb\xe8\x03") == b"\x00\x00"
    assert padding_for(b"\xfc\x20") == b"\x20" and padding_for(b"\xfd\x01") == b"\x01"
    assert padding_for(b"\xf9\x00") == b"\x00" and padding_for(b"\xfe\x01\x02") == b"\x00\x00"
    assert padding_for(b"\xff") == b"" and padding_for(bytes(8)) == b""


def test_robust_encoding_avoids_command_like_payload_bytes() -> None:
    port, dev = session("usb", True, SafetyGuard())
    dev.configure(StimConfig(current_ua=2500))  # code 250 = 0xFA: a command byte as the low byte
    assert dev.current_ua == 2440 and any(e["rule"] == "encoding" for e in dev.guard.log)
    from tactdeform_hw.errors import LimitError

    with pytest.raises(LimitError, match="pulse_width_us"):
        dev.configure(StimConfig(current_ua=100, pulse_width_us=250))
    dev.close()


def test_default_pacers() -> None:
    assert isinstance(default_pacer(EmulatorPort()).clock, InstantClock)
    with open_device("emulator") as dev:
        assert isinstance(dev.pacer.clock, InstantClock)  # the untimed emulator is never slowed down
    port = TimedPort()
    assert default_pacer(port).clock is port.pacing_clock and default_pacer(port).robust

    class RealLike:
        is_open = True

    assert isinstance(default_pacer(RealLike()).clock, MonotonicClock)


def _burst_then_pattern(firmware_name: str) -> tuple[float, float]:
    """(time the eight configuration commands took to write, the pattern's wait after them), paced for the
    TactDeform setting's scans on ``firmware_name``."""
    from tactdeform_hw.protocol.commands import V2_COMMANDS as c2
    from tactdeform_hw.protocol.firmware import V1_2, V2

    fw = V2 if firmware_name == "v2" else V1_2
    clock = SimulatedClock()
    pacer = Pacer(clock=clock, policy=PacingPolicy(firmware=fw, queue_bytes=fw.rx_queue_bytes))
    pacer.set_timing(0.008, 0.00785)
    burst = [
        c2.encode_electrode_num(32),
        c2.encode_stim_mode(0),
        c2.encode_polarity(1),
        c2.encode_pulse_width(200),
        c2.encode_sense_height(0),
        c2.encode_sense_width(0),
        c2.encode_discharge(45),
        c2.encode_frequency(125),
    ]
    for data in burst:
        pacer.write(lambda _b: None, data)
    burst_s = clock.now()
    pacer.write(lambda _b: None, c2.encode_pattern([100] * 32, electrode_num=32))
    return burst_s, clock.now() - burst_s


def test_v2_reads_a_configuration_burst_back_to_back_but_a_pattern_waits_its_own_gap() -> None:
    """v2's parser sleeps only when idle: a configuration burst is written at once.  A pattern still waits
    a whole interval after the last command, so it is the first thing read after a scan and its copy ends
    before the next scan (no torn pattern); v1.2 spaces every command with a payload."""
    v2_burst, v2_wait = _burst_then_pattern("v2")
    v12_burst, v12_wait = _burst_then_pattern("v1.2")
    interval = Pacer(clock=SimulatedClock())
    interval.set_timing(0.008, 0.00785)
    assert v2_burst == 0.0
    assert v12_burst >= 7 * interval.payload_interval_s()
    need = interval.payload_interval_s() - 1e-9  # the waits are differences of clock readings
    assert v2_wait >= need and v12_wait >= need


def test_v2_a_pattern_written_alone_is_torn_when_the_parsers_tick_falls_just_before_a_scan() -> None:
    """Why pacing cannot prevent torn scans on v2.  16 electrodes at 222 Hz: a 3.8 ms scan in a 4.5 ms
    period, a gap shorter than a tick, yet the period is no whole number of ticks, so now and then the idle
    parser's tick falls in the gap just before an alarm.  A pattern written alone — nothing else written
    for 40 ms, so nothing queued before it — that arrives before such a tick is read on it, and the scan
    pre-empts its copy: the first channels new, the rest old.  The write's moment only chooses the tick
    when the host knows where the alarms are, and no reply tells it."""
    from tactdeform_hw.emulator.timed.model_v2 import TimedEmulatorV2
    from tactdeform_hw.protocol.commands import V2_COMMANDS as c2
    from tactdeform_hw.protocol.firmware import OpcodeV2

    n = 16
    emu = TimedEmulatorV2(link="uart")
    setup = (
        c2.encode_electrode_num(n)
        + c2.encode_stim_mode(c2.STIM_MODE_MONOPHASIC)
        + c2.encode_pulse_width(200)
        + c2.encode_discharge(45)
        + c2.encode_frequency(222)
        + c2.encode_pattern([0] * n, electrode_num=n)
    )
    emu.write(setup, 0.0)
    emu.advance_to(40_000.0)
    last, before = emu.scans[-1], emu.scans[-2]
    period_ns = last.start_ns - before.start_ns
    assert period_ns - last.duration_ns < emu.model.rtos_tick_ns  # the gap is shorter than a tick
    tick = emu.model.rtos_tick_ns
    alarm = next(
        last.start_ns + j * period_ns
        for j in range(5, 1000)
        if 0 < (last.start_ns + j * period_ns) % tick < 20_000
    )
    wake = alarm - alarm % tick  # the parser's tick, less than 20 µs before the alarm
    emu.write(c2.encode_pattern([100] * n, electrode_num=n), (wake - 500_000) / 1000)  # arrives 120 µs before
    emu.advance_to(alarm / 1000 + 10_000)
    assert [(t, op) for t, op, _ in emu.applied if t > last.start_ns] == [(wake, OpcodeV2.PATTERN)]
    torn = [h for h in emu.hazards if h.kind is HazardKind.TORN_PATTERN]
    assert len(torn) == 1 and torn[0].time_us == alarm / 1000
    assert 0 < torn[0].detail["new_channels"] < n


def test_a_raised_count_is_paced_by_its_own_scan_at_the_new_period() -> None:
    """The pacing rule of a count raised while a configuration is in force: the new rate and widths go
    first, and the bytes behind the count are paced by the new count's longest scan at the new period —
    never by the old count's scan, and never at the old period, which the new count's scan overruns."""
    old = StimConfig(electrode_count=32, current_ua=1500, pulse_width_us=50, rate_hz=100)
    new = StimConfig(electrode_count=255, current_ua=1500, pulse_width_us=50, rate_hz=26)
    assert timing_before_count(old, new)
    assert not timing_before_count(new, old) and not timing_before_count(old, old)
    assert timing_before_count(None, new)  # a first configuration: from the count 0 the identification leaves
    period_us, scan_us = count_raise_timing(new)
    assert period_us == firmware_period_us(new.rate_hz)
    assert scan_us == pytest.approx(worst_scan_s(new) * 1e6)
    idle_us = scan_of(new, bytes(255))
    assert idle_us <= scan_us < period_us  # the raised count's scans leave a gap at the new period...
    assert idle_us > firmware_period_us(old.rate_hz)  # ...and none at the old one: why the timing goes first
    pacer = Pacer(clock=SimulatedClock())
    pacer.set_timing(firmware_period_us(old.rate_hz) / 1e6, scan_of(old, bytes(32)) / 1e6)
    old_interval_s = pacer.payload_interval_s()
    pacer.set_timing(period_us / 1e6, scan_us / 1e6)
    assert pacer.payload_interval_s() > period_us / 1e6 > old_interval_s  # one command per scan at most


@pytest.mark.parametrize("firmware", list(FIRMWARES))
def test_a_raised_count_is_written_after_the_new_rate(firmware: str) -> None:
    """On the wire: raising 32 -> 255 writes the rate before the count; lowering 255 -> 32 keeps the count
    first (the scan shortens: the order every other configuration has always had)."""
    emu = (TimedEmulatorV2 if firmware == "v2" else TimedEmulator)("compact", 8, link="usb")
    port = TimedPort(emu, link="usb", faults=[], seed=0, robust_encoding=False)
    dev = EtactileKitDevice(port, firmware=firmware, guard=SafetyGuard(1500))  # type: ignore[arg-type]
    small = StimConfig(electrode_count=32, current_ua=1500, pulse_width_us=50, rate_hz=100)
    large = StimConfig(electrode_count=255, current_ua=1500, pulse_width_us=50, rate_hz=26)
    dev.configure(small)
    writes: list[bytes] = []
    write = port.write
    port.write = lambda data: writes.append(bytes(data)) or write(data)  # type: ignore[method-assign]
    dev.configure(large)
    order = [w[:2] for w in writes]
    rate = bytes((Opcode.FREQUENCY, 26))
    assert order.index(rate) < order.index(bytes((Opcode.ELECTRODE_NUM, 255)))
    writes.clear()
    dev.configure(small)
    order = [w[:2] for w in writes]
    assert order.index(bytes((Opcode.ELECTRODE_NUM, 32))) < order.index(bytes((Opcode.FREQUENCY, 100)))
    assert sum(lo.count for lo in emu.losses) == 0
    dev.close()
