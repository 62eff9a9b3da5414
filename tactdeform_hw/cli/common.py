"""Options shared by subcommands."""

from __future__ import annotations

import argparse
import json
import sys
from typing import Any

DEVICE_HELP = (
    "serial port path (e.g. /dev/ttyACM0), pyserial URL (e.g. etactile://?board=compact), "
    "or 'emulator' (default: the in-process emulator)"
)


def add_device_arg(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--device", default="emulator", help=DEVICE_HELP)
    parser.add_argument("--timeout", type=float, default=0.5, help="read/write timeout in seconds (default 0.5)")


def print_json(obj: Any) -> None:
    json.dump(obj, sys.stdout, indent=2, sort_keys=False, default=str)
    sys.stdout.write("\n")


def progress(msg: str) -> None:
    print(msg, file=sys.stderr, flush=True)
