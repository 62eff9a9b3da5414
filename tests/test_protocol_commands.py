"""Each firmware's construct formats (plain and compiled), its fast encoders, limits and replies.

The formats and encoders are built from the firmware tables, so what does not depend on the version runs
over every table in ``FIRMWARES``; each version's own facts (its byte layouts, its limits) are named below.
"""

from __future__ import annotations

import json
import random
from dataclasses import replace

import pytest

from tactdeform_hw import protocol as p
from tactdeform_hw.emulator import Emulator
from tactdeform_hw.errors import ConfigurationError, DecodeError, LimitError
from tactdeform_hw.protocol import commands as c
from tactdeform_hw.protocol.commands import V1_2_COMMANDS, V2_COMMANDS, FirmwareCommands, commands_for
from tactdeform_hw.protocol.constants import Opcode
from tactdeform_hw.protocol.firmware import FIRMWARES, V1_2, V2, FirmwareSpec, OpcodeV2

from .conftest import DATA

ALL = pytest.mark.parametrize("fw", list(FIRMWARES.values()), ids=list(FIRMWARES))

#: The encoder of each u8/u16 register, and the lowest and highest value it accepts, per version (v1.2
#: refuses a pulse width of 0, which it ignores; v2 stores it.  The pulse height's ceiling is the caller's
#: ``limit``, 65535 by default).
ENCODERS: dict[str, dict[str, tuple[str, int, int]]] = {
    "v1.2": {
        "polarity": ("encode_polarity", 0, 1),
        "electrode_num": ("encode_electrode_num", 0, 255),
        "pulse_height": ("encode_pulse_height", 0, 65535),
        "pulse_width": ("encode_pulse_width", 1, 65535),
        "sense_pulse_height": ("encode_sense_height", 0, 255),
        "sense_pulse_width": ("encode_sense_width", 0, 255),
        "discharge_time": ("encode_discharge", 0, 255),
        "frequency": ("encode_frequency", 1, 65535),
    },
    "v2": {
        "polarity": ("encode_polarity", 0, 1),
        "electrode_num": ("encode_electrode_num", 0, 255),
        "stim_mode": ("encode_stim_mode", 0, 2),
        "pulse_width": ("encode_pulse_width", 0, 65535),
        "sense_pulse_height": ("encode_sense_height", 0, 255),
        "sense_pulse_width": ("encode_sense_width", 0, 255),
        "discharge_time": ("encode_discharge", 0, 255),
        "frequency": ("encode_frequency", 1, 65535),
    },
}
#: How each version names a pattern's elements in its errors.
PATTERN_LABEL = {"v1.2": "pattern", "v2": "heights"}


def scalar_ops(fw: FirmwareSpec) -> list[int]:
    return [cmd.opcode for cmd in fw.commands if cmd.kind in ("u8", "u16")]


def test_every_version_is_listed_here() -> None:
    assert set(ENCODERS) == set(PATTERN_LABEL) == set(FIRMWARES)


def test_the_module_level_names_are_v12s() -> None:
    assert commands_for(V1_2) is V1_2_COMMANDS and commands_for(V2) is V2_COMMANDS
    assert c.AnyCommand is V1_2_COMMANDS.AnyCommand and c.FORMATS is V1_2_COMMANDS.FORMATS
    assert c.encode_pattern(b"\x01\x02") == V1_2_COMMANDS.encode_pattern(b"\x01\x02") == b"\xfe\x01\x02"
    assert (c.MEASURE_REQUEST, c.HV513_COUNT_REQUEST) == (b"\xff", b"\xf5")
    assert p.encode_frequency(125) == V1_2_COMMANDS.encode_frequency(125) and p.AnyCommand is c.AnyCommand


@ALL
def test_formats_cover_the_table(fw: FirmwareSpec) -> None:
    cmds = commands_for(fw)
    assert set(cmds.FORMATS) == set(cmds.FIELD_NAME) == set(fw.by_opcode)
    for op, fmt in cmds.FORMATS.items():
        if fw.by_opcode[op].kind != "pattern":
            assert fmt.sizeof() == 1 + fw.size_of(op, 0)
        assert (cmds.FIELD_NAME[op] is None) == (fw.by_opcode[op].kind is None)


@ALL
@pytest.mark.parametrize("use_compiled", [False, True])
def test_parse_build_size_fixed(fw: FirmwareSpec, use_compiled: bool) -> None:
    cmds = commands_for(fw)
    for op in scalar_ops(fw):
        u8 = fw.by_opcode[op].kind == "u8"
        fmt = cmds.compiled(op) if use_compiled else cmds.FORMATS[op]
        field = cmds.FIELD_NAME[op]
        assert field == fw.by_opcode[op].register
        value = 0xA5 if u8 else 0x1234
        data = cmds.build(op, value, use_compiled=use_compiled)
        assert data[0] == op
        assert data[1:] == (bytes([value]) if u8 else b"\x34\x12")
        assert fmt.parse(data)[field] == value
        assert fmt.sizeof() == len(data)


