"""Fuzzing: the decoder, the emulator, the profile loader and the driver API take anything a caller or a
link can throw at them — wrong lengths, negative, NaN, huge, fractional, wrong types — and answer with a
clear error or a correct result: never a crash, never a hang, never a write that breaks a limit.

Every property counts its cases in :data:`CASES` (``tools/safety_report.py`` reports the total).
"""

from __future__ import annotations

import datetime as dt
import math
from collections import Counter
from typing import Any

from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from tactdeform_hw.device import EtactileKitDevice, StimConfig
from tactdeform_hw.device.participant.profiles import ParticipantProfile, profile_from_dict
from tactdeform_hw.device.safety.guard import SafetyGuard
from tactdeform_hw.emulator import Emulator
from tactdeform_hw.emulator.timed.model_v1_2 import TimedEmulator
from tactdeform_hw.errors import TactDeformError
from tactdeform_hw.protocol.decoder import StreamDecoder, decode

from .safety_helpers import RecordingPort, defects

CASES: Counter[str] = Counter()
PROFILE = ParticipantProfile(
    "FZ01", 2000, (1500, 1400, 1500, 1300, 1200, 1300, 1500, 1400, 1500), dt.date(2024, 5, 1)
)
LIMITS = SafetyGuard.from_profile(PROFILE).electrode_limits(32)
FAST = settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])

command_bytes = st.one_of(st.integers(0xF5, 0xFF), st.integers(0, 3), st.integers(0, 255))
streams = st.lists(command_bytes, max_size=300).map(bytes)
anything = st.one_of(
    st.none(),
    st.booleans(),
    st.integers(-(2**70), 2**70),
    st.floats(allow_nan=True, allow_infinity=True),
    st.text(max_size=5),
    st.binary(max_size=5),
    st.lists(st.integers(-3, 300), max_size=3),
    st.decimals(allow_nan=True, allow_infinity=True),
)


def within_limits(emu: Emulator) -> bool:
    s = emu.state()
    h = s.pulse_height * 10
    n = s.electrode_num
    for ch in range(min(n, 32)):
        level = s.stim_pattern[ch]
        if level in (1, 2) and h > LIMITS[ch]:
            return False
        if level not in (1, 2) and s.sense_pulse_height * 10 > LIMITS[ch]:
            return False
    return not (n > 32 and h > 0 and any(v in (1, 2) for v in s.stim_pattern[32:n]))


# --- the decoder --------------------------------------------------------------------------------------------


@FAST
@given(data=streams, electrode_num=st.integers(0, 255), cuts=st.lists(st.integers(0, 300), max_size=8))
def test_decoder_streams_any_bytes_split_anywhere(data: bytes, electrode_num: int, cuts: list[int]) -> None:
    CASES["decoder"] += 1
    whole = decode(data, electrode_num)
    assert b"".join(i.raw for i in whole) == data
    dec = StreamDecoder(electrode_num)
    items = []
    points = sorted({min(c, len(data)) for c in cuts} | {0, len(data)})
    for a, b in zip(points, points[1:]):
        items += dec.feed(data[a:b])
    items += dec.finish()
    assert b"".join(i.raw for i in items) == data


# --- the emulators -----------------------------------------------------------------------------------------


@FAST
@given(chunks=st.lists(streams, max_size=4), reset_at=st.integers(-1, 3))
def test_emulator_takes_any_stream(chunks: list[bytes], reset_at: int) -> None:
    CASES["emulator"] += 1
    emu = Emulator()
    for i, c in enumerate(chunks):
        if i == reset_at:
            emu.reset()
        emu.feed(c)
        s = emu.state()
        assert 0 <= s.pulse_height <= 4095 and s.polarity in (0, 1) and len(s.stim_pattern) == 256
        assert 0 <= s.electrode_num <= 255


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    data=st.lists(command_bytes, max_size=120).map(bytes),
    gap_us=st.floats(0, 3000),
    link=st.sampled_from(["usb", "uart"]),
)
def test_timed_emulator_takes_any_stream(data: bytes, gap_us: float, link: str) -> None:
    CASES["timed_emulator"] += 1
    emu = TimedEmulator(link=link)
    half = len(data) // 2
    emu.write(data[:half])
    emu.advance(gap_us)
    emu.write(data[half:])
    emu.advance(20_000)
    assert emu.now_us >= 20_000
    for lo in emu.losses:
        assert lo.count > 0


