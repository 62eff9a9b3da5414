"""The audit log: every command a session sent, with its time, as JSON lines.

A study's ethics record needs to show what current went into whose finger and when, and a fault needs a
record to be replayed from.  The log is enabled per session (``Device(audit=AuditLog(path))`` or
``--audit-log FILE`` on the commands that stimulate) and written line by line, flushed after each line,
so a crash loses at most the line being written.

Line types (``type``):

* ``session`` — the first line: format version, start time, participant, device, free fields;
* ``tx`` — one write: ``seq``, ``t`` (seconds since the session started, on the device's pacing clock),
  ``wall`` (Unix time), ``cmd`` (command name), ``value`` (decoded value; a list for patterns), ``hex``
  (exactly the bytes written, padding included), ``ok`` (false when the transport failed) and ``op``
  (the device method that sent it); a write of several commands at once (v2's cover around a pattern)
  gives one line per command, each with ``part`` ``[k, n]`` (the k-th of the write's n commands, from 1),
  so a reader sees every command as the firmware reads it and a replay writes them again as one write;
* ``safety`` — a refusal or a clip by the guard (the guard's log entry);
* ``event`` — fail-safe actions: watchdog stop, resync, reconnect, reset.

``tactdeform-hw replay-log FILE`` re-runs the ``tx`` lines on the emulator.
"""

from __future__ import annotations

import datetime as _dt
import json
import os
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import IO, Any

from tactdeform_hw.errors import ConfigurationError
from tactdeform_hw.protocol.firmware import DEFAULT_FIRMWARE, FirmwareSpec
from tactdeform_hw.protocol.reader import first_command

AUDIT_VERSION = 1


def describe_command(data: bytes, firmware: FirmwareSpec = DEFAULT_FIRMWARE) -> tuple[str, Any]:
    """Name and value of the first command in ``data`` as the firmware reads it (for humans reading the
    log; the value is the one sent, before the firmware's clamp; a pattern's levels as stored)."""
    c = first_command(data, firmware=firmware)
    if c is None:
        return "EMPTY", None
    if c.opcode is None:
        return ("ZEROS" if not any(data) else "UNKNOWN"), len(data)
    name = firmware.command(c.opcode).name
    if c.levels is not None:
        return name, list(c.levels)
    return name, c.read_value


class AuditLog:
    """Append-only JSON-lines log.  ``path`` may be a file path or an open text stream."""

    #: The firmware whose reading names the commands (the device sets v2 when it speaks v2).
    firmware: FirmwareSpec = DEFAULT_FIRMWARE

    def __init__(self, path: str | os.PathLike[str] | IO[str], **session: Any) -> None:
        if isinstance(path, (str, os.PathLike)):
            self.path: Path | None = Path(path)
            try:
                self._fh: IO[str] = open(self.path, "a", encoding="utf-8")  # noqa: SIM115
            except OSError as exc:
                raise ConfigurationError(f"audit log {path}: cannot be opened ({exc})") from exc
            self._owns = True
        else:
            self.path = None
            self._fh = path
            self._owns = False
        # Reentrant: the stop handler (:mod:`.failsafe`) runs on the main thread wherever a signal caught
        # it — inside this log's own write, too — and logs its all-off here; a plain lock would make that
        # stop wait for itself forever, with the board still stimulating.
        self._lock = threading.RLock()
        self._seq = 0
        self._t0: float | None = None
        self.closed = False
        header = {
            "type": "session",
            "version": AUDIT_VERSION,
            "started": _dt.datetime.now(_dt.timezone.utc).isoformat(),
            **session,
        }
        self._line(header)

    def _line(self, obj: dict[str, Any]) -> None:
        # whole before the lock: one write a line
        text = json.dumps(obj, default=str, separators=(",", ":")) + "\n"
        with self._lock:
            if self.closed:
                return
            self._fh.write(text)
            self._fh.flush()

    def rel(self, t: float) -> float:
        if self._t0 is None:
            self._t0 = t
        return t - self._t0

    def tx(
        self,
        data: bytes,
        *,
        t: float,
        ok: bool = True,
        op: str = "",
        logical: bytes | None = None,
        part: tuple[int, int] | None = None,
    ) -> None:
        name, value = describe_command(logical if logical is not None else data, self.firmware)
        self._seq += 1
        rec: dict[str, Any] = {
            "type": "tx",
            "seq": self._seq,
            "t": round(self.rel(t), 7),
            "wall": round(time.time(), 6),
            "cmd": name,
            "value": value,
            "hex": bytes(data).hex(),
            "ok": ok,
            "op": op,
        }
        if part is not None:
            rec["part"] = list(part)
        self._line(rec)
        if ok:
            self.sent(name, value)

    def sent(self, name: str, value: Any) -> None:
        """A command the transport took, as :func:`describe_command` read it for its ``tx`` line.  Nothing
        here: a log that also reports what a session sent (the session's delivery log) keeps it, from the
        same reading as the line it wrote."""

    def safety(self, entry: dict[str, Any]) -> None:
        self._line({"type": "safety", **entry})

    def event(self, kind: str, t: float | None = None, **detail: Any) -> None:
        rec: dict[str, Any] = {"type": "event", "event": kind, "wall": round(time.time(), 6)}
        if t is not None:
            rec["t"] = round(self.rel(t), 7)
        rec.update(detail)
        self._line(rec)

    def close(self) -> None:
        with self._lock:
            if self.closed:
                return
            self.closed = True
            if self._owns:
                self._fh.close()


def read_log(path: str | os.PathLike[str]) -> Iterator[dict[str, Any]]:
    """The records of an audit log; a malformed line raises naming the line number."""
    p = Path(path)
    try:
        fh = open(p, encoding="utf-8")  # noqa: SIM115
    except OSError as exc:
        raise ConfigurationError(f"audit log {p}: cannot be read ({exc.strerror or exc})") from exc
    with fh:
        for lineno, line in enumerate(fh, start=1):
            if not line.strip():
                continue
            try:
                rec = json.loads(line)
            except ValueError as exc:
                raise ConfigurationError(f"audit log {p} line {lineno}: not JSON ({exc})") from exc
            if not isinstance(rec, dict) or "type" not in rec:
                raise ConfigurationError(f"audit log {p} line {lineno}: a record needs a 'type'")
            if rec["type"] == "tx":
                if not isinstance(rec.get("hex"), str) or not isinstance(rec.get("t"), (int, float)):
                    raise ConfigurationError(f"audit log {p} line {lineno}: a tx record needs 'hex' and 't'")
                try:
                    bytes.fromhex(rec["hex"])
                except ValueError as exc:
                    raise ConfigurationError(f"audit log {p} line {lineno}: hex: {exc}") from exc
            yield rec
