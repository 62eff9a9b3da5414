"""Firmware v2's commands and replies as ``construct`` formats, and the host's fast encoders for them.

v2 reuses v1.2's bytes with other meanings, so its formats live apart from :mod:`.commands`: 0xFB is
the stimulation mode (u8, 0 monophasic, 1 biphasic, 2 impedance only), the pattern carries one u16 DAC
code per electrode (little-endian), 0xF9 stores the sense height unshifted, 0xFA stores a width of 0,
and 0xF4 asks for the electrode count (one byte back).  Opcodes, payload kinds and clamps come from the
v2 table (:data:`.firmware.V2`); the formats are module-level, ``this``-expressions only, so
``.compile()`` works; ``tests/test_v2_protocol.py`` holds the ``encode_*`` functions byte-identical to
them, plain and compiled.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import construct as cs
from construct import this

from ..errors import DecodeError, LimitError
from .commands import _u8_command, _u16_command
from .constants import U8_MAX, U16_MAX
from .firmware import V2, OpcodeV2
from .units import check_int

_DAC_MAX = V2.dac_max_code
_MODE_MAX = V2.command(OpcodeV2.STIM_MODE).max_value or 2

STIM_MODE_MONOPHASIC = 0
STIM_MODE_BIPHASIC = 1
STIM_MODE_IMPEDANCE = 2
STIM_MODES = {"mono": STIM_MODE_MONOPHASIC, "bi": STIM_MODE_BIPHASIC, "impedance": STIM_MODE_IMPEDANCE}


MeasureRequest = cs.Struct("opcode" / cs.Const(bytes([OpcodeV2.MEASURE])))
Hv513CountRequest = cs.Struct("opcode" / cs.Const(bytes([OpcodeV2.HV513_COUNT])))
SyncCheckRequest = cs.Struct("opcode" / cs.Const(bytes([OpcodeV2.SYNC_CHECK])))
PatternCommand = cs.Struct(
    "opcode" / cs.Const(bytes([OpcodeV2.PATTERN])),
    "heights" / cs.Array(this._params.electrode_num, cs.Int16ul),
)
PolarityCommand = _u8_command(OpcodeV2.POLARITY, "polarity")
ElectrodeNumCommand = _u8_command(OpcodeV2.ELECTRODE_NUM, "electrode_num")
StimModeCommand = _u8_command(OpcodeV2.STIM_MODE, "stim_mode")
PulseWidthCommand = _u16_command(OpcodeV2.PULSE_WIDTH, "pulse_width")
SenseHeightCommand = _u8_command(OpcodeV2.SENSE_HEIGHT, "sense_height")
SenseWidthCommand = _u8_command(OpcodeV2.SENSE_WIDTH, "sense_width")
DischargeCommand = _u8_command(OpcodeV2.DISCHARGE, "discharge_time")
FrequencyCommand = _u16_command(OpcodeV2.FREQUENCY, "frequency")

#: Any single v2 command; unknown bytes carry no payload, as on the device.  Plain-int keys (construct
#: issue 913: an IntEnum-keyed Switch breaks once compiled).
AnyCommand = cs.Struct(
    "opcode" / cs.Int8ul,
    "payload"
    / cs.Switch(
        this.opcode,
        {
            0xFE: cs.Array(this._params.electrode_num, cs.Int16ul),
            0xFD: cs.Int8ul,
            0xFC: cs.Int8ul,
            0xFB: cs.Int8ul,
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
MeasureReply = cs.Struct("adc" / cs.Array(this._params.electrode_num, cs.Int16ul))
Hv513CountReply = cs.Struct("hv513_count" / cs.Int8ul)
SyncReply = cs.Struct("electrode_num" / cs.Int8ul)

FIELD_NAME: dict[int, str | None] = {
    OpcodeV2.MEASURE: None,
    OpcodeV2.PATTERN: "heights",
    OpcodeV2.POLARITY: "polarity",
    OpcodeV2.ELECTRODE_NUM: "electrode_num",
    OpcodeV2.STIM_MODE: "stim_mode",
    OpcodeV2.PULSE_WIDTH: "pulse_width",
    OpcodeV2.SENSE_HEIGHT: "sense_height",
    OpcodeV2.SENSE_WIDTH: "sense_width",
    OpcodeV2.DISCHARGE: "discharge_time",
    OpcodeV2.FREQUENCY: "frequency",
    OpcodeV2.HV513_COUNT: None,
    OpcodeV2.SYNC_CHECK: None,
}

FORMATS: dict[int, cs.Construct] = {
    OpcodeV2.MEASURE: MeasureRequest,
    OpcodeV2.PATTERN: PatternCommand,
    OpcodeV2.POLARITY: PolarityCommand,
    OpcodeV2.ELECTRODE_NUM: ElectrodeNumCommand,
    OpcodeV2.STIM_MODE: StimModeCommand,
    OpcodeV2.PULSE_WIDTH: PulseWidthCommand,
    OpcodeV2.SENSE_HEIGHT: SenseHeightCommand,
    OpcodeV2.SENSE_WIDTH: SenseWidthCommand,
    OpcodeV2.DISCHARGE: DischargeCommand,
    OpcodeV2.FREQUENCY: FrequencyCommand,
    OpcodeV2.HV513_COUNT: Hv513CountRequest,
    OpcodeV2.SYNC_CHECK: SyncCheckRequest,
}

_compiled: dict[int, cs.Construct] = {}


def compiled(opcode: int) -> cs.Construct:
    """The compiled form of a v2 command's format (compiled once, on first use)."""
    fmt = _compiled.get(opcode)
    if fmt is None:
        fmt = FORMATS[OpcodeV2(opcode)].compile()
        _compiled[opcode] = fmt
    return fmt


