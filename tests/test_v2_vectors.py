"""The v2 firmware's own parser is ground truth: all 300 golden streams, in one arrival and as recorded."""

from __future__ import annotations

import json

import numpy as np
import pytest

from tactdeform_hw.emulator import Emulator, HazardKind

from .conftest import DATA

VECTORS = [
    json.loads(line) for line in (DATA / "protocol_vectors_v2.jsonl").read_text().splitlines() if line.strip()
]
TIMEOUT_US = 2_000_000


def test_all_vectors_present() -> None:
    assert len(VECTORS) == 300


def _arrivals(vector: dict) -> list[tuple[int, bytes]]:
    if "arrivals" in vector:
        return [(int(t), bytes.fromhex(h)) for t, h in vector["arrivals"]]
    return [(0, bytes.fromhex(vector["stream"]))]


def _drive(
    vector: dict, arrivals: list[tuple[int, bytes]], final_time_us: int | None
) -> tuple[Emulator, bytes]:
    board = vector["board"]
    emu = Emulator(
        board["kind"], board["switching_boards"], stack_reading=board.get("stack_reading"), firmware="v2"
    )
    tx = b"".join(emu.feed(data, at_us=t) for t, data in arrivals)
    if final_time_us is not None:
        tx += emu.advance(final_time_us)
    return emu, tx


def _check(vector: dict, emu: Emulator, tx: bytes) -> None:
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


@pytest.mark.parametrize("index", range(len(VECTORS)), ids=[v["id"] for v in VECTORS])
def test_vector_as_recorded(index: int) -> None:
    """The recorded arrivals (the whole stream at t = 0 when none are recorded) and ``final_time_us``."""
    vector = VECTORS[index]
    emu, tx = _drive(vector, _arrivals(vector), vector.get("final_time_us"))
    _check(vector, emu, tx)


def _split_is_harmless(vector: dict) -> bool:
    """Whether the firmware's state cannot depend on the split: no arrival or final poll is more than
    the timeout after the first byte (a payload then always completes within 2 s of its command byte)."""
    times = [t for t, _ in _arrivals(vector)] + [vector.get("final_time_us") or 0]
    return max(times) <= TIMEOUT_US


ONE_ARRIVAL = [i for i, v in enumerate(VECTORS) if _split_is_harmless(v)]


@pytest.mark.parametrize("index", ONE_ARRIVAL, ids=[VECTORS[i]["id"] for i in ONE_ARRIVAL])
def test_vector_in_one_arrival(index: int) -> None:
    """The whole stream at once, then the recorded final time."""
    vector = VECTORS[index]
    emu, tx = _drive(vector, [(0, bytes.fromhex(vector["stream"]))], vector.get("final_time_us"))
    _check(vector, emu, tx)


def test_one_arrival_covers_the_set() -> None:
    """Every vector whose state can be split-independent is checked in one arrival too."""
    assert len(ONE_ARRIVAL) >= 270
    assert sum(1 for i in ONE_ARRIVAL if "arrivals" in VECTORS[i]) >= 20


UPSTREAM = [
    i for i, v in enumerate(VECTORS) if _split_is_harmless(v) and not v["category"].startswith("overflow")
]


@pytest.mark.parametrize("index", UPSTREAM[::7])
def test_vector_as_upstream_host_writes_it(index: int) -> None:
    """The upstream Python and Unity APIs write 8-byte chunks with 3 ms gaps: same state."""
    vector = VECTORS[index]
    data = bytes.fromhex(vector["stream"])
    chunks = [(3000 * k, data[i : i + 8]) for k, i in enumerate(range(0, len(data), 8))]
    if chunks and chunks[-1][0] > TIMEOUT_US:
        pytest.skip("stream longer than the timeout at 8 bytes per 3 ms")
    emu, tx = _drive(vector, chunks, vector.get("final_time_us"))
    _check(vector, emu, tx)


def _hazard_kinds(emu: Emulator) -> set[HazardKind]:
    return {h.kind for h in emu.hazards}


