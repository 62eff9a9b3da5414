"""The capture decoder reads v2 streams as the v2 firmware does: replaying what it read gives the state the
v2 golden vectors hold (the CLI's ``decode --firmware`` is in ``test_protocol_decoder.py``)."""

from __future__ import annotations

import json

import pytest

from tactdeform_hw.emulator.firmware.registers import V2_SCAN_REGISTERS
from tactdeform_hw.protocol.decoder import OK, TRUNCATED, decode
from tactdeform_hw.protocol.firmware import V2

from .conftest import DATA

VECTORS = [
    json.loads(line) for line in (DATA / "protocol_vectors_v2.jsonl").read_text().splitlines() if line.strip()
]
UNTIMED = [
    v
    for v in VECTORS
    if "arrivals" not in v and "final_time_us" not in v and not v["category"].startswith("overflow")
]


def test_untimed_set_is_large() -> None:
    assert len(UNTIMED) >= 230


@pytest.mark.parametrize("vector", UNTIMED[::3], ids=[v["id"] for v in UNTIMED[::3]])
def test_decoded_commands_rebuild_the_firmware_state(vector: dict) -> None:
    """Replaying what the decoder read gives the state the real v2 firmware reached."""
    state = {k: v for k, v in V2.power_on.items()}
    pattern = [0] * 256
    pending = False
    for item in decode(bytes.fromhex(vector["stream"]), 0, V2):
        if item.status == TRUNCATED:
            pending = True
            continue
        assert item.status in (OK, "unknown")
        if item.status != OK or item.opcode is None:
            continue
        spec = V2.by_opcode[item.opcode]
        if spec.kind == "pattern":
            assert isinstance(item.value, tuple)
            pattern[: len(item.value)] = item.value
        elif spec.register and item.stored is not None and spec.register != "frequency":
            state[spec.register] = item.stored
    expect = vector["expect"]
    for key in V2_SCAN_REGISTERS:
        assert state[key] == expect[key], key
    assert pattern == expect["stim_pattern"]
    assert pending == expect["command_in_progress"]
