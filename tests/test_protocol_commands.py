"""construct formats (plain and compiled), the fast encoders, limits and replies."""

from __future__ import annotations

import json
import random

import pytest

from tactdeform_hw import protocol as p
from tactdeform_hw.errors import DecodeError, LimitError
from tactdeform_hw.protocol import commands as c
from tactdeform_hw.protocol.constants import Opcode

from .conftest import DATA

U8_FIELDS = [Opcode.POLARITY, Opcode.ELECTRODE_NUM, Opcode.SENSE_HEIGHT, Opcode.SENSE_WIDTH, Opcode.DISCHARGE]
U16_FIELDS = [Opcode.PULSE_HEIGHT, Opcode.PULSE_WIDTH, Opcode.FREQUENCY]


@pytest.mark.parametrize("use_compiled", [False, True])
@pytest.mark.parametrize("op", U8_FIELDS + U16_FIELDS)
def test_parse_build_size_fixed(op: Opcode, use_compiled: bool) -> None:
    fmt = c.compiled(op) if use_compiled else c.FORMATS[op]
    field = c.FIELD_NAME[op]
    value = 0xA5 if op in U8_FIELDS else 0x1234
    data = c.build(op, value, use_compiled=use_compiled)
    assert data[0] == op
    assert data[1:] == (bytes([value]) if op in U8_FIELDS else b"\x34\x12")
    assert fmt.parse(data)[field] == value
    assert fmt.sizeof() == len(data)


@pytest.mark.parametrize("use_compiled", [False, True])
def test_pattern_format_takes_length_from_electrode_num(use_compiled: bool) -> None:
    fmt = c.compiled(Opcode.PATTERN) if use_compiled else c.PatternCommand
    data = fmt.build({"levels": b"\x01\x02\x00"}, electrode_num=3)
    assert data == b"\xfe\x01\x02\x00"
    assert fmt.parse(data, electrode_num=3).levels == b"\x01\x02\x00"
    assert fmt.sizeof(electrode_num=32) == 33


def test_formats_against_golden_bytes() -> None:
    """Commands cut from the golden streams parse with the generic format, plain and compiled."""
    compiled_any = c.AnyCommand.compile()
    seen: set[int] = set()
    for line in (DATA / "protocol_vectors.jsonl").read_text().splitlines()[:60]:
        data = bytes.fromhex(json.loads(line)["stream"])
        electrodes = 0
        for item in p.decode(data):
            if item.status != "ok":
                break
            plain = c.parse(item.raw, electrode_num=electrodes)
            comp = compiled_any.parse(item.raw, electrode_num=electrodes)
            assert plain["opcode"] == comp.opcode == item.opcode
            assert plain["value"] == comp.payload
            if isinstance(item.value, int):
                assert plain["value"] == item.value
            if item.opcode == Opcode.ELECTRODE_NUM:
                electrodes = item.value
            seen.add(item.opcode)
    assert {Opcode.PATTERN, Opcode.PULSE_HEIGHT, Opcode.FREQUENCY, Opcode.MEASURE} <= seen


def test_fast_encoders_match_construct_on_random_inputs() -> None:
    rng = random.Random(1234)
    encoders = {
        Opcode.POLARITY: (c.encode_polarity, 0, 1),
        Opcode.ELECTRODE_NUM: (c.encode_electrode_num, 0, 255),
        Opcode.PULSE_HEIGHT: (c.encode_pulse_height, 0, 65535),
        Opcode.PULSE_WIDTH: (c.encode_pulse_width, 1, 65535),
        Opcode.SENSE_HEIGHT: (c.encode_sense_height, 0, 255),
        Opcode.SENSE_WIDTH: (c.encode_sense_width, 0, 255),
        Opcode.DISCHARGE: (c.encode_discharge, 0, 255),
        Opcode.FREQUENCY: (c.encode_frequency, 1, 65535),
    }
    for op, (fn, lo, hi) in encoders.items():
        for v in [lo, hi] + [rng.randint(lo, hi) for _ in range(300)]:
            assert fn(v) == c.build(op, v) == c.build(op, v, use_compiled=True)
    for _ in range(500):
        n = rng.randint(1, 255)
        levels = [rng.randint(0, 255) for _ in range(n)]
        assert (
            c.encode_pattern(levels)
            == c.build(Opcode.PATTERN, levels)
            == c.build(Opcode.PATTERN, levels, use_compiled=True)
        )
    for _ in range(100):
        adc = [rng.randint(0, 65535) for _ in range(rng.randint(0, 64))]
        assert c.encode_measure_reply(adc) == c.build_measure_reply(adc)


@pytest.mark.parametrize(
    ("fn", "value", "field"),
    [
        (c.encode_pulse_width, 0, "pulse_width_us"),
        (c.encode_pulse_width, 65536, "pulse_width_us"),
        (c.encode_frequency, 0, "rate_hz"),
        (c.encode_frequency, -1, "rate_hz"),
        (c.encode_polarity, 2, "polarity"),
        (c.encode_discharge, 256, "discharge_us"),
        (c.encode_electrode_num, 300, "electrode_num"),
        (c.encode_discharge, 4.5, "discharge_us"),
        (c.encode_discharge, float("nan"), "discharge_us"),
        (c.encode_discharge, True, "discharge_us"),
        (c.encode_discharge, "45", "discharge_us"),
    ],
)
def test_out_of_range_values_name_field_value_and_limit(fn, value, field: str) -> None:  # type: ignore[no-untyped-def]
    with pytest.raises(LimitError) as err:
        fn(value)
    assert err.value.field == field
    assert field in str(err.value) and repr(value) in str(err.value)


def test_pattern_limits() -> None:
    with pytest.raises(LimitError, match="pattern\\[2\\]"):
        c.encode_pattern([1, 0, 256])
    with pytest.raises(LimitError, match="exactly electrode_num = 4"):
        c.encode_pattern([1, 0, 1], electrode_num=4)
    with pytest.raises(LimitError, match="at most 255"):
        c.encode_pattern(bytes(256))
    for bad in (None, 5, "0101", 1.5):
        with pytest.raises(LimitError, match="pattern"):
            c.encode_pattern(bad)  # type: ignore[arg-type]


def test_construct_overflow_is_a_limit_error() -> None:
    with pytest.raises(LimitError, match="pulse_height"):
        c.build(Opcode.PULSE_HEIGHT, 70000)


def test_replies() -> None:
    assert p.parse_hv513_reply(b"\x04") == 4
    assert p.parse_measure_reply(b"\x01\x00\xff\x0f", 2) == [1, 4095]
    with pytest.raises(DecodeError):
        p.parse_measure_reply(b"\x01", 2)
    with pytest.raises(DecodeError):
        p.parse_hv513_reply(b"")


def test_current_transfer() -> None:
    t = p.DEFAULT_TRANSFER
    assert t.to_code(10_000) == 1000 and t.to_code(0) == 0 and t.to_ua(250) == 2500
    with pytest.raises(LimitError, match="multiple of 10"):
        t.to_code(15)
    with pytest.raises(LimitError, match="0 to 10000"):
        t.to_code(10_010)
    cal = p.CurrentTransfer(ua_per_code=2.5)
    assert cal.to_code(100) == 40
    with pytest.raises(LimitError, match="DAC code"):
        p.CurrentTransfer(ua_per_code=1.0).to_code(5000)
