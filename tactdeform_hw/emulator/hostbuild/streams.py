"""Byte streams for the firmware differential: timed writes a host could send, edges first, then random.

A :class:`Stream` is a list of writes, each a time and bytes, and an end time: both sides of a comparison
are fed the same writes at the same virtual times.  Three sources:

* :func:`edge_streams` — every opcode of the protocol with the payload edges (0, 1, the clamp, the
  largest value, a value the firmware ignores), electrode counts 0, 1 and 255 before and after a pattern, a
  command cut in half with the rest arriving later, a burst larger than the receive queue, unknown bytes;
* :func:`random_stream` — a seeded mix of well-formed commands, cut commands, overflowing bursts and raw
  random bytes, at random arrival times;
* :func:`recorded_streams` — the golden vectors' streams (``protocol_vectors*.jsonl``), as recorded.

With no protocol (a firmware that speaks something else) the generator speaks raw bytes: every byte value
as a first byte, then random bytes.
"""

from __future__ import annotations

import json
import math
import random
from dataclasses import dataclass
from pathlib import Path

from tactdeform_hw.errors import ConfigurationError
from tactdeform_hw.protocol.constants import U8_MAX
from tactdeform_hw.protocol.firmware import FirmwareSpec

SETUP_US = 2000.5
"""The host's first byte arrives this long after boot, once the firmware's ``setup()`` (1010.25 µs on the
upstream trees: the stack detection) has run: the Python model's parser runs from 0, the firmware's only
after ``setup()``, so earlier bytes would measure the boot, not the parser."""

TICK_US = 1000.0
"""The RTOS tick.  No write arrives exactly on one: at a tie the host build delivers the bytes before the
main loop wakes and the model wakes the loop first, a convention of each, not a behaviour (see
:func:`off_tick`)."""


def off_tick(t_us: float) -> float:
    """``t_us``, moved 0.5 µs later when it falls exactly on an RTOS tick."""
    return t_us + 0.5 if math.isclose(math.fmod(t_us, TICK_US), 0.0, abs_tol=1e-6) else t_us


@dataclass(frozen=True)
class Stream:
    """Writes ``(at_us, bytes)`` in time order, then the run continues to ``end_us``."""

    writes: tuple[tuple[float, bytes], ...]
    end_us: float
    label: str = ""

    @property
    def size(self) -> int:
        return sum(len(b) for _, b in self.writes)

    def to_dict(self) -> dict[str, object]:
        return {
            "label": self.label,
            "end_us": self.end_us,
            "writes": [{"at_us": t, "hex": b.hex()} for t, b in self.writes],
        }


def _end(writes: list[tuple[float, bytes]], settle_us: float) -> float:
    last = max((t for t, _ in writes), default=SETUP_US)
    total = sum(len(b) for _, b in writes)
    return last + settle_us + 1000.0 * min(total, 600)  # a byte per RTOS tick at worst, bounded


def _command(spec: FirmwareSpec, op: int, value: int, electrodes: int, rng: random.Random) -> bytes:
    size = spec.size_of(op, electrodes)
    if size is None or size == 0:
        return bytes([op])
    if spec.by_opcode[op].kind == "pattern":
        per = spec.pattern_bytes_per_electrode
        body = bytearray()
        for _ in range(electrodes):
            level = rng.choice((0, 1, 2, 3, U8_MAX, rng.randrange(1 << (8 * per))))
            body += level.to_bytes(per, "little")
        return bytes([op]) + bytes(body)
    return bytes([op]) + (value & ((1 << (8 * size)) - 1)).to_bytes(size, "little")


def _edges(spec: FirmwareSpec, op: int) -> list[int]:
    c = spec.by_opcode[op]
    if c.kind in (None, "pattern"):
        return [0]
    top = (1 << (8 * (2 if c.kind == "u16" else 1))) - 1
    vals = {0, 1, 2, top, top - 1}
    if c.max_value is not None:
        vals |= {c.max_value, c.max_value + 1, c.max_value - 1}
    return sorted(v for v in vals if 0 <= v <= top)