def build(
    opcode: int, value: Any = None, *, electrode_num: int | None = None, use_compiled: bool = False
) -> bytes:
    """Build one v2 command with construct (the reference the ``encode_*`` functions are held to)."""
    op = OpcodeV2(opcode)
    fmt = compiled(op) if use_compiled else FORMATS[op]
    field = FIELD_NAME[op]
    obj: dict[str, Any] = {} if field is None else {field: value}
    kwargs: dict[str, Any] = {}
    if op == OpcodeV2.PATTERN:
        obj["heights"] = list(value)
        kwargs["electrode_num"] = len(obj["heights"]) if electrode_num is None else electrode_num
    try:
        return bytes(fmt.build(obj, **kwargs))
    except cs.ConstructError as exc:
        raise LimitError(f"{op.name.lower()}.{field}", value, str(exc).splitlines()[-1]) from exc


def parse(data: bytes, *, electrode_num: int = 0) -> dict[str, Any]:
    """One whole v2 command (opcode first) → ``{"opcode": int, "value": …}`` (a pattern: a list of ints)."""
    try:
        c = AnyCommand.parse(data, electrode_num=electrode_num)
    except cs.ConstructError as exc:
        raise DecodeError(f"cannot parse v2 command {data.hex()}: {exc}") from exc
    value = list(c.payload) if isinstance(c.payload, list) else c.payload
    return {"opcode": int(c.opcode), "value": value}


def parse_measure_reply(data: bytes, electrode_num: int) -> list[int]:
    if len(data) != 2 * electrode_num:
        raise DecodeError(f"measure reply: expected {2 * electrode_num} bytes, got {len(data)}")
    return list(MeasureReply.parse(data, electrode_num=electrode_num).adc)


def parse_hv513_reply(data: bytes) -> int:
    if len(data) != 1:
        raise DecodeError(f"HV513 count reply: expected 1 byte, got {len(data)}")
    return int(Hv513CountReply.parse(data).hv513_count)


def parse_sync_reply(data: bytes) -> int:
    """The electrode count from a 0xF4 reply (one byte: ``(byte)ElectrodeNum``)."""
    if len(data) != 1:
        raise DecodeError(f"sync reply: expected 1 byte, got {len(data)}")
    return int(SyncReply.parse(data).electrode_num)


# --- fast path -----------------------------------------------------------------------------------------

