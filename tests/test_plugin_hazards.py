"""Severity and origin of the emulated board's hazard records, and the driver's designed byte spans."""

from __future__ import annotations

import sys
from pathlib import Path

from tactdeform_hw import protocol as p
from tactdeform_hw.device.driver.firmware_probe import IDENT_OFF, SIGNATURE
from tactdeform_hw.device.driver.pacing import padding_for
from tactdeform_hw.emulator import Emulator
from tactdeform_hw.emulator.firmware.hazards import (
    SEVERITY,
    Hazard,
    HazardKind,
    Origin,
    Severity,
    assess,
    severity_of,
)
from tactdeform_hw.testing import driver_spans, identification_spans

if sys.version_info >= (3, 11):
    import tomllib
else:  # the same code before 3.11
    import tomli as tomllib

REPO = Path(__file__).resolve().parents[1]


def test_every_kind_has_a_severity() -> None:
    assert set(SEVERITY) == set(HazardKind)
    assert SEVERITY[HazardKind.UNKNOWN_BYTES] is Severity.INFO
    assert SEVERITY[HazardKind.HV513_REINIT] is Severity.INFO
    for kind in (HazardKind.PARSER_LOCKED, HazardKind.TORN_PATTERN, HazardKind.QUEUE_OVERFLOW):
        assert SEVERITY[kind] is Severity.DEFECT


def test_a_value_byte_meant_as_a_value_is_info() -> None:
    meant = Hazard(HazardKind.PAYLOAD_HOLDS_COMMAND_BYTE, 3, {"meant_as_command": False})
    cut = Hazard(HazardKind.PAYLOAD_HOLDS_COMMAND_BYTE, 3, {})
    assert severity_of(meant) is Severity.INFO
    assert severity_of(cut) is Severity.DEFECT


def test_origin_is_the_span_the_record_falls_in() -> None:
    h = Hazard(HazardKind.UNKNOWN_BYTES, 10, {"count": 4})
    assert assess(h, [(0, 11)]).origin is Origin.DRIVER
    assert assess(h, [(0, 10)]).origin is Origin.HOST
    assert assess(h, None).origin is Origin.UNKNOWN
    d = assess(h, [(0, 11)]).to_dict()
    assert d["severity"] == "info" and d["origin"] == "driver" and d["kind"] == "unknown_bytes"


def _assessed(stream: bytes, firmware: str = "v1.2") -> list[tuple[str, str, str]]:
    emu = Emulator(firmware=firmware)
    emu.feed(stream)
    spans = driver_spans(stream, firmware)
    return [(a.kind.value, a.severity.value, a.origin.value) for a in (assess(h, spans) for h in emu.hazards)]


def test_the_identification_and_padding_are_the_drivers_and_a_lock_is_the_programs() -> None:
    count = p.encode_electrode_num(8)
    height = p.encode_pulse_height(0)
    stream = IDENT_OFF + SIGNATURE + bytes(4) + b"\xf5" + count + padding_for(count) + height
    stream += padding_for(height)
    clean = _assessed(stream)
    assert clean and all(sev == "info" and origin == "driver" for _, sev, origin in clean), clean
    # the same session, then a pattern for zero electrodes (locks v1.2's parser): a defect, the program's
    locked = _assessed(stream + p.encode_electrode_num(0) + b"\xfe" + b"\x01\x02")
    defects = [r for r in locked if r[1] == "defect"]
    assert ("parser_locked", "defect", "host") in defects


def test_a_zero_run_alone_is_not_taken_for_the_driver() -> None:
    assert driver_spans(b"\x01\x00\x00\x07") == []  # zeros followed by nothing the driver sends after them
    assert identification_spans(b"\x33" + SIGNATURE) == [(1, 1 + len(SIGNATURE))]


def test_the_plugin_is_declared_as_a_pytest11_entry_point() -> None:
    meta = tomllib.loads((REPO / "pyproject.toml").read_text())
    assert meta["project"]["entry-points"]["pytest11"] == {"etactile": "tactdeform_hw.testing.plugin"}
