"""Files other tools read and write: eTactileKit electrode arrays and patterns, TactDeform frame records."""

from .etactilekit import (
    ArrayFile,
    PatternSequence,
    PatternStep,
    array_to_dict,
    dumps_pattern,
    parse_array,
    parse_pattern,
    pattern_to_dict,
    read_array_file,
    read_pattern_file,
    sequence_from_frames,
    write_array_file,
    write_pattern_file,
)
from .frames import Frame, delivered_spans, iter_frames, read_frames_file

__all__ = [
    "ArrayFile",
    "Frame",
    "PatternSequence",
    "PatternStep",
    "array_to_dict",
    "delivered_spans",
    "dumps_pattern",
    "iter_frames",
    "parse_array",
    "parse_pattern",
    "pattern_to_dict",
    "read_array_file",
    "read_frames_file",
    "read_pattern_file",
    "sequence_from_frames",
    "write_array_file",
    "write_pattern_file",
]