MEASURE_REQUEST = bytes([OpcodeV2.MEASURE])
HV513_COUNT_REQUEST = bytes([OpcodeV2.HV513_COUNT])
SYNC_CHECK = bytes([OpcodeV2.SYNC_CHECK])
_PATTERN_PREFIX = bytes([OpcodeV2.PATTERN])


def encode_pattern(
    heights: Sequence[int], *, electrode_num: int | None = None, limit: int = _DAC_MAX, field: str = "heights"
) -> bytes:
    """0xFE and one u16 DAC code per electrode.  ``limit`` is the caller's ceiling (the hardware's 10 mA,
    a participant's cap); the firmware's own clamp is 4095.  ``electrode_num``, when given, must equal the
    length: the firmware reads ``2 × electrode_num`` bytes."""
    if isinstance(heights, (int, str, bytes, bytearray)) or not isinstance(heights, Sequence):
        raise LimitError(field, heights, f"a sequence of integers from 0 to {limit}")
    n = len(heights)
    if n > V2.max_electrodes:
        raise LimitError(f"{field} length", n, f"at most {V2.max_electrodes} channels")
    if electrode_num is not None and n != electrode_num:
        raise LimitError(f"{field} length", n, f"exactly electrode_num = {electrode_num}")
    out = bytearray(_PATTERN_PREFIX)
    for i, h in enumerate(heights):
        v = check_int(f"{field}[{i}]", h, 0, min(limit, _DAC_MAX))
        out += bytes((v & 0xFF, v >> 8))
    return bytes(out)


def _u8(opcode: int, value: object, field: str, lo: int = 0, hi: int = U8_MAX) -> bytes:
    return bytes((opcode, check_int(field, value, lo, hi)))


def _u16(opcode: int, value: object, field: str, lo: int = 0, hi: int = U16_MAX) -> bytes:
    v = check_int(field, value, lo, hi)
    return bytes((opcode, v & 0xFF, v >> 8))


def encode_stim_mode(mode: int) -> bytes:
    """0 monophasic, 1 biphasic (first phase at the configured polarity), 2 impedance only (the sense
    pulse on every channel, pattern ignored).  Values above 2 are refused (the firmware would clamp)."""
    return _u8(OpcodeV2.STIM_MODE, mode, "stim_mode", 0, _MODE_MAX)


def encode_polarity(polarity: int) -> bytes:
    return _u8(OpcodeV2.POLARITY, polarity, "polarity", 0, 1)


def encode_electrode_num(electrode_num: int) -> bytes:
    return _u8(OpcodeV2.ELECTRODE_NUM, electrode_num, "electrode_num", 0, V2.max_electrodes)


def encode_pulse_width(width_us: int) -> bytes:
    """Pulse width in µs.  v2 stores 0 (it still gives a ≈ 6.6 µs pulse at the pattern height)."""
    return _u16(OpcodeV2.PULSE_WIDTH, width_us, "pulse_width_us", 0, U16_MAX)


def encode_sense_height(code: int) -> bytes:
    """Sense pulse height as a DAC code 0-255, stored as sent (v1.2 shifted it left by 2)."""
    return _u8(OpcodeV2.SENSE_HEIGHT, code, "sense_height", 0, U8_MAX)


def encode_sense_width(width_us: int) -> bytes:
    return _u8(OpcodeV2.SENSE_WIDTH, width_us, "sense_width_us", 0, U8_MAX)


def encode_discharge(discharge_us: int) -> bytes:
    return _u8(OpcodeV2.DISCHARGE, discharge_us, "discharge_us", 0, U8_MAX)


def encode_frequency(rate_hz: int) -> bytes:
    """Rate in Hz; 0 is refused because the firmware ignores it."""
    return _u16(OpcodeV2.FREQUENCY, rate_hz, "rate_hz", 1, U16_MAX)


def encode_sync_reply(electrode_num: int) -> bytes:
    """What the firmware writes for 0xF4 (used by the emulator's tests): ``(byte)ElectrodeNum``."""
    return bytes(SyncReply.build({"electrode_num": electrode_num & 0xFF}))
