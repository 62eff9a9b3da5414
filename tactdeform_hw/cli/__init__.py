"""``tactdeform-hw``: one console script, one module per subcommand (``register`` + ``run``)."""

from __future__ import annotations

import argparse
import importlib
import os
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


#: Exit status when the reader of stdout went away (``tactdeform-hw timing --json | head -3``): 128 + SIGPIPE,
#: what a shell reports for a tool the signal stopped, so ``set -o pipefail`` still sees the output was cut.
EXIT_BROKEN_PIPE = 141


def main(argv: Sequence[str] | None = None) -> int:
    """Run one command; its exit status.  A closed stdout ends the command quietly with
    :data:`EXIT_BROKEN_PIPE` instead of a traceback."""
    try:
        code = _main(argv)
        sys.stdout.flush()  # here, not at interpreter exit, where a broken pipe can no longer be caught
    except BrokenPipeError:
        _discard_stdout()
        return EXIT_BROKEN_PIPE
    except SystemExit:  # --help, --version, a usage error: argparse has written and exits
        try:
            sys.stdout.flush()
        except BrokenPipeError:
            _discard_stdout()
        raise
    return code


def _main(argv: Sequence[str] | None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "func", None):
        parser.print_help()
        return 2
    from .common import run_command

    try:
        return run_command(args.func, args)
    except TactDeformError as exc:
        print(f"tactdeform-hw {args.command}: error: {exc}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        return 130


def _discard_stdout() -> None:
    """Point stdout at the null device, so the interpreter's own flush at exit finds no broken pipe
    (the output still buffered is dropped: nobody reads it)."""
    try:
        fd = sys.stdout.fileno()
    except (AttributeError, OSError, ValueError):  # replaced by something without a descriptor
        return
    devnull = os.open(os.devnull, os.O_WRONLY)
    try:
        os.dup2(devnull, fd)
    finally:
        os.close(devnull)


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
