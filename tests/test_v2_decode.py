"""``decode --firmware v2``: the capture decoder reads v2 streams as the v2 firmware does."""

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


def test_cli_decodes_v2(capsys: pytest.CaptureFixture[str]) -> None:
    import argparse

    from tactdeform_hw.cli import decode as cli

    parser = argparse.ArgumentParser()
    cli.register(parser.add_subparsers())
    for argv, want in (
        (
            ["--firmware", "v2", "fc 02 fe 64 00 ff 0f fb 01 f4"],
            ["levels=[100,4095]", "STIM_MODE stim_mode=1", "SYNC_CHECK"],
        ),
        (["fc 02 fe 64 00 ff 0f fb 01 f4"], ["levels=[100,0]", "MEASURE", "PULSE_HEIGHT"]),
    ):
        args = parser.parse_args(["decode", *argv])
        assert args.func(args) == 0
        out = capsys.readouterr()
        for w in want:
            assert w in out.out
    args = parser.parse_args(["decode", "--firmware", "v2", "fa 00"])
    args.func(args)
    assert "within 2 s of its command byte" in capsys.readouterr().err
