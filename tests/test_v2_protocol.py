"""Firmware v2's construct formats (plain and compiled), its fast encoders, limits and replies."""

from __future__ import annotations

import json
import random

import pytest

from tactdeform_hw.emulator import Emulator
from tactdeform_hw.errors import DecodeError, LimitError
from tactdeform_hw.protocol import commands_v2 as c
from tactdeform_hw.protocol.firmware import V2, OpcodeV2

from .conftest import DATA

U8 = [
    OpcodeV2.POLARITY,
    OpcodeV2.ELECTRODE_NUM,
    OpcodeV2.STIM_MODE,
    OpcodeV2.SENSE_HEIGHT,
    OpcodeV2.SENSE_WIDTH,
    OpcodeV2.DISCHARGE,
]
U16 = [OpcodeV2.PULSE_WIDTH, OpcodeV2.FREQUENCY]
NO_PAYLOAD = [OpcodeV2.MEASURE, OpcodeV2.HV513_COUNT, OpcodeV2.SYNC_CHECK]


def test_formats_cover_the_v2_table() -> None:
    assert set(c.FORMATS) == set(V2.by_opcode)
    for op, fmt in c.FORMATS.items():
        kind = V2.by_opcode[op].kind
        if kind in ("u8", "u16", None):
            assert fmt.sizeof() == 1 + V2.size_of(op, 0)


@pytest.mark.parametrize("use_compiled", [False, True])
@pytest.mark.parametrize("op", U8 + U16)
def test_parse_build_size_fixed(op: OpcodeV2, use_compiled: bool) -> None:
    fmt = c.compiled(op) if use_compiled else c.FORMATS[op]
    field = c.FIELD_NAME[op]
    value = 0x02 if op in U8 else 0x1234
    data = c.build(op, value, use_compiled=use_compiled)
    assert data[0] == op
    assert data[1:] == (bytes([value]) if op in U8 else b"\x34\x12")
    assert fmt.parse(data)[field] == value
    assert fmt.sizeof() == len(data)


@pytest.mark.parametrize("use_compiled", [False, True])
@pytest.mark.parametrize("op", NO_PAYLOAD)
def test_requests(op: OpcodeV2, use_compiled: bool) -> None:
    assert c.build(op, use_compiled=use_compiled) == bytes([op])


@pytest.mark.parametrize("use_compiled", [False, True])
def test_pattern_is_one_u16_per_electrode(use_compiled: bool) -> None:
    fmt = c.compiled(OpcodeV2.PATTERN) if use_compiled else c.PatternCommand
    data = fmt.build({"heights": [1, 300, 4095]}, electrode_num=3)
    assert data == bytes.fromhex("fe01002c01ff0f")
    assert list(fmt.parse(data, electrode_num=3).heights) == [1, 300, 4095]
    assert fmt.sizeof(electrode_num=32) == 65


def test_fast_encoders_equal_construct() -> None:
    rng = random.Random(7)
    for _ in range(300):
        n = rng.randint(0, 40)
        heights = [rng.randint(0, 4095) for _ in range(n)]
        for use_compiled in (False, True):
            assert c.encode_pattern(heights) == c.build(OpcodeV2.PATTERN, heights, use_compiled=use_compiled)
        mode, width, rate = rng.randint(0, 2), rng.randint(0, 65535), rng.randint(1, 65535)
        byte = rng.randint(0, 255)
        assert c.encode_stim_mode(mode) == c.build(OpcodeV2.STIM_MODE, mode)
        assert c.encode_pulse_width(width) == c.build(OpcodeV2.PULSE_WIDTH, width, use_compiled=True)
        assert c.encode_frequency(rate) == c.build(OpcodeV2.FREQUENCY, rate)
        assert c.encode_sense_height(byte) == c.build(OpcodeV2.SENSE_HEIGHT, byte)
        assert c.encode_sense_width(byte) == c.build(OpcodeV2.SENSE_WIDTH, byte)
        assert c.encode_discharge(byte) == c.build(OpcodeV2.DISCHARGE, byte)
        assert c.encode_polarity(byte & 1) == c.build(OpcodeV2.POLARITY, byte & 1)
        assert c.encode_electrode_num(byte) == c.build(OpcodeV2.ELECTRODE_NUM, byte)


