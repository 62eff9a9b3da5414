"""The firmware's own parser is ground truth: every golden stream must reach exactly its recorded state."""

from __future__ import annotations

import json

import numpy as np
import pytest

from tactdeform_hw.emulator import Emulator

from .conftest import DATA

VECTORS = [
    json.loads(line) for line in (DATA / "protocol_vectors.jsonl").read_text().splitlines() if line.strip()
]


def test_all_vectors_present() -> None:
    assert len(VECTORS) == 250


def _check(vector: dict, chunks: list[bytes]) -> None:
    board = vector["board"]
    emu = Emulator(board["kind"], board["switching_boards"])
    tx = b"".join(emu.feed(c) for c in chunks)
    state = emu.state()
    expect = vector["expect"]
    assert tx.hex() == expect["tx"]
    assert np.float32(state.period_us) == np.float32(expect["period_us"])
    for key, value in expect.items():
        if key in ("tx", "period_us"):
            continue
        assert state.as_dict()[key] == value, key


@pytest.mark.parametrize("index", range(len(VECTORS)))
def test_vector_in_one_arrival(index: int) -> None:
    vector = VECTORS[index]
    _check(vector, [bytes.fromhex(vector["stream"])])


@pytest.mark.parametrize("index", range(0, len(VECTORS), 5))
def test_vector_byte_by_byte(index: int) -> None:
    vector = VECTORS[index]
    data = bytes.fromhex(vector["stream"])
    _check(vector, [data[i : i + 1] for i in range(len(data))])


def test_vectors_cover_the_defects() -> None:
    """The golden set exercises the defects the emulator must reproduce (locks, half u16s, replies)."""
    locked = sum(1 for v in VECTORS if v["expect"]["rx_pending"] > 1)
    replies = sum(1 for v in VECTORS if v["expect"]["tx"])
    assert locked > 0 and replies > 0
