"""Each firmware version's table against the facts of its protocol reference."""

from __future__ import annotations

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from tactdeform_hw.emulator import Emulator
from tactdeform_hw.errors import ConfigurationError
from tactdeform_hw.protocol import constants as c
from tactdeform_hw.protocol.firmware import FIRMWARES, V1_2, V2, Opcode, OpcodeV2, get_firmware


def test_registry_and_lookup() -> None:
    assert FIRMWARES == {"v1.2": V1_2, "v2": V2}
    assert get_firmware("v2") is V2
    assert get_firmware(V1_2) is V1_2
    with pytest.raises(ConfigurationError, match=r"firmware='v3'.*v1\.2, v2"):
        get_firmware("v3")
    with pytest.raises(ConfigurationError, match=r"--firmware=None"):
        get_firmware(None, "--firmware")  # type: ignore[arg-type]


def test_v12_table() -> None:
    assert {op: V1_2.size_of(op, 32) for op in V1_2.by_opcode} == {
        0xFF: 0,
        0xFE: 32,
        0xFD: 1,
        0xFC: 1,
        0xFB: 2,
        0xFA: 2,
        0xF9: 1,
        0xF8: 1,
        0xF7: 1,
        0xF6: 2,
        0xF5: 0,
    }
    assert V1_2.size_of(0xF4, 32) is None and V1_2.command_byte_min == 0xF5
    assert V1_2.command(Opcode.PULSE_HEIGHT).stored(0xF900) == 4095
    assert V1_2.command(Opcode.POLARITY).stored(7) == 1
    assert V1_2.command(Opcode.SENSE_HEIGHT).stored(255) == 1020
    assert V1_2.command(Opcode.PULSE_WIDTH).stored(0) is None
    assert V1_2.command(Opcode.FREQUENCY).stored(0) is None
    assert (
        V1_2.reply_bytes(0xFF, 32) == 64
        and V1_2.reply_bytes(0xF5, 32) == 1
        and V1_2.reply_bytes(0xFB, 32) == 0
    )
    assert V1_2.rx_queue_bytes == 256 and V1_2.usb_packet_bytes == 64
    assert V1_2.zero_pattern_locks and V1_2.partial_payload_applied and V1_2.command_timeout_us is None
    assert (
        V1_2.sleeps_after(0xFB, True)
        and not V1_2.sleeps_after(0xFF, True)
        and not V1_2.sleeps_after(0x00, True)
    )
    assert V1_2.sleeps_after(None, False) and V1_2.sleeps_after(0xFE, False)  # idle; waiting for a payload
    assert V1_2.timing.discharge_exchange and V1_2.pattern_level_max() == 255
    assert V1_2.power_on["polarity"] == 1 and V1_2.power_on["period_us"] == 10_000.0


def test_v2_table() -> None:
    assert V2.size_of(OpcodeV2.PATTERN, 32) == 64 and V2.size_of(OpcodeV2.PATTERN, 0) == 0
    assert V2.size_of(OpcodeV2.STIM_MODE, 32) == 1 and V2.size_of(OpcodeV2.SYNC_CHECK, 32) == 0
    assert V2.command_byte_min == 0xF4
    assert V2.command(OpcodeV2.STIM_MODE).stored(220) == 2
    assert V2.command(OpcodeV2.PATTERN).stored(0x2101) == 4095
    assert V2.command(OpcodeV2.SENSE_HEIGHT).stored(255) == 255  # no shift
    assert V2.command(OpcodeV2.PULSE_WIDTH).stored(0) == 0  # width 0 accepted
    assert V2.reply_bytes(0xF4, 7) == 1 and V2.reply_bytes(0xFF, 3) == 6
    assert V2.rx_queue_bytes == 1024 and V2.command_timeout_us == 2_000_000
    assert not V2.zero_pattern_locks and not V2.partial_payload_applied
    assert not V2.sleeps_after(0xFB, True) and V2.sleeps_after(None, False)
    assert not V2.timing.discharge_exchange and V2.pattern_level_max() == 4095
    assert "pulse_height" not in V2.power_on and V2.power_on["stim_mode"] == 0
    with pytest.raises(ConfigurationError, match="no command setting 'pulse_height'"):
        V2.opcode_of("pulse_height")


def test_busy_wait_rule() -> None:
    t = V1_2.timing
    assert t.delay_ticks(0) == 0 and t.delay_ticks(3) == 0 and t.delay_ticks(4) == 2
    assert t.busy_wait_us(193) == 193 - 2.5 - 0.5  # int(386 - 5.4) = 380 ticks = 190 µs
    assert t.pulse_wait_us(6) == 0.0 and t.discharge_wait_us(7) == 0.0


def test_constants_read_the_v12_table() -> None:
    assert c.PAYLOAD_KIND == V1_2.payload_kind and c.PAYLOAD_SIZE == V1_2.payload_size
    assert c.RX_QUEUE_SIZE == V1_2.rx_queue_bytes and c.USB_PACKET_SIZE == V1_2.usb_packet_bytes
    assert c.DAC_MAX_CODE == V1_2.dac_max_code and c.SENSE_HEIGHT_SHIFT == 2
    assert c.Opcode is Opcode and c.POWER_ON_PERIOD_US == V1_2.power_on["period_us"]


@settings(max_examples=150, deadline=None)
@given(
    data=st.lists(
        st.one_of(st.integers(0xF5, 0xFF), st.integers(0, 3), st.integers(0, 255)), max_size=120
    ).map(bytes)
)
def test_the_yield_rule_is_the_emulator_parsers(data: bytes) -> None:
    """Call by call, the v1.2 table's yield rule says when the emulator's parser sleeps a tick."""
    emu = Emulator()
    parser = emu.parser
    parser.receive(data)
    for _ in range(len(data) + 3):
        before = (parser.offset, len(parser.tx))
        opcode = parser.cmd if parser.cmd is not None else (parser.rx[parser.pos] if parser.pending else None)
        result = parser.step()
        if result.name == "STUCK_U16":  # the call spins on a half u16 and has not returned
            break
        progressed = (parser.offset, len(parser.tx)) != before
        assert V1_2.sleeps_after(opcode, progressed) == result.slept, (result, opcode, progressed)
        if result.name in ("IDLE", "LOCKED"):
            break