def test_timeout_is_recorded_with_what_it_discarded() -> None:
    vector = next(v for v in VECTORS if v["id"] == "v2-0276")
    emu, _ = _drive(vector, _arrivals(vector), vector["final_time_us"])
    timeouts = [h for h in emu.hazards if h.kind is HazardKind.COMMAND_TIMEOUT]
    assert len(timeouts) == 1
    assert timeouts[0].detail["command"] == "PATTERN" and timeouts[0].detail["discarded"] == 5


def test_pending_command_is_recorded() -> None:
    emu = Emulator(firmware="v2")
    emu.feed(bytes.fromhex("fc04fe0101"))
    assert emu.state().command_in_progress
    assert HazardKind.COMMAND_PENDING in _hazard_kinds(emu)


def test_v12_host_bytes_are_recorded_as_defects() -> None:
    """A v1.2 pulse-height command: ``FB 64 00`` sets mode 2 (clamped) and the 00 is an unknown byte."""
    emu = Emulator(firmware="v2")
    emu.feed(bytes.fromhex("fb6400"))
    assert emu.state().stim_mode == 2
    assert {HazardKind.CLAMPED, HazardKind.UNKNOWN_BYTES} <= _hazard_kinds(emu)


def test_desync_and_clamp_and_stale_are_recorded() -> None:
    emu = Emulator(firmware="v2")
    emu.feed(bytes.fromhex("fc02fe" + "ffff" + "0100") + bytes.fromhex("fc01fc02"))
    kinds = _hazard_kinds(emu)
    assert HazardKind.CLAMPED in kinds and HazardKind.STALE_CHANNELS in kinds
    emu.feed(bytes.fromhex("fafd00"))
    assert HazardKind.PAYLOAD_HOLDS_COMMAND_BYTE in _hazard_kinds(emu)
    assert emu.state().pulse_width_us == 0x00FD


def test_queue_overflow_is_recorded() -> None:
    emu = Emulator(firmware="v2")
    emu.feed(bytes(1500))
    assert emu.state().rx_dropped == 1500 - 1024
    assert HazardKind.QUEUE_OVERFLOW in _hazard_kinds(emu)


def test_unknown_firmware_is_refused() -> None:
    from tactdeform_hw.errors import ConfigurationError

    with pytest.raises(ConfigurationError, match="firmware='v3'"):
        Emulator(firmware="v3")


def test_mode_2_with_zero_heights_is_recorded_when_it_starts() -> None:
    emu = Emulator(firmware="v2")
    emu.feed(bytes.fromhex("fc02fe00000000f90a"))
    assert HazardKind.MODE_SENSE_ALL not in _hazard_kinds(emu)
    emu.feed(bytes.fromhex("fb02"))
    hz = [h for h in emu.hazards if h.kind is HazardKind.MODE_SENSE_ALL]
    assert len(hz) == 1 and hz[0].detail["channels"] == [0, 1] and hz[0].detail["sense_code"] == 10
    emu.feed(bytes.fromhex("f90b"))
    assert len([h for h in emu.hazards if h.kind is HazardKind.MODE_SENSE_ALL]) == 1  # still the same state


def test_a_new_client_inherits_a_cut_command_within_2_s() -> None:
    """Wi-Fi build: nothing resets the parser on reconnect.  A cut 0xFE (2 electrodes) followed within
    2 s by a new client's setup stores 0x20FC as a height, clamped to 4095 — recorded."""
    emu = Emulator(firmware="v2")
    emu.feed(bytes.fromhex("fc02fe"), at_us=0)
    assert emu.feed(bytes.fromhex("fc20fb00f4"), at_us=1_500_000) == b"\x02"  # the count is still 2
    assert list(emu.state().stim_pattern[:2]) == [4095, 0x00FB]
    clamped = [
        h for h in emu.hazards if h.kind is HazardKind.CLAMPED and h.detail.get("field") == "stim_pattern"
    ]
    assert clamped and clamped[0].detail["values"][0] == 0x20FC
    # after 2 s the same bytes would have found the parser free
    late = Emulator(firmware="v2")
    late.feed(bytes.fromhex("fc02fe"), at_us=0)
    assert late.feed(bytes.fromhex("fc20fb00f4"), at_us=2_100_000) == b"\x20"
