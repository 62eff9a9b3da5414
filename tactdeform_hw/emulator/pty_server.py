"""The emulator on a real pseudo-terminal, so any program that opens a serial port can talk to it.

The server keeps its own handle on the slave side open, so a client may open, close and reopen the
device path without the master seeing end-of-file.  The slave is put in raw mode (no echo, no line
editing, no CR/LF translation) before any client opens it; clients such as pyserial set raw mode too.
"""

from __future__ import annotations

import os
import select
import sys
import threading
import time
import tty
from collections.abc import Callable

from ..errors import TransportError
from .core import Emulator

if sys.platform == "win32":  # pragma: no cover - pty is POSIX only
    raise ImportError("the pty server needs a POSIX system")

ByteHook = Callable[[str, bytes, float], None]


class PtyServer:
    """Serve ``emulator`` on a new pty.  ``path`` is the device a client opens.

    ``hook(direction, data, t)`` (optional) sees every byte both ways with a monotonic timestamp — the
    spy and trace recorders attach here.
    """

    def __init__(self, emulator: Emulator | None = None, *, hook: ByteHook | None = None) -> None:
        self.emulator = emulator if emulator is not None else Emulator()
        self.hook = hook
        try:
            self._master, self._slave = os.openpty()
        except OSError as exc:
            raise TransportError(f"cannot create a pseudo-terminal: {exc}") from exc
        tty.setraw(self._slave)
        self.path = os.ttyname(self._slave)
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self.bytes_in = 0
        self.bytes_out = 0

    def serve_forever(self, poll_s: float = 0.05) -> None:
        """Relay bytes until :meth:`stop` (or KeyboardInterrupt in the caller)."""
        master = self._master
        while not self._stop.is_set():
            ready, _, _ = select.select([master], [], [], poll_s)
            if not ready:
                continue
            try:
                data = os.read(master, 4096)
            except OSError:  # the slave side went away entirely
                time.sleep(poll_s)
                continue
            if not data:
                continue
            now = time.monotonic()
            self.bytes_in += len(data)
            if self.hook:
                self.hook("host->dev", data, now)
            reply = self.emulator.feed(data)
            if reply:
                if self.hook:
                    self.hook("dev->host", reply, time.monotonic())
                self._write_all(reply)

    def _write_all(self, data: bytes) -> None:
        view = memoryview(data)
        while view:
            n = os.write(self._master, view)
            self.bytes_out += n
            view = view[n:]

    def start(self) -> PtyServer:
        """Serve in a daemon thread (tests and in-process tools)."""
        self._thread = threading.Thread(target=self.serve_forever, name="etactile-pty", daemon=True)
        self._thread.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2)
            self._thread = None
        for fd in (self._master, self._slave):
            try:
                os.close(fd)
            except OSError:
                pass

    def __enter__(self) -> PtyServer:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()
