"""``tactdeform-hw decode``: a byte capture → one readable line per command."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

from ..errors import ConfigurationError
from .common import print_json


def register(sub: Any) -> None:
    p: argparse.ArgumentParser = sub.add_parser(
        "decode",
        help="decode a host-to-device byte capture into commands",
        description="Decode bytes sent to an eTactileKit the way its firmware reads them: one line per "
        "command with its byte offset. Truncated commands, unknown bytes, a parser-locking pattern and the "
        "bytes a locked parser never reads are marked.",
    )
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument(
        "hex", nargs="?", help="hex bytes, e.g. 'fc 20 fe 01 01 ...' (spaces, colons, 0x allowed)"
    )
    src.add_argument(
        "--file",
        type=Path,
        help="capture file ('-' for standard input): raw bytes, or hex text with --hex-file (a file of hex "
        "text read as raw bytes is refused: every command byte of the firmware is 0xF4 or above)",
    )
    p.add_argument("--hex-file", action="store_true", help="the --file holds hex text, not raw bytes")
    p.add_argument(
        "--electrodes",
        type=int,
        default=0,
        help="electrode_num in force when the capture starts, 0-255 (default 0, power-on)",
    )
    p.add_argument(
        "--firmware",
        default="v1.2",
        help="the firmware whose parser reads the capture: v1.2 (default) or v2; v2 reads 0xFB as the "
        "stimulation mode, one u16 per electrode in a pattern and 0xF4 as the sync check (without "
        "arrival times, its 2 s timeout is not applied)",
    )
    p.add_argument("--json", action="store_true", help="print a JSON list instead of lines")
    p.set_defaults(func=run)


def read_hex(text: str) -> bytes:
    """Bytes from hex text (spaces, colons, commas, ``0x`` allowed between bytes); refused, naming the
    position in the text (counted from 0), when a byte has one digit or a character is not hex."""
    from ..protocol.decoder import parse_hex

    odd_at: int | None = None  # where the byte being read started, while it has one digit
    i, n = 0, len(text)
    while i < n:
        ch = text[i]
        if odd_at is None and text.startswith(("0x", "0X"), i) and i + 2 < n and text[i + 2] in _HEX:
            i += 2
            continue
        if ch in _HEX:
            odd_at = i if odd_at is None else None
        elif ch in _SEPARATORS:
            if odd_at is not None:
                break
        else:
            raise ConfigurationError(f"{ch!r} at position {i} is not a hex digit")
        i += 1
    if odd_at is not None:
        raise ConfigurationError(f"odd number of hex digits at position {odd_at}: a byte is two digits")
    return parse_hex(text)


def looks_like_hex_text(raw: bytes) -> bool:
    """Raw bytes that are all hex digits, separators and ``0x``: hex text.  A real capture has command
    bytes (0xF4 and above), which no text holds."""
    text = raw.decode("latin-1")
    return bool(text.strip()) and all(ch in _HEX or ch in _SEPARATORS or ch in "xX" for ch in text)


_HEX = frozenset("0123456789abcdefABCDEF")
_SEPARATORS = frozenset(" \t\r\n:,;-")


def run(args: argparse.Namespace) -> int:
    from ..protocol.decoder import OK, decode
    from ..protocol.firmware import get_firmware
    from .options import check_range

    firmware = get_firmware(args.firmware, "--firmware")
    check_range("--electrodes", args.electrodes, 0, firmware.max_electrodes)
    parse_hex = read_hex
    try:
        if args.file is not None:
            raw = sys.stdin.buffer.read() if str(args.file) == "-" else args.file.read_bytes()
            if not args.hex_file and looks_like_hex_text(raw):
                raise ConfigurationError(
                    f"--file {args.file}: holds hex text ({raw[:16].decode('ascii').strip()!r}…), not raw "
                    "bytes; give --hex-file to decode it as hex"
                )
            data = parse_hex(raw.decode("ascii")) if args.hex_file else raw
        else:
            data = parse_hex(args.hex)
    except ConfigurationError:
        raise
    except (ValueError, UnicodeDecodeError) as exc:
        raise ConfigurationError(
            f"cannot read the capture as {'hex' if args.hex_file or args.file is None else 'bytes'}: {exc}"
        ) from exc
    except OSError as exc:
        raise ConfigurationError(f"cannot read {args.file}: {exc}") from exc
    if not data:
        raise ConfigurationError("the capture is empty: no bytes to decode")
    items = decode(data, args.electrodes, firmware)
    if args.json:
        print_json([c.to_dict() for c in items])
    else:
        for c in items:
            print(c.describe())
        bad = sum(1 for c in items if c.status != OK)
        if firmware.command_timeout_us is not None and any(c.status == "truncated" for c in items):
            print(
                f"# firmware {firmware.name}: a cut command is completed by the bytes sent within "
                f"{firmware.command_timeout_us / 1e6:g} s of its command byte, else discarded with "
                "everything queued then",
                file=sys.stderr,
            )
        print(
            f"# firmware {firmware.name}: {len(data)} bytes, {len(items)} item(s), {bad} marked",
            file=sys.stderr,
        )
    return 0
