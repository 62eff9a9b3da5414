"""What only v2's golden vectors hold: recorded arrival times, the 2 s command timeout, the upstream host's
8-byte chunks, and the hazards the emulator records on the way.  Every vector in one arrival and byte by
byte, on every version, is in ``test_golden_vectors.py``."""

from __future__ import annotations

import pytest

from tactdeform_hw.emulator import Emulator, HazardKind
from tactdeform_hw.protocol.firmware import V2

from .test_golden_vectors import ONE_ARRIVAL, VECTORS, arrivals, check, drive, split_is_harmless

FIRMWARE = V2.name
V2_VECTORS = VECTORS[FIRMWARE]
TIMEOUT_US = V2.command_timeout_us


@pytest.mark.parametrize("index", range(len(V2_VECTORS)), ids=[v["id"] for v in V2_VECTORS])
def test_vector_as_recorded(index: int) -> None:
    """The recorded arrivals (the whole stream at t = 0 when none are recorded) and ``final_time_us``."""
    vector = V2_VECTORS[index]
    emu, tx = drive(FIRMWARE, vector, arrivals(vector), vector.get("final_time_us"))
    check(vector, emu, tx)


def test_one_arrival_covers_the_set() -> None:
    """Every vector whose state can be split-independent is checked in one arrival too, recorded arrival
    times among them."""
    one = [i for fw, i in ONE_ARRIVAL if fw == FIRMWARE]
    assert len(one) >= 270
    assert sum(1 for i in one if "arrivals" in V2_VECTORS[i]) >= 20


UPSTREAM = [
    i
    for i, v in enumerate(V2_VECTORS)
    if split_is_harmless(FIRMWARE, v) and not v["category"].startswith("overflow")
]


@pytest.mark.parametrize("index", UPSTREAM[::7])
def test_vector_as_upstream_host_writes_it(index: int) -> None:
    """The upstream Python and Unity APIs write 8-byte chunks with 3 ms gaps: same state."""
    vector = V2_VECTORS[index]
    data = bytes.fromhex(vector["stream"])
    chunks = [(3000 * k, data[i : i + 8]) for k, i in enumerate(range(0, len(data), 8))]
    if chunks and chunks[-1][0] > TIMEOUT_US:
        pytest.skip("stream longer than the timeout at 8 bytes per 3 ms")
    emu, tx = drive(FIRMWARE, vector, chunks, vector.get("final_time_us"))
    check(vector, emu, tx)


def _hazard_kinds(emu: Emulator) -> set[HazardKind]:
    return {h.kind for h in emu.hazards}


def test_timeout_is_recorded_with_what_it_discarded() -> None:
    vector = next(v for v in V2_VECTORS if v["id"] == "v2-0276")
    emu, _ = drive(FIRMWARE, vector, arrivals(vector), vector["final_time_us"])
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