def edge_streams(spec: FirmwareSpec | None, settle_us: float = 30_000.0) -> list[Stream]:
    """The deterministic streams: every opcode and payload edge (see the module documentation)."""
    rng = random.Random(0)
    out: list[Stream] = []
    if spec is None:
        for first in range(256):
            w = [(SETUP_US, bytes([first, 0, 1, U8_MAX, 0x10, 0x0F]))]
            out.append(Stream(tuple(w), _end(w, settle_us), f"edge byte 0x{first:02X}"))
        return out
    pat = spec.pattern_command.opcode
    en = spec.opcode_of("electrode_num")
    for op in sorted(spec.by_opcode):
        for v in _edges(spec, op):
            for n in (0, 1, U8_MAX):
                data = bytes([en, n]) + _command(spec, pat, 0, n, rng) + _command(spec, op, v, n, rng)
                w = [(SETUP_US, data)]
                out.append(Stream(tuple(w), _end(w, settle_us), f"edge 0x{op:02X}={v} electrodes={n}"))
        cmd = _command(spec, op, _edges(spec, op)[-1], 4, rng)
        if len(cmd) > 1:  # cut in half, the rest 1.5 ms later
            half = len(cmd) // 2 or 1
            w = [(SETUP_US, bytes([en, 4]) + cmd[:half]), (SETUP_US + 1500.0, cmd[half:])]
            out.append(Stream(tuple(w), _end(w, settle_us), f"edge 0x{op:02X} cut"))
    known = set(spec.by_opcode)
    unknown = bytes(b for b in range(256) if b not in known)
    w = [(SETUP_US, unknown)]
    out.append(Stream(tuple(w), _end(w, settle_us), "edge unknown bytes"))
    burst = bytes([en, U8_MAX]) + _command(spec, pat, 0, U8_MAX, rng) + _command(spec, pat, 0, U8_MAX, rng)
    w = [(SETUP_US, burst)]
    out.append(Stream(tuple(w), _end(w, settle_us), "edge overflowing burst"))
    return out


def random_stream(spec: FirmwareSpec | None, seed: int, settle_us: float = 20_000.0) -> Stream:
    """One seeded random stream (see the module documentation)."""
    rng = random.Random(seed)
    t = SETUP_US + rng.choice((0.0, rng.uniform(0, 3000)))
    writes: list[tuple[float, bytes]] = []
    electrodes = 0
    for _ in range(rng.randint(1, 6)):
        roll = rng.random()
        if spec is None or roll < 0.12:
            data = bytes(rng.randrange(256) for _ in range(rng.randint(1, 12)))
        else:
            ops = sorted(spec.by_opcode)
            data = b""
            for _ in range(rng.randint(1, 5)):
                op = rng.choice(ops)
                if spec.by_opcode[op].register == "electrode_num":
                    v = rng.choice((0, 1, 2, 4, 8, 32, U8_MAX, rng.randrange(256)))
                else:
                    v = rng.choice([*_edges(spec, op), rng.randrange(1 << 16)])
                cmd = _command(spec, op, v, electrodes, rng)
                if spec.by_opcode[op].register == "electrode_num":
                    electrodes = v & 0xFF
                data += cmd
            if roll > 0.9:  # an overflowing burst: the same commands many times in one write
                data = data * rng.randint(2, 40)
            elif roll > 0.75 and len(data) > 1:  # cut: the rest arrives later
                cut = rng.randrange(1, len(data))
                writes.append((t, data[:cut]))
                t += (
                    rng.uniform(1_900_000, 2_100_000)
                    if rng.random() < 0.03
                    else rng.choice((0.0, 40.0, rng.uniform(0, 4000)))
                )
                data = data[cut:]
        writes.append((t, data))
        t += rng.choice((0.0, 10.0, rng.uniform(0, 1500), rng.uniform(0, 12_000)))
    t_round = [(off_tick(round(at, 3)), b) for at, b in writes]
    return Stream(tuple(t_round), round(_end(t_round, settle_us), 3), f"random seed {seed}")


def recorded_streams(path: Path, settle_us: float = 30_000.0) -> list[Stream]:
    """The golden vectors' streams (``stream`` hex, or v2's timed ``arrivals``), shifted past setup."""
    out: list[Stream] = []
    try:
        lines = path.read_text(encoding="utf-8").splitlines()
    except OSError as exc:
        raise ConfigurationError(f"recorded streams {path}: {exc.strerror or exc}") from exc
    for n, line in enumerate(lines, 1):
        if not line.strip():
            continue
        try:
            v = json.loads(line)
            arrivals = v.get("arrivals") or [[0, v["stream"]]]
            w = [(off_tick(SETUP_US + float(t)), bytes.fromhex(hx)) for t, hx in arrivals]
        except (ValueError, KeyError, TypeError) as exc:
            raise ConfigurationError(f"recorded streams {path}:{n}: not a golden vector ({exc})") from exc
        out.append(Stream(tuple(w), _end(w, settle_us), f"recorded {v.get('id', n)}"))
    return out
