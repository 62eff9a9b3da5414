"""Every eTactileKit command and reply as a ``construct`` format: the one definition of the wire format.

The formats are module-level values built only from ``this`` expressions so that ``.compile()`` works on
them; the pattern's length comes from the build/parse keyword ``electrode_num`` (the firmware takes it
from its register at the moment the command byte is read).

The ``encode_*`` functions are the host's fast path.  They validate every value against the firmware's
and the hardware's limits (naming field, value and limit on failure) and pack with plain ``bytes``;
``tests/test_protocol_commands.py`` proves them byte-identical to the construct formats over many random
inputs, so construct stays the definition and the fast path only its cheaper spelling.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import construct as cs
from construct import this

from ..errors import DecodeError, LimitError
from .constants import (
    MAX_ELECTRODES,
    U8_MAX,
    U16_MAX,
    Opcode,
)
from .units import check_int

# --- formats ---------------------------------------------------------------------------------------------


def _u8_command(opcode: int, field: str) -> cs.Struct:
    return cs.Struct("opcode" / cs.Const(bytes([opcode])), field / cs.Int8ul)


def _u16_command(opcode: int, field: str) -> cs.Struct:
    return cs.Struct("opcode" / cs.Const(bytes([opcode])), field / cs.Int16ul)


MeasureRequest = cs.Struct("opcode" / cs.Const(bytes([Opcode.MEASURE])))
Hv513CountRequest = cs.Struct("opcode" / cs.Const(bytes([Opcode.HV513_COUNT])))
PatternCommand = cs.Struct(
    "opcode" / cs.Const(bytes([Opcode.PATTERN])),
    "levels" / cs.Bytes(this._params.electrode_num),
)
PolarityCommand = _u8_command(Opcode.POLARITY, "polarity")
ElectrodeNumCommand = _u8_command(Opcode.ELECTRODE_NUM, "electrode_num")
PulseHeightCommand = _u16_command(Opcode.PULSE_HEIGHT, "pulse_height")
PulseWidthCommand = _u16_command(Opcode.PULSE_WIDTH, "pulse_width")
SenseHeightCommand = _u8_command(Opcode.SENSE_HEIGHT, "sense_height")
SenseWidthCommand = _u8_command(Opcode.SENSE_WIDTH, "sense_width")
DischargeCommand = _u8_command(Opcode.DISCHARGE, "discharge_time")
FrequencyCommand = _u16_command(Opcode.FREQUENCY, "frequency")

#: Any single command: the opcode byte picks the payload.  Keys are plain ints (a Switch keyed by an
#: IntEnum breaks once compiled, construct issue 913).  Unknown opcodes carry no payload, as on the device.
AnyCommand = cs.Struct(
    "opcode" / cs.Int8ul,
    "payload"
    / cs.Switch(
        this.opcode,
        {
            0xFE: cs.Bytes(this._params.electrode_num),
            0xFD: cs.Int8ul,
            0xFC: cs.Int8ul,
            0xFB: cs.Int16ul,
            0xFA: cs.Int16ul,
            0xF9: cs.Int8ul,
            0xF8: cs.Int8ul,
            0xF7: cs.Int8ul,
            0xF6: cs.Int16ul,
        },
        cs.Pass,
    ),
)

#: Replies (device to host).
Hv513CountReply = cs.Struct("hv513_count" / cs.Int8ul)
MeasureReply = cs.Struct("adc" / cs.Array(this._params.electrode_num, cs.Int16ul))

#: Name of each command's value field, by opcode (None: no payload).
FIELD_NAME: dict[int, str | None] = {
    Opcode.MEASURE: None,
    Opcode.PATTERN: "levels",
    Opcode.POLARITY: "polarity",
    Opcode.ELECTRODE_NUM: "electrode_num",
    Opcode.PULSE_HEIGHT: "pulse_height",
    Opcode.PULSE_WIDTH: "pulse_width",
    Opcode.SENSE_HEIGHT: "sense_height",
    Opcode.SENSE_WIDTH: "sense_width",
    Opcode.DISCHARGE: "discharge_time",
    Opcode.FREQUENCY: "frequency",
    Opcode.HV513_COUNT: None,
}

FORMATS: dict[int, cs.Construct] = {
    Opcode.MEASURE: MeasureRequest,
    Opcode.PATTERN: PatternCommand,
    Opcode.POLARITY: PolarityCommand,
    Opcode.ELECTRODE_NUM: ElectrodeNumCommand,
    Opcode.PULSE_HEIGHT: PulseHeightCommand,
    Opcode.PULSE_WIDTH: PulseWidthCommand,
    Opcode.SENSE_HEIGHT: SenseHeightCommand,
    Opcode.SENSE_WIDTH: SenseWidthCommand,
    Opcode.DISCHARGE: DischargeCommand,
    Opcode.FREQUENCY: FrequencyCommand,
    Opcode.HV513_COUNT: Hv513CountRequest,
}

_compiled: dict[int, cs.Construct] = {}


def compiled(opcode: int) -> cs.Construct:
    """The compiled form of a command's format (compiled once, on first use)."""
    fmt = _compiled.get(opcode)
    if fmt is None:
        fmt = FORMATS[Opcode(opcode)].compile()
        _compiled[opcode] = fmt
    return fmt


def build(
    opcode: int, value: Any = None, *, electrode_num: int | None = None, use_compiled: bool = False
) -> bytes:
    """Build one command with construct (the reference encoder; the ``encode_*`` functions are faster)."""
    op = Opcode(opcode)
    fmt = compiled(op) if use_compiled else FORMATS[op]
    field = FIELD_NAME[op]
    obj: dict[str, Any] = {} if field is None else {field: value}
    kwargs: dict[str, Any] = {}
    if op == Opcode.PATTERN:
        obj["levels"] = bytes(value)
        kwargs["electrode_num"] = len(obj["levels"]) if electrode_num is None else electrode_num
    try:
        return bytes(fmt.build(obj, **kwargs))
    except cs.ConstructError as exc:
        raise LimitError(f"{op.name.lower()}.{field}", value, str(exc).splitlines()[-1]) from exc


