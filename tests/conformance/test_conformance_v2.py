"""Conformance of a firmware v2 target: the package's checks
(:mod:`~tactdeform_hw.testing.conformance.checks_v2`: the sync check, the measure reply, version
detection, the device layer driving per-electrode heights, the 2 s command timeout), and an
upstream-style host (8-byte chunks, 3 ms apart) reaching the state the golden vectors of this repository
predict.

Emulated v2 targets (:data:`~tactdeform_hw.testing.conformance.targets.V2_TARGETS`), each transport the
v1.2 suite runs on, serving v2: the pyserial URL handler with the untimed v2 emulator
(``etactile://?firmware=v2&timed=0``) and with the timed v2 board on the wall clock
(``etactile://?firmware=v2``), a pseudo-terminal (``pty?firmware=v2``), a TCP port with the Wi-Fi build's
rules (``tcp?firmware=v2``) and the emulated USB device through pyusb (``usb-emulator?firmware=v2``).
``--device`` with a real v2 board (a serial port or ``usb:``) runs the same checks on it, except the
vector replay, which sets non-zero heights; ``--device`` naming a v1.2 emulated target skips this file.
"""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Any

import pytest

from tactdeform_hw.emulator.firmware.registers import V2_SCAN_REGISTERS
from tactdeform_hw.testing.conformance.checks_v2 import *  # noqa: F403 - the checks, their fixture and hook
from tactdeform_hw.testing.conformance.checks_v2 import read_reply
from tactdeform_hw.testing.conformance.targets import Target

# --- an upstream-style host: 8-byte chunks, 3 ms apart -----------------------------------------------------

VECTORS_FILE = Path(__file__).resolve().parents[1] / "data" / "protocol_vectors_v2.jsonl"
#: golden streams a host could send from power-up, covering the upstream API's configuration burst
#: (v2-0065), a configuration burst (v2-0002), complete patterns (v2-0001; v2-0027 leaves stale channels
#: past the count), a pattern still waiting for its payload (v2-0009), unknown bytes before a command
#: (v2-0246), the sync check (v2-0072) and measure requests between sync checks (v2-0041).  All arrive in
#: one piece in the vectors and end within the 2 s timeout, so the split cannot change the final state.
UPSTREAM_VECTORS = ("v2-0065", "v2-0002", "v2-0001", "v2-0027", "v2-0009", "v2-0246", "v2-0072", "v2-0041")
#: what the upstream Python ``write_byte_array`` and Unity ``SerialHandler.Write`` do: 8 bytes, then 3 ms
CHUNK_BYTES = 8
CHUNK_GAP_S = 0.003
#: the registers a vector predicts (``period_us`` is compared as float32, as the firmware stores it)
COMPARED = (
    *V2_SCAN_REGISTERS,
    "timer_alarm_ticks",
    "hv513_num",
    "stim_pattern",
    "command_in_progress",
)


def _vectors() -> dict[str, dict[str, Any]]:
    wanted = set(UPSTREAM_VECTORS)
    out: dict[str, dict[str, Any]] = {}
    for line in VECTORS_FILE.read_text().splitlines():
        if line.strip():
            vec = json.loads(line)
            if vec["id"] in wanted:
                out[vec["id"]] = vec
    return out


VECTORS = _vectors()


@pytest.mark.parametrize("vector_id", UPSTREAM_VECTORS)
def test_v2_upstream_host_in_8_byte_chunks_reaches_the_vectors_state(
    v2_target: Target, vector_id: str
) -> None:
    """The upstream APIs pace every write (8 bytes, 3 ms); through the transport, the board must end in
    the state the firmware's own parser gives for the stream in one piece, and answer the same bytes."""
    if v2_target.is_board:
        pytest.skip("the vectors set non-zero heights with channels on: replayed on emulated targets only")
    vec = VECTORS[vector_id]
    assert "arrivals" not in vec and "final_time_us" not in vec, "the replay needs a one-arrival vector"
    board = vec["board"]
    assert (board["kind"], board["switching_boards"]) == ("compact", 1), "the targets serve one compact board"
    stream = bytes.fromhex(vec["stream"])
    expect = vec["expect"]
    want_tx = bytes.fromhex(expect["tx"])
    port = v2_target.open()  # a fresh target: the board is at its power-on state, as the vectors assume
    try:
        for i in range(0, len(stream), CHUNK_BYTES):
            port.write(stream[i : i + CHUNK_BYTES])
            time.sleep(CHUNK_GAP_S)
        replies = read_reply(port, len(want_tx)) if want_tx else b""
        v2_target.settle(len(stream))
        port.timeout = v2_target.quiet_s
        extra = bytes(port.read(1))
        assert replies == want_tx, f"{vector_id}: replies {replies.hex()} instead of {want_tx.hex()}"
        assert extra == b"", f"{vector_id}: a reply byte {extra.hex()} the vector does not predict"
        if v2_target.state is not None:
            state = v2_target.state()
            held = state.as_dict()
            for key in COMPARED:
                if key == "command_in_progress" and key not in held:
                    continue  # a host build: the parser's progress is a function-local static
                assert held[key] == expect[key], f"{vector_id}: {key}"
            assert float(state.period_us) == pytest.approx(expect["period_us"], rel=1e-6)
    finally:
        port.close()
