"""A firmware version is a value: what differs between versions is read from its table, and the protocol
layer never asks which version it holds by name."""

from __future__ import annotations

import ast
from dataclasses import replace
from pathlib import Path

import pytest

from tactdeform_hw.errors import ConfigurationError
from tactdeform_hw.protocol.firmware import FIRMWARES, V1_2, V2, FirmwareSpec

PROTOCOL = Path(__file__).resolve().parents[1] / "tactdeform_hw" / "protocol"
ALL = pytest.mark.parametrize("fw", list(FIRMWARES.values()), ids=list(FIRMWARES))


@ALL
def test_the_questions_other_layers_ask_read_the_table(fw: FirmwareSpec) -> None:
    assert fw.pattern_command.kind == "pattern" and fw.pattern_command is fw.by_opcode[0xFE]
    assert fw.has_register("stim_pattern") and not fw.has_register("no_such_register")
    assert fw.opcode_replying("measure") == 0xFF and fw.opcode_replying("hv513") == 0xF5
    assert fw.answers_sync_check == (fw.opcode_replying("sync") is not None)
    assert fw.pattern_holds_heights == (not fw.has_register("pulse_height"))
    assert (fw.pattern_buffer_size, fw.max_electrodes, fw.dac_max_code, fw.usb_packet_bytes) == (
        256,
        255,
        4095,
        64,
    )


def test_what_the_two_versions_answer() -> None:
    assert not V1_2.pattern_holds_heights and V2.pattern_holds_heights
    assert not V1_2.answers_sync_check and V2.answers_sync_check
    assert V1_2.opcode_replying("sync") is None and V2.opcode_replying("sync") == 0xF4
    assert V1_2.has_register("pulse_height") and not V2.has_register("pulse_height")
    assert V2.has_register("stim_mode") and not V1_2.has_register("stim_mode")
    assert V1_2.pattern_command.field is None and V2.pattern_command.field == "heights"
    assert V1_2.power_on["pulse_height"] == 0 and V2.power_on["stim_mode"] == 0
    assert {k: v for k, v in V1_2.power_on.items() if k != "pulse_height"} == {
        k: v for k, v in V2.power_on.items() if k != "stim_mode"
    }


def test_a_table_needs_exactly_one_pattern_command() -> None:
    no_pattern = tuple(c for c in V1_2.commands if c.kind != "pattern")
    with pytest.raises(ConfigurationError, match=r"firmware x: its command table has 0 pattern commands"):
        replace(V1_2, name="x", commands=no_pattern)
    two = (*V1_2.commands, replace(V1_2.pattern_command, opcode=0xF0))
    with pytest.raises(ConfigurationError, match="has 2 pattern commands"):
        replace(V1_2, name="x", commands=two)


def _name_comparisons(source: str) -> list[int]:
    """Lines comparing with a version's name or its module-level table (``== "v2"``, ``is V1_2``)."""
    names = {"V1_2", "V2"}
    found = []
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Compare):
            for side in (node.left, *node.comparators):
                literal = isinstance(side, ast.Constant) and side.value in FIRMWARES
                if literal or (isinstance(side, ast.Name) and side.id in names):
                    found.append(node.lineno)
    return found


def test_the_protocol_layer_branches_on_table_fields_not_names() -> None:
    assert _name_comparisons('if fw is V2:\n    pass\nok = spec.name == "v1.2"\nfine = a == b\n') == [1, 3]
    found = {
        path.name: lines
        for path in sorted(PROTOCOL.glob("*.py"))
        if (lines := _name_comparisons(path.read_text(encoding="utf-8")))
    }
    assert found == {}
