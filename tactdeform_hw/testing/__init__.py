"""Testing a program against the emulated eTactileKit board: the pytest plugin (``etactile_board``, the
``etactile_board`` marker, ``--etactile-device``), the board it serves and its assertions.  See
``docs/testing-downstream.md``."""

from tactdeform_hw.testing.board import (
    DeliveredPulse,
    EmulatedBoard,
    HazardReport,
    RecordingBoard,
    delivered_pulses,
    driver_spans,
    identification_spans,
)

__all__ = [
    "DeliveredPulse",
    "EmulatedBoard",
    "HazardReport",
    "RecordingBoard",
    "delivered_pulses",
    "driver_spans",
    "identification_spans",
]
