"""The one reading of a byte stream (protocol.reader) agrees with the firmware's own parser: the golden
vectors and the emulator, on arbitrary streams, whole, resumed from any cut, and per firmware table."""

from __future__ import annotations

import json
from typing import Any

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from tactdeform_hw.emulator import Emulator
from tactdeform_hw.protocol import firmware_math as fm
from tactdeform_hw.protocol.firmware import FIRMWARES, V1_2, V2, FirmwareSpec
from tactdeform_hw.protocol.reader import (
    COMMAND,
    UNKNOWN,
    UNREAD,
    ParserState,
    iter_commands,
    read_commands,
)

from .conftest import DATA, shared_path

VECTORS = [
    json.loads(line) for line in (DATA / "protocol_vectors.jsonl").read_text().splitlines() if line.strip()
]
HV513_ONE_BOARD = 4  # the compact board with one switching board reports 4 chips
ALL = pytest.mark.parametrize("fw", list(FIRMWARES.values()), ids=list(FIRMWARES))

byte = st.one_of(st.integers(0xF5, 0xFF), st.integers(0, 3), st.integers(0, 255))
streams = st.lists(byte, max_size=400).map(bytes)


def registers_after(
    data: bytes, firmware: FirmwareSpec = V1_2, hv513: int = HV513_ONE_BOARD
) -> dict[str, Any]:
    """The firmware's variables after reading ``data`` from power-on, built only from the reader's items."""
    regs: dict[str, Any] = dict(firmware.power_on)
    regs["timer_alarm_ticks"] = fm.alarm_ticks(float(regs["period_us"]))
    regs["hv513_num"] = hv513
    pattern = [0] * firmware.pattern_buffer_size
    tx = bytearray()
    reading = read_commands(data, int(regs["electrode_num"]), firmware)
    for c in reading.commands:
        if c.kind != COMMAND or c.opcode is None:
            continue
        spec = firmware.command(c.opcode)
        if spec.reply == "measure":
            tx += bytes(firmware.reply_bytes(c.opcode, regs["electrode_num"]))  # voltages: 0 before any scan
            continue
        if spec.reply is not None:
            tx.append(hv513 if spec.reply == "hv513" else regs["electrode_num"] & 0xFF)
            continue
        if spec.kind == "pattern":
            if c.levels:
                pattern[c.start : c.start + len(c.levels)] = c.levels
            continue
        if not c.complete or c.value is None:
            continue
        if spec.register == "frequency":
            regs["period_us"] = fm.period_us_from_rate(c.value)
            regs["timer_alarm_ticks"] = fm.alarm_ticks(regs["period_us"])
        else:
            assert spec.register is not None
            regs[spec.register] = c.value
    end = reading.state
    if end.locked:
        pending = sum(len(c.raw) for c in reading.commands if c.kind == UNREAD)
    elif end.opcode is not None and (
        not firmware.partial_payload_applied or firmware.command(end.opcode).kind == "u16"
    ):
        # v2 reads a payload only when it is whole; v1.2 a u16 only when both bytes wait
        pending = len(end.got)
    else:
        pending = 0
    regs.update(
        stim_pattern=pattern, tx=tx.hex(), rx_pending=pending, command_in_progress=not end.at_boundary
    )
    return regs


@pytest.mark.parametrize("index", range(len(VECTORS)))
def test_reader_reaches_every_golden_state(index: int) -> None:
    vector = VECTORS[index]
    got = registers_after(bytes.fromhex(vector["stream"]))
    for key, value in vector["expect"].items():
        if key == "period_us":
            assert np.float32(got[key]) == np.float32(value)
        else:
            assert got[key] == value, key


def _v2_vectors() -> list[dict[str, Any]]:
    path = shared_path("golden", "protocol_vectors_v2.jsonl")
    vectors = [json.loads(line) for line in path.read_text().splitlines() if line.strip()]
    # the reader is untimed and has no queue: the vectors with arrival times, a 2 s timeout or a queue
    # overflow belong to the emulator's tests
    return [
        v
        for v in vectors
        if "arrivals" not in v and "final_time_us" not in v and not v["expect"]["rx_dropped"]
    ]


def test_reader_reaches_every_untimed_v2_golden_state() -> None:
    vectors = _v2_vectors()
    assert len(vectors) >= 240
    for vector in vectors:
        got = registers_after(bytes.fromhex(vector["stream"]), V2)
        for key, value in vector["expect"].items():
            if key == "rx_dropped":
                continue
            if key == "period_us":
                assert np.float32(got[key]) == np.float32(value), vector["id"]
            else:
                assert got[key] == value, (vector["id"], key)


