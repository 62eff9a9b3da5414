"""The eTactileKit serial protocol: command bytes, payloads, replies, units and limits.  No I/O here."""

from .commands import (
    HV513_COUNT_REQUEST,
    MEASURE_REQUEST,
    AnyCommand,
    Hv513CountReply,
    MeasureReply,
    build,
    encode_discharge,
    encode_electrode_num,
    encode_frequency,
    encode_pattern,
    encode_polarity,
    encode_pulse_height,
    encode_pulse_width,
    encode_sense_height,
    encode_sense_width,
    parse,
    parse_hv513_reply,
    parse_measure_reply,
)
from .constants import PAYLOAD_KIND, Opcode
from .decoder import DecodedCommand, StreamDecoder, decode
from .units import DEFAULT_TRANSFER, CurrentTransfer, check_int

__all__ = [
    "AnyCommand",
    "CurrentTransfer",
    "DEFAULT_TRANSFER",
    "DecodedCommand",
    "HV513_COUNT_REQUEST",
    "Hv513CountReply",
    "MEASURE_REQUEST",
    "MeasureReply",
    "Opcode",
    "PAYLOAD_KIND",
    "StreamDecoder",
    "build",
    "check_int",
    "decode",
    "encode_discharge",
    "encode_electrode_num",
    "encode_frequency",
    "encode_pattern",
    "encode_polarity",
    "encode_pulse_height",
    "encode_pulse_width",
    "encode_sense_height",
    "encode_sense_width",
    "parse",
    "parse_hv513_reply",
    "parse_measure_reply",
]
