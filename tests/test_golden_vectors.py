"""The firmware's own parser is ground truth: every golden stream must reach exactly its recorded state, on
every firmware version of the registry (each version's vectors were recorded from its own source).  What
only v2's vectors hold (recorded arrival times, the 2 s timeout, the upstream host's chunks, the hazards
recorded) is in ``test_v2_vectors.py``."""

from __future__ import annotations

import json

import numpy as np
import pytest

from tactdeform_hw.emulator import Emulator
from tactdeform_hw.protocol.firmware import FIRMWARES

from .conftest import DATA

#: Each version's golden vectors and how many the file holds.
VECTOR_FILES = {"v1.2": ("protocol_vectors.jsonl", 250), "v2": ("protocol_vectors_v2.jsonl", 300)}
VECTORS = {
    firmware: [json.loads(line) for line in (DATA / name).read_text().splitlines() if line.strip()]
    for firmware, (name, _) in VECTOR_FILES.items()
}


def test_every_firmware_has_all_its_vectors() -> None:
    assert set(VECTOR_FILES) == set(FIRMWARES)
    assert {fw: len(v) for fw, v in VECTORS.items()} == {fw: n for fw, (_, n) in VECTOR_FILES.items()}


def arrivals(vector: dict) -> list[tuple[int, bytes]]:
    """The recorded arrivals (µs, bytes); the whole stream at t = 0 when none are recorded."""
    if "arrivals" in vector:
        return [(int(t), bytes.fromhex(h)) for t, h in vector["arrivals"]]
    return [(0, bytes.fromhex(vector["stream"]))]


def drive(
    firmware: str, vector: dict, chunks: list[tuple[int, bytes]], final_time_us: int | None
) -> tuple[Emulator, bytes]:
    """The vector's board, fed ``chunks`` (µs, bytes), then run to ``final_time_us``; its replies."""
    board = vector["board"]
    emu = Emulator(
        board["kind"], board["switching_boards"], stack_reading=board.get("stack_reading"), firmware=firmware
    )
    tx = b"".join(emu.feed(data, at_us=t) for t, data in chunks)
    if final_time_us is not None:
        tx += emu.advance(final_time_us)
    return emu, tx


def check(vector: dict, emu: Emulator, tx: bytes) -> None:
    """The replies byte for byte, the period as the firmware's float holds it, every register expected."""
    state = emu.state()
    expect = vector["expect"]
    assert tx.hex() == expect["tx"]
    assert np.float32(state.period_us) == np.float32(expect["period_us"])
    assert state.period_us == float(np.float32(expect["period_us"]))
    assert set(expect) <= set(state.as_dict()) | {"tx"}
    for key, value in expect.items():
        if key in ("tx", "period_us"):
            continue
        assert state.as_dict()[key] == value, key


def split_is_harmless(firmware: str, vector: dict) -> bool:
    """Whether the firmware's state cannot depend on how the stream is split: a version without a command
    timeout always; one with it when no arrival or final poll is more than the timeout after the first
    byte (a payload then always completes within the timeout of its command byte)."""
    timeout_us = FIRMWARES[firmware].command_timeout_us
    if timeout_us is None:
        return True
    times = [t for t, _ in arrivals(vector)] + [vector.get("final_time_us") or 0]
    return max(times) <= timeout_us


ONE_ARRIVAL = [(fw, i) for fw in FIRMWARES for i, v in enumerate(VECTORS[fw]) if split_is_harmless(fw, v)]
#: Every fifth of those, but the queue overflows: those are recorded as one arrival that overflows the
#: receive queue, which a byte at a time never does.
BYTE_BY_BYTE = [
    (fw, i)
    for fw in FIRMWARES
    for k, (f, i) in enumerate(ONE_ARRIVAL)
    if f == fw and k % 5 == 0 and not VECTORS[fw][i].get("category", "").startswith("overflow")
]


def _id(case: tuple[str, int]) -> str:
    fw, i = case
    return f"{fw}-{VECTORS[fw][i].get('id', i)}"


@pytest.mark.parametrize("case", ONE_ARRIVAL, ids=[_id(c) for c in ONE_ARRIVAL])
def test_vector_in_one_arrival(case: tuple[str, int]) -> None:
    """The whole stream at once, then the recorded final time (if any)."""
    firmware, index = case
    vector = VECTORS[firmware][index]
    emu, tx = drive(firmware, vector, [(0, bytes.fromhex(vector["stream"]))], vector.get("final_time_us"))
    check(vector, emu, tx)


@pytest.mark.parametrize("case", BYTE_BY_BYTE, ids=[_id(c) for c in BYTE_BY_BYTE])
def test_vector_byte_by_byte(case: tuple[str, int]) -> None:
    """The same stream one byte per arrival (all at t = 0): a parser reaches the same state however the
    bytes are cut."""
    firmware, index = case
    vector = VECTORS[firmware][index]
    data = bytes.fromhex(vector["stream"])
    emu, tx = drive(
        firmware, vector, [(0, data[i : i + 1]) for i in range(len(data))], vector.get("final_time_us")
    )
    check(vector, emu, tx)


@pytest.mark.parametrize("firmware", list(FIRMWARES))
def test_vectors_cover_the_defects(firmware: str) -> None:
    """The golden set exercises what the emulator must reproduce: a command left waiting for its payload,
    replies, and the checks in one arrival cover most of the set."""
    vectors = VECTORS[firmware]
    waiting = sum(
        1 for v in vectors if v["expect"]["rx_pending"] > 1 or v["expect"].get("command_in_progress")
    )
    replies = sum(1 for v in vectors if v["expect"]["tx"])
    assert waiting > 0 and replies > 0
    assert sum(1 for fw, _ in ONE_ARRIVAL if fw == firmware) >= 0.9 * len(vectors)