# --- profiles ----------------------------------------------------------------------------------------------

profile_values = st.dictionaries(
    st.sampled_from(
        [
            "version",
            "participant",
            "cap_ua",
            "regions_ua",
            "pulse_width_us",
            "polarity",
            "contact_mode",
            "calibrated_on",
            "max_charge_nc",
            "ramp_ua_per_frame",
            "notes",
            "extra",
        ]
    ),
    anything,
    max_size=12,
)


@FAST
@given(data=profile_values)
def test_profile_loader_never_crashes(data: dict[str, Any]) -> None:
    CASES["profile"] += 1
    base = PROFILE.to_dict()
    base.update(data)
    try:
        prof = profile_from_dict(base)
    except TactDeformError as exc:
        assert "participant profile" in str(exc)
        return
    assert 0 <= prof.cap_ua <= 10_000 and all(0 <= r <= prof.cap_ua for r in prof.regions_ua)


# --- the driver API ----------------------------------------------------------------------------------------


def configured() -> tuple[EtactileKitDevice, RecordingPort]:
    port = RecordingPort()
    dev = EtactileKitDevice(port, guard=SafetyGuard.from_profile(PROFILE))
    dev.configure(StimConfig(current_ua=1500))
    return dev, port


@FAST
@given(value=anything)
def test_set_current_with_anything(value: Any) -> None:
    CASES["set_current"] += 1
    dev, port = configured()
    dev.send_pattern([1 if r in (0, 4) else 0 for r in range(32)])
    n = len(port.writes)
    try:
        dev.set_current(value)
    except TactDeformError:
        assert len(port.writes) == n  # refused: nothing written
    else:
        assert isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)
    assert within_limits(port.emulator)


@FAST
@given(
    levels=st.one_of(
        st.lists(anything, max_size=40), st.lists(st.integers(-2, 4), min_size=30, max_size=34), anything
    )
)
def test_send_pattern_with_anything(levels: Any) -> None:
    CASES["send_pattern"] += 1
    dev, port = configured()
    n = len(port.writes)
    try:
        dev.send_pattern(levels)
    except TactDeformError:
        assert len(port.writes) == n
    else:
        assert list(port.emulator.state().stim_pattern[:32]) == list(levels)
    assert within_limits(port.emulator)


stim_fields = st.fixed_dictionaries(
    {},
    optional={
        "electrode_count": anything | st.integers(0, 300),
        "current_ua": anything | st.integers(-100, 12_000).map(lambda v: v - v % 10),
        "pulse_width_us": anything | st.integers(0, 70_000),
        "discharge_us": anything | st.integers(0, 300),
        "rate_hz": anything | st.integers(0, 70_000),
        "polarity": anything | st.sampled_from(["anodic", "cathodic"]),
        "sense_current_ua": anything | st.integers(0, 1100).map(lambda v: v - v % 40),
        "sense_width_us": anything | st.integers(0, 300),
    },
)


@settings(max_examples=200, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(fields=stim_fields)
def test_configure_with_anything(fields: dict[str, Any]) -> None:
    CASES["configure"] += 1
    port = RecordingPort()
    dev = EtactileKitDevice(port, guard=SafetyGuard.from_profile(PROFILE))
    opened = len(port.writes)  # the proof that the parser is in step, at open
    try:
        dev.configure(StimConfig(**fields))
    except TactDeformError:
        assert len(port.writes) == opened
        return
    assert within_limits(port.emulator)
    assert all(h.kind.value == "channels_beyond_hv513" for h in defects(port.emulator.hazards))


@FAST
@given(data=streams)
def test_interlock_accepts_no_unsafe_write(data: bytes) -> None:
    """Raw bytes through the device's single exit: refused, or the firmware stays within every limit."""
    CASES["interlock"] += 1
    dev, port = configured()
    dev.send_pattern([1 if r == 0 else 0 for r in range(32)])
    n = len(port.writes)
    try:
        dev._send(data)
    except TactDeformError:
        assert len(port.writes) == n
        return
    assert within_limits(port.emulator), data.hex()
