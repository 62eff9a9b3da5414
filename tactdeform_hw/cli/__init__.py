"""``tactdeform-hw``: one console script, one module per subcommand (``register`` + ``run``)."""

from __future__ import annotations

import argparse
import importlib
import sys
from collections.abc import Sequence

from ..errors import TactDeformError

#: Subcommand modules, in the order ``--help`` lists them.
COMMANDS: tuple[str, ...] = (
    "emulate",
    "ports",
    "decode",
    "send",
    "play",
    "export",
    "render",
    "study",
    "timing",
    "calibrate",
    "replay_log",
)


def build_parser() -> argparse.ArgumentParser:
    from .. import __version__

    parser = argparse.ArgumentParser(
        prog="tactdeform-hw",
        description="eTactileKit protocol tools, a byte-exact firmware emulator and the TactDeform renderer. "
        "Every command that talks to a device takes --device: a serial port path, a pyserial URL, or "
        "'emulator' (the default: the in-process emulator, no hardware needed).",
    )
    parser.add_argument("--version", action="version", version=f"%(prog)s {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name in COMMANDS:
        importlib.import_module(f".{name}", __name__).register(sub)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "func", None):
        parser.print_help()
        return 2
    try:
        return int(args.func(args) or 0)
    except TactDeformError as exc:
        print(f"tactdeform-hw {args.command}: error: {exc}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        return 130


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