def parse(data: bytes, *, electrode_num: int = 0) -> dict[str, Any]:
    """Parse one whole command (opcode first) with construct into ``{"opcode": int, "value": …}``."""
    try:
        c = AnyCommand.parse(data, electrode_num=electrode_num)
    except cs.ConstructError as exc:
        raise DecodeError(f"cannot parse command {data.hex()}: {exc}") from exc
    return {"opcode": int(c.opcode), "value": c.payload}


def parse_measure_reply(data: bytes, electrode_num: int) -> list[int]:
    """ADC codes, one per channel, from a 0xFF reply of exactly ``2 * electrode_num`` bytes."""
    if len(data) != 2 * electrode_num:
        raise DecodeError(f"measure reply: expected {2 * electrode_num} bytes, got {len(data)}")
    return list(MeasureReply.parse(data, electrode_num=electrode_num).adc)


def parse_hv513_reply(data: bytes) -> int:
    """The HV513 chip count from a 0xF5 reply (one byte)."""
    if len(data) != 1:
        raise DecodeError(f"HV513 count reply: expected 1 byte, got {len(data)}")
    return int(Hv513CountReply.parse(data).hv513_count)


def build_measure_reply(adc: Sequence[int]) -> bytes:
    """The bytes the firmware writes for a measure request (used by the emulator)."""
    return bytes(MeasureReply.build({"adc": list(adc)}, electrode_num=len(adc)))


# --- fast path ---------------------------------------------------------------------------------------------

_PATTERN_PREFIX = bytes([Opcode.PATTERN])
MEASURE_REQUEST = bytes([Opcode.MEASURE])
HV513_COUNT_REQUEST = bytes([Opcode.HV513_COUNT])


def encode_pattern(levels: bytes | bytearray | Sequence[int], *, electrode_num: int | None = None) -> bytes:
    """0xFE and one byte per channel.  ``electrode_num`` (the device's register), when given, must equal
    the length: a shorter pattern desynchronises the parser, a longer one leaks into the next command."""
    if isinstance(levels, (int, str)) or not isinstance(levels, (bytes, bytearray, Sequence)):
        raise LimitError("pattern", levels, "a sequence of integers from 0 to 255")
    try:
        payload = bytes(levels)
    except (TypeError, ValueError) as exc:
        for i, v in enumerate(levels):
            check_int(f"pattern[{i}]", v, 0, U8_MAX)
        raise LimitError("pattern", levels, "a sequence of integers from 0 to 255") from exc
    n = len(payload)
    if n > MAX_ELECTRODES:
        raise LimitError("pattern length", n, f"at most {MAX_ELECTRODES} channels")
    if electrode_num is not None and n != electrode_num:
        raise LimitError("pattern length", n, f"exactly electrode_num = {electrode_num}")
    return _PATTERN_PREFIX + payload


def encode_u8(opcode: int, value: object, field: str, lo: int = 0, hi: int = U8_MAX) -> bytes:
    v = check_int(field, value, lo, hi)
    return bytes((opcode, v))


def encode_u16(opcode: int, value: object, field: str, lo: int = 0, hi: int = U16_MAX) -> bytes:
    v = check_int(field, value, lo, hi)
    return bytes((opcode, v & 0xFF, v >> 8))


def encode_polarity(polarity: int) -> bytes:
    """1 anodic, 0 cathodic.  Values above 1 are refused (the firmware would clamp them)."""
    return encode_u8(Opcode.POLARITY, polarity, "polarity", 0, 1)


def encode_electrode_num(electrode_num: int) -> bytes:
    return encode_u8(Opcode.ELECTRODE_NUM, electrode_num, "electrode_num", 0, MAX_ELECTRODES)


def encode_pulse_height(dac_code: int, *, limit: int = U16_MAX) -> bytes:
    """Pulse height as a DAC code.  Callers pass the hardware limit (10 mA → code 1000 by default)."""
    return encode_u16(Opcode.PULSE_HEIGHT, dac_code, "pulse_height", 0, limit)


def encode_pulse_width(width_us: int) -> bytes:
    """Stimulation pulse width in µs; 0 is refused because the firmware ignores it."""
    return encode_u16(Opcode.PULSE_WIDTH, width_us, "pulse_width_us", 1, U16_MAX)


def encode_sense_height(raw: int) -> bytes:
    """Sense pulse height as sent: the firmware stores ``raw << 2`` as the DAC code."""
    return encode_u8(Opcode.SENSE_HEIGHT, raw, "sense_height", 0, U8_MAX)


def encode_sense_width(width_us: int) -> bytes:
    return encode_u8(Opcode.SENSE_WIDTH, width_us, "sense_width_us", 0, U8_MAX)


def encode_discharge(discharge_us: int) -> bytes:
    return encode_u8(Opcode.DISCHARGE, discharge_us, "discharge_us", 0, U8_MAX)


def encode_frequency(rate_hz: int) -> bytes:
    """Stimulation rate in Hz; 0 is refused because the firmware ignores it."""
    return encode_u16(Opcode.FREQUENCY, rate_hz, "rate_hz", 1, U16_MAX)


def encode_measure_reply(adc: Sequence[int]) -> bytes:
    """Fast spelling of :data:`MeasureReply` (tested byte-identical): one u16 LE per channel."""
    return b"".join(v.to_bytes(2, "little") for v in adc)