def _emulator_state(data: bytes, firmware: FirmwareSpec) -> dict[str, Any]:
    emu = Emulator(firmware=firmware.name)
    tx = emu.feed(data)
    state = emu.state().as_dict()
    state["tx"] = tx.hex()
    return state


@ALL
@settings(max_examples=300, deadline=None)
@given(data=streams)
def test_reader_agrees_with_the_emulator_parser(fw: FirmwareSpec, data: bytes) -> None:
    assert list(iter_commands(data, 0, fw)) == list(read_commands(data, 0, fw).commands)
    mine = registers_after(data, fw)
    emu = _emulator_state(data, fw)
    registers = [k for k in fw.power_on if k != "period_us"]
    assert len(registers) == 7
    for key in (*registers, "timer_alarm_ticks", "stim_pattern", "tx", "rx_pending"):
        assert mine[key] == emu[key], key
    assert np.float32(mine["period_us"]) == np.float32(emu["period_us"])


@ALL
@settings(max_examples=300, deadline=None)
@given(data=streams, cut=st.integers(0, 400))
def test_a_reading_resumes_where_it_stopped(fw: FirmwareSpec, data: bytes, cut: int) -> None:
    """Reading in two pieces, the second from the state the first ended in, stores what one reading does."""
    cut = min(cut, len(data))
    whole = read_commands(data, 0, fw)
    first = read_commands(data[:cut], 0, fw)
    second = read_commands(data[cut:], firmware=fw, state=first.state, offset=cut)
    assert second.state == whole.state

    def effects(items: list[Any]) -> tuple[list[Any], list[Any]]:
        values, levels = [], []
        for c in items:
            if c.kind == COMMAND and c.complete and c.levels is None and c.value is not None:
                values.append((c.opcode, c.value))
            if c.levels:
                levels.extend(zip(range(c.start, c.start + len(c.levels)), c.levels))
        return values, levels

    assert effects(first.commands + second.commands) == effects(whole.commands)
    # every byte is accounted for exactly once
    assert b"".join(c.raw for c in first.commands + second.commands) == data


def test_items_name_offsets_values_and_clamps() -> None:
    items = list(iter_commands(bytes.fromhex("00 13 fc 02 fe 01 02 fb 00 f9 fd 05")))
    assert [(c.kind, c.opcode, c.offset) for c in items] == [
        (UNKNOWN, None, 0),
        (COMMAND, 0xFC, 2),
        (COMMAND, 0xFE, 4),
        (COMMAND, 0xFB, 7),
        (COMMAND, 0xFD, 10),
    ]
    assert items[0].unknown == 2 and items[1].value == 2 and items[2].levels == (1, 2)
    assert items[3].read_value == 0xF900 and items[3].value == 4095  # `fb 00` + `f9`: the clamp
    assert items[4].value == 1  # polarity clamped


def test_zero_electrode_pattern_locks_v12_but_not_v2() -> None:
    r = read_commands(b"\xfe\xfb\x10\x00", 0, V1_2)
    assert r.state.locked and [c.kind for c in r.commands] == [COMMAND, UNREAD] and r.commands[0].locked
    r2 = read_commands(b"\xfe\xfb\x01", 0, V2)
    assert r2.state.at_boundary and r2.commands[1].value == 1  # v2: mode 1 (biphasic), clamped at 2


def test_v2_reads_u16_elements_clamped_and_only_when_complete() -> None:
    r = read_commands(b"\xfc\x02\xfe\x01\x21\xe8", 0, V2)
    assert r.commands[-1].levels is None and not r.commands[-1].complete  # parse-when-complete
    assert r.state == ParserState(2, 0xFE, 4, b"\x01\x21\xe8")
    r = read_commands(b"\x03", state=r.state, firmware=V2)
    assert r.commands[0].levels == (4095, 1000) and r.commands[0].resumed and r.state.at_boundary
    # v1.2 stores each pattern byte as it arrives
    r12 = read_commands(b"\xfc\x03\xfe\x01\x02", 0, V1_2)
    assert r12.commands[-1].levels == (1, 2) and r12.state == ParserState(3, 0xFE, 3, b"\x01\x02")


def test_unknown_electrode_count_leaves_a_pattern_unreadable() -> None:
    r = read_commands(b"\xfe\x01\x01", None)
    assert r.state.needed == -1 and [c.kind for c in r.commands] == [COMMAND, UNREAD]
