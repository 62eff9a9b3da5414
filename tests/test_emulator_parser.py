"""Firmware parser behaviour, defect by defect, and the structured hazard records."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from tactdeform_hw.emulator import CallResult, Emulator, HazardKind


def kinds(emu: Emulator) -> list[str]:
    return [h.kind.value for h in emu.hazards]


def test_power_on_state() -> None:
    s = Emulator().state()
    assert s.electrode_num == 0 and s.polarity == 1 and s.period_us == 10_000.0
    assert s.timer_alarm_ticks == 20_000 and s.hv513_num == 4 and s.rx_pending == 0
    assert list(s.stim_pattern) == [0] * 256


def test_zero_electrode_pattern_locks_the_parser() -> None:
    emu = Emulator()
    emu.feed(b"\xfe")
    assert emu.locked
    emu.feed(b"\xfc\x20\xfb\x10\x00")
    s = emu.state()
    assert s.electrode_num == 0 and s.pulse_height == 0 and s.rx_pending == 5
    assert HazardKind.PARSER_LOCKED in [h.kind for h in emu.hazards]
    assert HazardKind.UNREAD_WHILE_LOCKED in [h.kind for h in emu.hazards]
    lock = next(h for h in emu.hazards if h.kind is HazardKind.PARSER_LOCKED)
    assert lock.offset == 0


def test_truncated_pattern_desynchronises_then_zeros_resync() -> None:
    """The spec's check: a pattern cut after 10 of 32 bytes, then 256 zeros, then a pulse height."""
    emu = Emulator()
    emu.feed(b"\xfc\x20" + b"\xfe" + b"\x01" * 10)
    emu.feed(bytes(256))
    emu.feed(b"\xfb\x64\x00")
    s = emu.state()
    assert list(s.stim_pattern[:10]) == [1] * 10 and list(s.stim_pattern[10:32]) == [0] * 22
    assert s.pulse_height == 100 and s.rx_pending == 0


def test_truncated_command_swallows_next_command_byte() -> None:
    emu = Emulator()
    emu.feed(b"\xfc\x04\xfe\x01\x01")  # pattern cut after 2 of 4 bytes
    emu.feed(b"\xfb\x10\x00")  # pulse height: its bytes become pattern payload
    s = emu.state()
    assert list(s.stim_pattern[:4]) == [1, 1, 0xFB, 0x10]
    assert s.pulse_height == 0 and s.rx_pending == 0  # the trailing 0x00 was an unknown byte
    assert HazardKind.PATTERN_HOLDS_COMMAND_BYTE in [h.kind for h in emu.hazards]


def test_half_received_u16_keeps_its_low_byte_through_zeros() -> None:
    emu = Emulator()
    emu.feed(b"\xfb\xdc")
    assert emu.state().rx_pending == 1
    assert emu.hazards[-1].kind is HazardKind.U16_WAITING
    emu.feed(bytes(256))
    assert emu.state().pulse_height == 220


def test_stale_channels_come_back() -> None:
    emu = Emulator()
    emu.feed(b"\xfc\x08\xfe" + bytes([1] * 8))
    emu.feed(b"\xfc\x04\xfe" + bytes(4))
    emu.feed(b"\xfc\x08")
    s = emu.state()
    assert list(s.stim_pattern[:8]) == [0, 0, 0, 0, 1, 1, 1, 1]
    stale = [h for h in emu.hazards if h.kind is HazardKind.STALE_CHANNELS]
    assert stale and stale[-1].detail["channels"] == {4: 1, 5: 1, 6: 1, 7: 1}


def test_clamping_and_ignored_zeros() -> None:
    emu = Emulator()
    emu.feed(b"\xfd\x07\xfb\xff\xff\xfa\x00\x00\xf6\x00\x00")
    s = emu.state()
    assert s.polarity == 1 and s.pulse_height == 4095 and s.pulse_width_us == 0
    assert s.period_us == 10_000.0
    assert kinds(emu).count("clamped") == 2 and kinds(emu).count("ignored_zero") == 2


def test_sense_height_is_shifted() -> None:
    emu = Emulator()
    emu.feed(b"\xf9\xff")
    assert emu.state().sense_pulse_height == 1020


@pytest.mark.parametrize("rate", [1, 3, 7, 125, 333, 65535])
def test_period_is_float32_and_ticks_truncate(rate: int) -> None:
    emu = Emulator()
    emu.feed(bytes([0xF6, rate & 0xFF, rate >> 8]))
    s = emu.state()
    assert s.period_us == float(np.float32(1e6) / np.float32(rate))
    assert s.timer_alarm_ticks == int(s.period_us) * 2


@pytest.mark.parametrize(
    ("kind", "boards", "expected"),
    [
        ("compact", 0, 0),
        ("compact", 1, 4),
        ("compact", 2, 8),
        ("large", 0, 1),
        ("large", 1, 8),
        ("large", 3, 24),
    ],
)
def test_hv513_count_by_board(kind: str, boards: int, expected: int) -> None:
    emu = Emulator(kind, boards)
    assert emu.feed(b"\xf5") == bytes([expected])
    assert emu.state().hv513_num == expected
    assert emu.hazards[-1].kind is HazardKind.HV513_REINIT


def test_measure_reply_length_and_unknown_bytes() -> None:
    emu = Emulator()
    emu.feed(b"\xfc\x05")
    assert emu.feed(b"\xff") == bytes(10)  # voltages are 0 until a scan runs
    assert emu.feed(b"\x00\x01\x02") == b""
    assert emu.hazards[-1].kind is HazardKind.UNKNOWN_BYTES and emu.hazards[-1].detail == {"count": 3}


def test_one_call_at_a_time_matches_the_fast_path() -> None:
    data = b"\xfc\x04\xfe\x01\x02\x00\x01\xff\x13\xfb\x10\x00\xf5"
    fast = Emulator()
    fast_tx = fast.feed(data)
    slow = Emulator()
    slow.parser.receive(data)
    results = []
    while True:
        r = slow.parser.step()
        results.append(r)
        if r is CallResult.IDLE:
            break
    assert slow.state() == fast.state()
    assert slow.parser.take_tx() == fast_tx == bytes(8) + b"\x04"
    # the rhythm: one command with a payload per call, each ending in the 1 ms sleep
    assert [r.name for r in results] == [
        "COMPLETED",
        "COMPLETED",
        "REPLIED",
        "IGNORED",
        "COMPLETED",
        "REPLIED",
        "IDLE",
    ]
    assert [r.slept for r in results] == [True, True, False, False, True, False, True]


def test_state_is_a_frozen_copy() -> None:
    """A state read earlier does not follow the board: later commands leave it as it was."""
    emu = Emulator()
    s = emu.state()
    emu.feed(b"\xfc\x01\xfe\x09")
    assert s.stim_pattern[0] == 0 and s.electrode_num == 0
    assert emu.state().stim_pattern[0] == 9
    with pytest.raises(dataclasses.FrozenInstanceError):
        s.electrode_num = 3  # type: ignore[misc]


def test_reset_returns_to_power_on_but_keeps_history() -> None:
    emu = Emulator()
    emu.feed(b"\xfe")
    emu.reset()
    assert not emu.locked and emu.state().rx_pending == 0
    assert emu.hazards  # history stays
