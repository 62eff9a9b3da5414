"""``tactdeform-hw``: one console script, one module per subcommand (``register`` + ``run``)."""

from __future__ import annotations

import argparse
import errno
import importlib
import logging
import os
import sys
import traceback
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from typing import Any

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
    "diff_firmware",
)


#: The exit statuses, as ``--help`` and the researcher's guide give them.
EXIT_STATUS_HELP = """exit status:
  0    done
  1    refused (a value out of range, a safety limit, a bad file, an output that cannot be
       written, no device: checked before the device is opened, so nothing was sent)
       or failed while running
  2    usage: unknown option, missing value, a value of the wrong kind (not a number,
       a negative duration, not one of the choices)
  3    a check failed: study (a trial check, or a trial skipped), replay-log --participant
       (a pulse above the limits), timing (the scan OVERRUNs its period)
  4    timing: the scan trips the interrupt WATCHDOG (the board resets)
  130  interrupted (Ctrl-C); emulate, a server that runs until it is stopped, ends with 0 on
       Ctrl-C or SIGTERM (its normal stop)
  141  standard output was closed (e.g. piped into head)

Every error is one line 'tactdeform-hw COMMAND: error: ...'; --debug adds the traceback."""


class CommandLineParser(argparse.ArgumentParser):
    """The top-level parser, knowing each command's own parser (so an error names the command and shows
    its usage)."""

    def __init__(self, **kwargs: Any) -> None:
        super().__init__(**kwargs)
        self.commands: dict[str, argparse.ArgumentParser] = {}