@ALL
@pytest.mark.parametrize("use_compiled", [False, True])
def test_requests(fw: FirmwareSpec, use_compiled: bool) -> None:
    cmds = commands_for(fw)
    ops = [cmd.opcode for cmd in fw.commands if cmd.kind is None]
    assert ops and all(fw.by_opcode[op].reply for op in ops)
    for op in ops:
        assert cmds.build(op, use_compiled=use_compiled) == bytes([op])
        assert cmds.request(fw.by_opcode[op].reply or "") == bytes([op])
    assert cmds.MEASURE_REQUEST == b"\xff" and cmds.HV513_COUNT_REQUEST == b"\xf5"


def test_v2_alone_answers_the_sync_check() -> None:
    assert V2_COMMANDS.SYNC_CHECK == b"\xf4"
    with pytest.raises(ConfigurationError, match=r"firmware v1\.2 has no command answering 'sync'"):
        _ = V1_2_COMMANDS.SYNC_CHECK


@pytest.mark.parametrize("use_compiled", [False, True])
def test_v12_pattern_is_one_byte_per_electrode(use_compiled: bool) -> None:
    fmt = c.compiled(Opcode.PATTERN) if use_compiled else c.PatternCommand
    data = fmt.build({"levels": b"\x01\x02\x00"}, electrode_num=3)
    assert data == b"\xfe\x01\x02\x00"
    assert fmt.parse(data, electrode_num=3).levels == b"\x01\x02\x00"
    assert fmt.sizeof(electrode_num=32) == 33


@pytest.mark.parametrize("use_compiled", [False, True])
def test_v2_pattern_is_one_u16_per_electrode(use_compiled: bool) -> None:
    v2 = V2_COMMANDS
    fmt = v2.compiled(OpcodeV2.PATTERN) if use_compiled else v2.PatternCommand
    data = fmt.build({"heights": [1, 300, 4095]}, electrode_num=3)
    assert data == bytes.fromhex("fe01002c01ff0f")
    assert list(fmt.parse(data, electrode_num=3).heights) == [1, 300, 4095]
    assert fmt.sizeof(electrode_num=32) == 65


@ALL
def test_fast_encoders_match_construct_on_random_inputs(fw: FirmwareSpec) -> None:
    cmds = commands_for(fw)
    rng = random.Random(1234)
    encoders = ENCODERS[fw.name]
    assert {fw.by_opcode[op].register for op in scalar_ops(fw)} == set(encoders)
    for register, (name, lo, hi) in encoders.items():
        op = fw.opcode_of(register)
        fn = getattr(cmds, name)
        for v in [lo, hi] + [rng.randint(lo, hi) for _ in range(300)]:
            assert fn(v) == cmds.build(op, v) == cmds.build(op, v, use_compiled=True)
        for bad in (lo - 1, hi + 1):
            with pytest.raises(LimitError):
                fn(bad)
    top = fw.pattern_level_max()
    for n in [0, fw.max_electrodes] + [rng.randint(1, fw.max_electrodes) for _ in range(300)]:
        levels = [rng.randint(0, top) for _ in range(n)]
        assert (
            cmds.encode_pattern(levels)
            == cmds.build(fw.pattern_command.opcode, levels)
            == cmds.build(fw.pattern_command.opcode, levels, use_compiled=True)
        )
        assert len(cmds.encode_pattern(levels)) == 1 + fw.size_of(fw.pattern_command.opcode, n)


def test_fast_replies_match_construct() -> None:
    rng = random.Random(1234)
    for _ in range(100):
        adc = [rng.randint(0, 65535) for _ in range(rng.randint(0, 64))]
        assert c.encode_measure_reply(adc) == c.build_measure_reply(adc)
        data = c.build_measure_reply(adc)
        assert c.parse_measure_reply(data, len(adc)) == list(
            c.MeasureReply.parse(data, electrode_num=len(adc)).adc
        )


