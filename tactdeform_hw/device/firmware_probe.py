"""Which firmware runs the board, found before the first stimulating byte.

v2 answers the sync check 0xF4 with its electrode count; v1.2 ignores 0xF4 as an unknown byte.  The board
may be in any parser state when a session starts (a cut command from an earlier host, a v1.2 parser
locked by a pattern with zero electrodes), so the probe first brings either firmware to a command boundary
with every current off, using only bytes that mean "less current" wherever either firmware reads them:

``00 × 512``  completes any command in progress on either version (the longest payload is v2's 2 × 255
              pattern bytes) — a zero is a pattern value of 0, an electrode count of 0, a stimulation
              mode of 0, a sense height of 0, and a width or rate that either version stores as 0 or
              ignores; past the pending command the zeros are unknown bytes;
``FC 00``     electrode count 0: neither firmware scans a channel any more;
``FB 00 00``  v1.2: pulse height 0 (a zero may have completed a half-received height, keeping its low
              byte); v2: mode 0 (off really is off) and an unknown byte;
``F9 00``     sense height 0 on both;
``F4``        the sync check: v2 replies ``0x00`` (the count just set), v1.2 reads an unknown byte.

Every suffix of this sequence, read from a command boundary, also ends at a boundary with the count at
0; that matters on v2, whose 2 s timeout may discard part of it when it arrives just as a stale command
times out.  Such a discard can swallow the whole probe, sync check included, so a missing reply is
checked once more with the whole probe (by then no command can be pending); a second silence means v1.2 (or a
v1.2 parser locked before the session, which reads nothing until reset).  A reply other than 0 means the bytes
were not read as sent: the board is reported, never driven.

The bytes go out in 64-byte writes with a gap between them, slow enough for v1.2's 256-byte queue even
while it scans; the sequence ends with the electrode count at 0, so the caller configures the board
afterwards in the detected version's commands.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass

from ..errors import ProtocolError
from ..protocol.firmware import V1_2, V2, FirmwareSpec, OpcodeV2

#: Zeros that complete the longest payload of every modelled firmware (v2: 2 × 255 pattern bytes).
FLUSH_ZEROS = max(f.max_electrodes * f.pattern_bytes_per_electrode for f in (V1_2, V2)) + 2
# electrode count 0; v1.2 pulse height 0 (v2: mode 0 and an unknown byte); sense height 0 — the same bytes
# on both versions, as the tables show (tests hold them to it)
SAFE_TAIL = bytes((OpcodeV2.ELECTRODE_NUM, 0, OpcodeV2.STIM_MODE, 0, 0, OpcodeV2.SENSE_HEIGHT, 0))
SYNC_CHECK = bytes((OpcodeV2.SYNC_CHECK,))
PROBE = bytes(FLUSH_ZEROS) + SAFE_TAIL + SYNC_CHECK
CHUNK_BYTES = 64


class FirmwareMismatchError(ProtocolError):
    """The board runs another firmware than the driver speaks (or answered what no firmware would)."""


@dataclass(frozen=True)
class Detection:
    """What the probe found, and the bytes it cost (the device counts them as its own writes)."""

    firmware: FirmwareSpec
    attempts: int
    reply: bytes
    bytes_sent: int = 0

    @property
    def name(self) -> str:
        return self.firmware.name


def detect_firmware(
    write: Callable[[bytes], object],
    read: Callable[[int], bytes],
    discard: Callable[[], object] = lambda: None,
    *,
    gap_s: float = 0.01,
    sleep: Callable[[float], object] = time.sleep,
) -> Detection:
    """Send :data:`PROBE` through ``write`` (``read(1)`` must return within the port's timeout, b"" when
    nothing came) and tell the version from the answer."""
    attempts = 0
    for attempts in (1, 2):
        for i in range(0, len(PROBE) - 1, CHUNK_BYTES):
            write(PROBE[i : min(i + CHUNK_BYTES, len(PROBE) - 1)])
            sleep(gap_s)
        discard()
        write(SYNC_CHECK)
        reply = read(1)
        if reply:
            if reply != b"\x00":
                raise FirmwareMismatchError(
                    f"the sync check after the electrode count 0 was answered {reply.hex()}, not 00: the "
                    "board did not read the probe as sent; nothing stimulating was sent"
                )
            return Detection(V2, attempts, reply, attempts * len(PROBE))
    return Detection(V1_2, attempts, b"", attempts * len(PROBE))


def check_firmware(expected: str, detection: Detection) -> None:
    """Refuse a board whose firmware is not the one the driver was told to speak."""
    if detection.name != expected:
        raise FirmwareMismatchError(
            f"the board runs firmware {detection.name} (sync check "
            f"{'answered' if detection.reply else 'unanswered'}), but firmware={expected!r} was asked for; "
            "nothing stimulating was sent"
        )
