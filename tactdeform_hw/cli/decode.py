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
    src.add_argument("hex", nargs="?", help="hex bytes, e.g. 'fc 20 fe 01 01 ...' (spaces, colons, 0x allowed)")
    src.add_argument("--file", type=Path, help="capture file: raw bytes, or hex text with --hex-file")
    p.add_argument("--hex-file", action="store_true", help="the --file holds hex text, not raw bytes")
    p.add_argument("--electrodes", type=int, default=0, help="electrode_num in force when the capture starts (default 0, power-on)")
    p.add_argument("--firmware", default="v1.2",
                   help="the firmware whose parser reads the capture: v1.2 (default) or v2; v2 reads 0xFB as the "
                   "stimulation mode, one u16 per electrode in a pattern and 0xF4 as the sync check (without "
                   "arrival times, its 2 s timeout is not applied)")
    p.add_argument("--json", action="store_true", help="print a JSON list instead of lines")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from ..protocol.decoder import OK, decode, parse_hex
    from ..protocol.firmware import get_firmware
    from ..protocol.units import check_int

    firmware = get_firmware(args.firmware, "--firmware")

    try:
        if args.file is not None:
            raw = args.file.read_bytes()
            data = parse_hex(raw.decode("ascii")) if args.hex_file else raw
        else:
            data = parse_hex(args.hex)
    except (ValueError, UnicodeDecodeError) as exc:
        raise ConfigurationError(f"cannot read the capture as {'hex' if args.hex_file or args.file is None else 'bytes'}: {exc}") from exc
    except OSError as exc:
        raise ConfigurationError(f"cannot read {args.file}: {exc}") from exc
    electrodes = check_int("--electrodes", args.electrodes, 0, firmware.max_electrodes)
    items = decode(data, electrodes, firmware)
    if args.json:
        print_json([c.to_dict() for c in items])
    else:
        for c in items:
            print(c.describe())
        bad = sum(1 for c in items if c.status != OK)
        if firmware.command_timeout_us is not None and any(c.status == "truncated" for c in items):
            print(f"# firmware {firmware.name}: a cut command is completed by the bytes sent within "
                  f"{firmware.command_timeout_us / 1e6:g} s of its command byte, else discarded with everything "
                  "queued then", file=sys.stderr)
        print(f"# firmware {firmware.name}: {len(data)} bytes, {len(items)} item(s), {bad} marked", file=sys.stderr)
    return 0