@ALL
@pytest.mark.parametrize(
    ("name", "value", "field"),
    [
        ("encode_pulse_width", 65536, "pulse_width_us"),
        ("encode_frequency", 0, "rate_hz"),
        ("encode_frequency", -1, "rate_hz"),
        ("encode_polarity", 2, "polarity"),
        ("encode_discharge", 256, "discharge_us"),
        ("encode_electrode_num", 300, "electrode_num"),
        ("encode_sense_height", 256, "sense_height"),
        ("encode_sense_width", 256, "sense_width_us"),
        ("encode_discharge", 4.5, "discharge_us"),
        ("encode_discharge", float("nan"), "discharge_us"),
        ("encode_discharge", True, "discharge_us"),
        ("encode_discharge", "45", "discharge_us"),
    ],
)
def test_out_of_range_values_name_field_value_and_limit(
    fw: FirmwareSpec, name: str, value: object, field: str
) -> None:
    with pytest.raises(LimitError) as err:
        getattr(commands_for(fw), name)(value)
    assert err.value.field == field
    assert field in str(err.value) and repr(value) in str(err.value)


def test_each_version_refuses_what_its_firmware_would_not_store() -> None:
    with pytest.raises(LimitError, match="pulse_width_us=0"):
        c.encode_pulse_width(0)  # v1.2 ignores a width of 0
    assert V2_COMMANDS.encode_pulse_width(0) == b"\xfa\x00\x00"  # v2 holds it
    with pytest.raises(LimitError, match="stim_mode.*3"):
        V2_COMMANDS.encode_stim_mode(3)
    with pytest.raises(ConfigurationError, match=r"firmware v1\.2 has no command setting 'stim_mode'"):
        V1_2_COMMANDS.encode_stim_mode(0)
    with pytest.raises(ConfigurationError, match="firmware v2 has no command setting 'pulse_height'"):
        V2_COMMANDS.encode_pulse_height(100)
    with pytest.raises(LimitError, match=r"pulse_height=1001.*0 to 1000"):
        c.encode_pulse_height(1001, limit=1000)