def build_parser() -> CommandLineParser:
    from .. import __version__

    parser = CommandLineParser(
        prog="tactdeform-hw",
        description="eTactileKit protocol tools, a byte-exact firmware emulator and the TactDeform renderer. "
        "Every command that talks to a device takes --device: a serial port path, a pyserial URL, or "
        "'emulator' (the default: the in-process emulator, no hardware needed).",
        epilog=EXIT_STATUS_HELP,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--version", action="version", version=f"%(prog)s {__version__}")
    parser.add_argument(
        "--debug",
        action="store_true",
        help="on an error, also print the Python traceback (for a bug report); may also "
        "follow the command's own options",
    )
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name in COMMANDS:
        importlib.import_module(f".{name}", __name__).register(sub)
    parser.commands = dict(sub.choices)
    return parser


#: Exit statuses shared by every command (a command may add its own, documented in its --help).
EXIT_FAILED = 1
EXIT_USAGE = 2

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
    words = list(sys.argv[1:] if argv is None else argv)
    end = words.index("--") if "--" in words else len(words)
    debug = "--debug" in words[:end]  # accepted anywhere on the line, where a user adds it after an error
    args, extra = parser.parse_known_args([w for i, w in enumerate(words) if i >= end or w != "--debug"])
    if extra:  # said by the command's own parser, so the line names the command and shows its usage
        commands = parser.commands
        (commands.get(getattr(args, "command", None) or "") or parser).error(
            f"unrecognized arguments: {' '.join(extra)}"
        )
    args.debug = debug
    if not getattr(args, "func", None):
        parser.print_help()
        return EXIT_USAGE
    prog = f"tactdeform-hw {args.command}"
    try:
        with _console_log(prog):
            from .options import finish
            from .outputs import preflight

            finish(args)  # the command's own conversions and checks (µA → the DAC code timing takes)
            preflight(args, warn=lambda m: print(f"{prog}: warning: {m}", file=sys.stderr, flush=True))
            from .common import run_command

            return run_command(args.func, args)
    except KeyboardInterrupt:
        return 130
    except BrokenPipeError:
        raise
    except Exception as exc:  # every error ends in one line; --debug adds the traceback
        if getattr(args, "debug", False):
            traceback.print_exc()
        print(f"{prog}: error: {_describe(exc, args)}", file=sys.stderr, flush=True)
        return EXIT_FAILED


def _describe(exc: BaseException, args: argparse.Namespace) -> str:
    """One line for the user: what was wrong, naming the flag or the file."""
    from .options import user_message

    if isinstance(exc, TactDeformError):
        return user_message(exc, args.command, args) + _device_hint(exc, args)
    if isinstance(exc, OSError):
        name = exc.filename if exc.filename is not None else ""
        what = exc.strerror or str(exc)
        if not name:
            return _output_error(exc, args) or what
        return f"{name}: {what}"
    if isinstance(exc, ImportError):
        return f"the Python package {exc.name!r} is not installed ({exc})" if exc.name else str(exc)
    hint = "" if getattr(args, "debug", False) else "; run 'tactdeform-hw --debug ...' for the traceback"
    return f"unexpected {type(exc).__name__}: {exc}{hint}"


def _device_hint(exc: TactDeformError, args: argparse.Namespace) -> str:
    """What to type instead, for the device errors a new user meets: the in-process emulator asked for
    v2 (it is a v1.2 board; an emulated v2 board is a URL), a path that opens but takes no serial
    settings (``/dev/null``: the operating system's errno alone says nothing of what to do)."""
    from ..errors import TransportError

    device = getattr(args, "device", None)
    name = type(exc).__name__
    if name == "FirmwareMismatchError" and device in ("emulator", "emu", "") and args.firmware == "v2":
        return (
            "; --device emulator is a v1.2 board: give --device 'etactile://?firmware=v2' for an emulated "
            "v2 board"
        )
    if isinstance(exc, TransportError) and "Could not configure port" in str(exc):
        return (
            f"; --device {device} opens but is not a serial port (it takes no baud rate); "
            "'tactdeform-hw ports' lists the boards it can see"
        )
    return ""


#: Errors a write to an output file ends with that carry no file name (a buffered write fails at its flush).
_OUTPUT_ERRNOS = (errno.ENOSPC, errno.EDQUOT, errno.EFBIG, errno.EROFS)


def _output_error(exc: OSError, args: argparse.Namespace) -> str | None:
    """The line for a write error without a file name: the outputs the command writes, each with its
    option, since a full disk or a quota says nothing of which file it stopped."""
    if exc.errno not in _OUTPUT_ERRNOS:
        return None
    from .outputs import planned_outputs

    try:
        outputs = [(path, flag) for path, flag, _kind in planned_outputs(args)]
    except Exception:  # the line must be printed whatever the arguments hold
        outputs = []
    what = exc.strerror or str(exc)
    if not outputs:
        return None
    if len(outputs) == 1:
        path, flag = outputs[0]
        return f"{flag} {path}: cannot be written ({what})"
    names = ", ".join(f"{flag} {path}" for path, flag in outputs)
    return f"one of the outputs ({names}) cannot be written ({what})"


class _ConsoleHandler(logging.Handler):
    """The package's warnings on stderr, one line each, prefixed like every other message of the command.

    A safety refusal is left out: the refused command ends with it as its error line, and printing it
    here too would say it twice."""

    def __init__(self, prog: str) -> None:
        super().__init__(logging.WARNING)
        self.prog = prog

    def emit(self, record: logging.LogRecord) -> None:
        if (
            record.name == "tactdeform_hw.safety"
            and str(record.msg).startswith("%s (%s)")
            and record.args
            and record.args[0] == "refused"  # type: ignore[index]
        ):
            return
        try:
            from .common import progress

            progress(f"{self.prog}: warning: {record.getMessage()}")  # one write: a stop cannot cut it
        except Exception:  # pragma: no cover - a closed stderr must not end the command
            pass


@contextmanager
def _console_log(prog: str) -> Iterator[None]:
    logger = logging.getLogger("tactdeform_hw")
    handler = _ConsoleHandler(prog)
    logger.addHandler(handler)
    try:
        yield
    finally:
        logger.removeHandler(handler)


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
