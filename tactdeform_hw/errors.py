"""The one exception tree of tactdeform_hw.

Every error the package raises derives from :class:`TactDeformError`, so a study script can catch one
type.  The branches follow what a caller can do about the failure: fix its input
(:class:`ConfigurationError`), fix its use of the protocol (:class:`ProtocolError`), check the cable or
port (:class:`TransportError`), or stop and look at the participant's limits (:class:`SafetyError`).
Foreign errors (``construct``, ``serial``, ``usb``) are re-raised ``from`` their cause so the original
traceback stays visible.
"""

from __future__ import annotations

from typing import Any


class TactDeformError(Exception):
    """Root of every error raised by tactdeform_hw.  ``code`` carries a backend code where one exists."""

    def __init__(self, message: str, *, code: int | None = None) -> None:
        super().__init__(message)
        self.code = code


# --- input that is wrong before anything is sent -------------------------------------------------------


class ConfigurationError(TactDeformError, ValueError):
    """A value, file or option that cannot be used as given."""


class OutputError(TactDeformError):
    """An output file that could not be written while the command ran (a full disk, a quota): the
    message names the option and the path, since the operating system's error names neither."""

    def __init__(self, flag: str, path: str, problem: str) -> None:
        super().__init__(f"{flag} {path}: cannot be written ({problem})")
        self.flag = flag
        self.path = path


class LimitError(ConfigurationError):
    """A value outside what the wire, the firmware or the hardware can carry.

    The message always names the field, the value and the limit, because a researcher reading it at the
    bench must be able to fix the input without opening the source.
    """

    def __init__(self, field: str, value: Any, limit: str) -> None:
        super().__init__(f"{field}={value!r} is out of range: {limit}")
        self.field = field
        self.value = value
        self.limit = limit


def install_command(extra: str) -> str:
    """The command that installs ``extra`` for the package being run: from a source checkout (a
    ``pyproject.toml`` beside the package) the editable install of that checkout, since the name on the
    package index is another copy; else the package's name."""
    from pathlib import Path

    root = Path(__file__).resolve().parent.parent
    if (root / "pyproject.toml").is_file():
        where = "." if Path.cwd().resolve() == root else str(root)
        return f"pip install -e '{where}[{extra}]'"
    return f"pip install 'tactdeform_hw[{extra}]'"


class MissingDependencyError(TactDeformError, ImportError):
    """An optional dependency is needed for what was asked; the message names the extra to install."""

    def __init__(self, package: str, extra: str, purpose: str) -> None:
        super().__init__(f"{purpose} needs the optional package {package!r}: {install_command(extra)}")
        self.package = package
        self.extra = extra


# --- the protocol --------------------------------------------------------------------------------------


class ProtocolError(TactDeformError):
    """The byte stream or its use does not match the eTactileKit protocol."""


class DecodeError(ProtocolError):
    """Bytes that cannot be read as the expected reply or command (wraps ``construct.ConstructError``)."""


class ReplyLengthError(ProtocolError):
    """The device's reply is not the length the command's reply holds: the reply proves nothing."""

    def __init__(self, command: str, expected: int, received: bytes) -> None:
        shown = received.hex() if len(received) <= 16 else f"{received[:16].hex()}…"
        super().__init__(
            f"{command}: expected a {expected}-byte reply, got {len(received)} byte(s) ({shown or 'nothing'})"
        )
        self.expected = expected
        self.received = received


class ShortReplyError(ReplyLengthError):
    """The device answered with fewer bytes than the command's reply holds."""


class LongReplyError(ReplyLengthError):
    """The device answered with more bytes than the command's reply holds: on v1.2 a 0xFF answered for
    more channels than the host's electrode count, so the board's count (and the pattern it scans) is not
    the one the host believes in force."""


class NotStoppedError(ProtocolError):
    """The board answered after an all-off, and the answer shows current still flowing (a corrupted or
    duplicated byte changed what the all-off set): the driver recovers and switches off again."""


class ProtocolMisuseError(ProtocolError):
    """A command sequence that would trigger a known firmware defect; refused before anything is written."""


class FirmwareBuildError(ConfigurationError):
    """A firmware source tree that cannot be built or run on the host (emulator.hostbuild).

    ``file`` and ``line`` name the first compiler error when there is one (``None`` otherwise, e.g. a
    missing compiler or an undefined symbol at link time), so the firmware developer can go straight to it.
    """

    def __init__(self, message: str, *, file: str | None = None, line: int | None = None) -> None:
        super().__init__(message)
        self.file = file
        self.line = line


# --- the link ------------------------------------------------------------------------------------------


class TransportError(TactDeformError):
    """The port, the USB link or the emulator's stream failed or is closed."""


class PortNotOpenError(TransportError):
    """I/O on a device or port that is closed."""


class DeviceTimeoutError(TransportError, TimeoutError):
    """A read or write did not complete in time."""


class TransportUnavailableError(TransportError):
    """A device name's transport cannot be loaded (its module, or a package it needs, is missing)."""

    def __init__(self, scheme: str, target: str, cause: BaseException) -> None:
        super().__init__(f"the {scheme!r} transport ({target}) cannot be loaded: {cause}")
        self.scheme = scheme
        self.target = target


class DeviceGoneError(TransportError):
    """The device disappeared mid-session (unplugged, reset, or its link was cut)."""


class DeviceBusyError(TransportError):
    """Another program owns the device: it was refused before a single byte was written.  ``holders``
    lists ``(pid, command line)`` of the processes found holding it (empty when none could be found)."""

    def __init__(self, device: str, holders: list[tuple[int, str]] | None = None, detail: str = "") -> None:
        self.device = device
        self.holders = list(holders or [])
        who = "; ".join(f"pid {pid} ({cmd})" if cmd else f"pid {pid}" for pid, cmd in self.holders)
        super().__init__(
            f"{device} is in use by another program"
            + (f": {who}" if who else "")
            + (f" ({detail})" if detail else "")
            + "; nothing was written to it"
        )


class BoardBusyError(DeviceBusyError):
    """A board that serves one client at a time (the Wi-Fi board) did not answer the identification:
    another program holds it.  Unlike :class:`DeviceBusyError` some bytes were written — only bytes that
    stop current on both firmware versions, which the board reads once the other program has left."""

    def __init__(self, device: str, waited_s: float) -> None:
        self.device = device
        self.holders = []
        self.waited_s = waited_s
        TransportError.__init__(
            self,
            f"{device} did not answer the firmware identification within {waited_s:.1f} s: the board serves "
            "one client at a time and another program holds it (or nothing answers there); it was not "
            "driven, and the only bytes written were ones that stop current",
        )


# --- the person ----------------------------------------------------------------------------------------


class SafetyError(TactDeformError):
    """A request that would exceed a participant's calibrated limits, or a fail-safe that tripped."""


class ProfileError(ConfigurationError):
    """A participant profile that cannot be used: the message names the file and the field, because the
    person fixing it is at the bench with the participant waiting."""

    def __init__(self, source: str, field: str, problem: str) -> None:
        super().__init__(f"participant profile {source}: {field}: {problem}; nothing was sent")
        self.source = source
        self.field = field
        self.problem = problem