def test_encoders_refuse_naming_field_value_and_limit() -> None:
    with pytest.raises(LimitError, match=r"heights\[1\].*4096.*0 to 4095"):
        c.encode_pattern([1, 4096])
    with pytest.raises(LimitError, match=r"heights\[0\].*1001.*0 to 1000"):
        c.encode_pattern([1001], limit=1000)
    with pytest.raises(LimitError, match="stim_mode.*3"):
        c.encode_stim_mode(3)
    with pytest.raises(LimitError, match="exactly electrode_num = 4"):
        c.encode_pattern([1, 2], electrode_num=4)
    with pytest.raises(LimitError, match="rate_hz"):
        c.encode_frequency(0)
    assert c.encode_pulse_width(0) == b"\xfa\x00\x00"  # v2 holds a width of 0


def test_what_the_encoders_send_is_what_v2_stores() -> None:
    emu = Emulator(firmware="v2")
    emu.feed(
        c.encode_electrode_num(3)
        + c.encode_stim_mode(1)
        + c.encode_pulse_width(0)
        + c.encode_sense_height(200)
        + c.encode_pattern([5, 4095, 0])
        + c.encode_frequency(125)
    )
    s = emu.state()
    assert (s.electrode_num, s.stim_mode, s.pulse_width_us, s.sense_pulse_height) == (3, 1, 0, 200)
    assert list(s.stim_pattern[:3]) == [5, 4095, 0] and s.timer_alarm_ticks == 16000
    assert emu.feed(c.SYNC_CHECK) == c.encode_sync_reply(3)
    assert c.parse_sync_reply(emu.feed(c.SYNC_CHECK)) == 3
    assert c.parse_measure_reply(emu.feed(c.MEASURE_REQUEST), 3) == [0, 0, 0]
    assert c.parse_hv513_reply(emu.feed(c.HV513_COUNT_REQUEST)) == 4


def test_reply_parsers_check_lengths() -> None:
    with pytest.raises(DecodeError, match="sync reply: expected 1 byte, got 0"):
        c.parse_sync_reply(b"")
    with pytest.raises(DecodeError, match="expected 4 bytes"):
        c.parse_measure_reply(b"\x00", 2)


def test_golden_streams_parse_with_the_generic_format() -> None:
    """Commands cut from v2 golden streams by the emulator's own parser parse alike, plain and compiled."""
    compiled_any = c.AnyCommand.compile()
    checked = 0
    for line in (DATA / "protocol_vectors_v2.jsonl").read_text().splitlines()[:80]:
        vector = json.loads(line)
        if "arrivals" in vector:
            continue
        data = bytes.fromhex(vector["stream"])
        emu = Emulator(firmware="v2")
        seen: list[tuple[int, object, int, int]] = []
        emu.parser.on_command = lambda op, value, off, s=seen, e=emu: s.append(
            (op, value, off, e.registers.electrode_num)
        )
        emu.feed(data)
        for op, value, off, _n in seen:
            size = V2.size_of(op, 0)
            if op == OpcodeV2.PATTERN:
                assert isinstance(value, list)
                raw = data[off : off + 1 + 2 * len(value)]
                got = c.parse(raw, electrode_num=len(value))
                comp = compiled_any.parse(raw, electrode_num=len(value))
                assert [min(v, 4095) for v in got["value"]] == value == [min(v, 4095) for v in comp.payload]
            elif size:
                raw = data[off : off + 1 + size]
                assert c.parse(raw)["value"] == value == compiled_any.parse(raw).payload
            checked += 1
    assert checked > 200