@ALL
def test_pattern_limits(fw: FirmwareSpec) -> None:
    cmds = commands_for(fw)
    label = PATTERN_LABEL[fw.name]
    top = fw.pattern_level_max()
    with pytest.raises(LimitError, match=rf"{label}\[2\].*{top + 1}.*0 to {top}"):
        cmds.encode_pattern([1, 0, top + 1])
    with pytest.raises(LimitError, match=rf"{label}\[0\].*{top // 3 + 1}.*0 to {top // 3}"):
        cmds.encode_pattern([top // 3 + 1], limit=top // 3)
    assert cmds.encode_pattern([top // 3], limit=top // 3) == cmds.build(
        fw.pattern_command.opcode, [top // 3]
    )
    with pytest.raises(LimitError, match=rf"{label} length.*exactly electrode_num = 4"):
        cmds.encode_pattern([1, 0, 1], electrode_num=4)
    with pytest.raises(LimitError, match=rf"{label} length.*at most 255"):
        cmds.encode_pattern([0] * 256)
    for bad in (None, 5, "0101", 1.5):
        with pytest.raises(LimitError, match=label):
            cmds.encode_pattern(bad)  # type: ignore[arg-type]


def test_v12_takes_bytes_and_v2_refuses_them() -> None:
    """A v2 height is two bytes: bytes given as heights would be read as one byte each."""
    assert c.encode_pattern(bytearray(b"\x01\x02")) == b"\xfe\x01\x02"
    with pytest.raises(LimitError, match="at most 255"):
        c.encode_pattern(bytes(256))
    with pytest.raises(LimitError, match="heights"):
        V2_COMMANDS.encode_pattern(b"\x01\x02")


@ALL
def test_construct_overflow_is_a_limit_error(fw: FirmwareSpec) -> None:
    cmds = commands_for(fw)
    for op in scalar_ops(fw):
        cmd = fw.by_opcode[op]
        with pytest.raises(LimitError, match=f"{cmd.name.lower()}.{cmd.register}"):
            cmds.build(op, 70000)


def test_replies() -> None:
    assert p.parse_hv513_reply(b"\x04") == 4
    assert p.parse_measure_reply(b"\x01\x00\xff\x0f", 2) == [1, 4095]
    assert c.parse_sync_reply(c.encode_sync_reply(259)) == 3
    with pytest.raises(DecodeError, match="expected 4 bytes"):
        p.parse_measure_reply(b"\x01", 2)
    with pytest.raises(DecodeError):
        p.parse_hv513_reply(b"")
    with pytest.raises(DecodeError, match="sync reply: expected 1 byte, got 0"):
        c.parse_sync_reply(b"")


#: A value for each register the encoders set, and the value the emulated firmware reports for it.
SENT = {
    "electrode_num": 3,
    "polarity": 0,
    "pulse_height": 5000,
    "stim_mode": 7,
    "pulse_width": 200,
    "sense_pulse_height": 200,
    "sense_pulse_width": 20,
    "discharge_time": 45,
}


@ALL
def test_what_the_encoders_send_is_what_the_firmware_stores(fw: FirmwareSpec) -> None:
    """Every register the encoders set reaches the emulated firmware as its table says it stores it."""
    cmds = commands_for(fw)
    emu = Emulator(firmware=fw.name)
    stream = b""
    registers = [r for r in SENT if fw.has_register(r)]
    for register in registers:
        op = fw.opcode_of(register)
        value = SENT[register]
        stream += bytes([op]) + value.to_bytes(fw.size_of(op, 0), "little")  # past the host's refusals
    stream += cmds.encode_frequency(125)
    levels = [1, fw.pattern_level_max(), 0]
    stream += cmds.encode_pattern(levels)
    emu.feed(stream)
    s = emu.state().as_dict()
    for register in registers:
        assert s[register] == fw.command(fw.opcode_of(register)).stored(SENT[register]), register
    assert list(s["stim_pattern"][:3]) == levels and s["timer_alarm_ticks"] == 16000
    assert c.parse_measure_reply(emu.feed(cmds.MEASURE_REQUEST), 3) == [0, 0, 0]
    assert c.parse_hv513_reply(emu.feed(cmds.HV513_COUNT_REQUEST)) == 4
    if fw.answers_sync_check:
        assert emu.feed(cmds.SYNC_CHECK) == c.encode_sync_reply(3)


def test_what_the_v2_encoders_send_is_what_v2_stores() -> None:
    v2 = V2_COMMANDS
    emu = Emulator(firmware="v2")
    emu.feed(
        v2.encode_electrode_num(3)
        + v2.encode_stim_mode(1)
        + v2.encode_pulse_width(0)
        + v2.encode_sense_height(200)
        + v2.encode_pattern([5, 4095, 0])
        + v2.encode_frequency(125)
    )
    s = emu.state()
    assert (s.electrode_num, s.stim_mode, s.pulse_width_us, s.sense_pulse_height) == (3, 1, 0, 200)
    assert list(s.stim_pattern[:3]) == [5, 4095, 0] and s.timer_alarm_ticks == 16000
    assert v2.parse_sync_reply(emu.feed(v2.SYNC_CHECK)) == 3


def test_a_new_table_gets_its_formats_and_encoders_with_no_new_code() -> None:
    """A version whose command bytes moved (and whose pattern elements are 2 bytes): the formats, the
    generic parse and the encoders follow its table."""
    moved = replace(
        V1_2,
        name="v1.2-moved",
        commands=tuple(replace(cmd, opcode=cmd.opcode - 0x10) for cmd in V1_2.commands),
        pattern_bytes_per_electrode=2,
    )
    cmds = commands_for(moved)
    assert isinstance(cmds, FirmwareCommands) and commands_for(moved) is cmds
    assert cmds.encode_frequency(125) == b"\xe6\x7d\x00" == cmds.build(0xE6, 125)
    assert cmds.encode_pulse_width(300) == b"\xea\x2c\x01"
    assert cmds.encode_pattern([1, 258]) == b"\xee\x01\x00\x02\x01" == cmds.build(0xEE, [1, 258])
    assert cmds.parse(b"\xee\x01\x00\x02\x01", electrode_num=2) == {"opcode": 0xEE, "value": [1, 258]}
    assert cmds.parse(b"\xe9\x05") == {"opcode": 0xE9, "value": 5}
    assert cmds.parse(b"\xfe\x05") == {"opcode": 0xFE, "value": None}  # not a command byte of this table
    assert cmds.MEASURE_REQUEST == b"\xef"
    with pytest.raises(ConfigurationError, match="byte 0xFE is not a command of firmware v1.2-moved"):
        cmds.build(0xFE, 1)


def test_v12_golden_commands_parse_with_the_generic_format() -> None:
    """Commands cut from the golden streams by the decoder parse alike with the generic format, plain and
    compiled."""
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


def test_v2_golden_commands_parse_with_the_generic_format() -> None:
    """Commands cut from v2 golden streams by the emulator's own parser parse alike, plain and compiled."""
    v2 = V2_COMMANDS
    compiled_any = v2.AnyCommand.compile()
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
                got = v2.parse(raw, electrode_num=len(value))
                comp = compiled_any.parse(raw, electrode_num=len(value))
                assert [min(v, 4095) for v in got["value"]] == value == [min(v, 4095) for v in comp.payload]
            elif size:
                raw = data[off : off + 1 + size]
                assert v2.parse(raw)["value"] == value == compiled_any.parse(raw).payload
            checked += 1
    assert checked > 200


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
