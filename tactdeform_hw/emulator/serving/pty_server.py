"""The emulated board on a real pseudo-terminal, so any program that opens a serial port can talk to it.

By default the board is the timed model on the wall clock (:class:`~.realtime.RealtimeEmulator`, USB
link, 256-byte queue; ``firmware="v2"``: the v2 model, its 1024-byte queue and 2 s command timeout): bytes
are stamped as the server reads them from the pty, replies are written
when the model delivers them, scans run.  An untimed :class:`~.core.Emulator` (``--untimed``) answers
every write at once instead.

The slave side is put in raw mode (no echo, no line editing, no CR/LF translation) and then closed by
the server, so the master sees when a client has the device open (no hang-up) and when the last one
closes it (hang-up): that is what ``reset_on_open`` acts on.  Raw mode stays with the device between
clients; clients such as pyserial set it themselves too.  Replies written while no client has the
device open are dropped (the firmware writes into a USB port nobody reads).
"""

from __future__ import annotations

import os
import select
import sys
import time
import tty
from typing import Any

from tactdeform_hw.emulator.serving.realtime import BoardServer, RealtimeEmulator, check_served_firmware
from tactdeform_hw.errors import TransportError

if sys.platform == "win32":  # pragma: no cover - pty is POSIX only
    raise ImportError("the pty server needs a POSIX system")

_HUP = select.POLLHUP | select.POLLERR


class PtyServer(BoardServer):
    """Serve ``board`` (default: a :class:`~.realtime.RealtimeEmulator` running ``firmware``, ``"v1.2"``
    or ``"v2"``) on a new pty; ``path`` is the device a client opens.  See :class:`~.realtime.BoardServer`
    for the options.  ``firmware`` names the default board's version, so a caller that wants a v2 board
    on a pty need not build one; with an explicit ``board`` it must agree with the board's own."""

    thread_name = "etactile-pty"

    def __init__(self, board: Any = None, *, firmware: str | None = None, **kwargs: Any) -> None:
        super().__init__(
            board if board is not None else RealtimeEmulator(firmware=firmware or "v1.2"), **kwargs
        )
        check_served_firmware(self.board, firmware)
        try:
            self._master, slave = os.openpty()
        except OSError as exc:
            raise TransportError(f"cannot create a pseudo-terminal: {exc}") from exc
        tty.setraw(slave)
        self.path = os.ttyname(slave)
        os.close(slave)
        os.set_blocking(self._master, False)
        self._poll = select.poll()
        self._poll.register(self._master, select.POLLIN)

    def _hung_up(self) -> bool:
        return any(ev & _HUP for _, ev in self._poll.poll(0))

    def serve_forever(self, poll_s: float | None = None) -> None:
        """Relay bytes until :meth:`stop` (or KeyboardInterrupt in the caller)."""
        if poll_s is not None:
            self.poll_s = poll_s
        master = self._master
        cpu0 = time.thread_time()
        self._begin()
        while not self._stop.is_set():
            hup = self._hung_up()
            if self.connected and hup:
                self._client_closed()
            elif not self.connected and not hup:
                self._client_opened()
            wait = self._tick()
            if self._out and self.connected:
                self._flush()
            rd: list[Any] = [self._wake_r]
            if self.connected:
                rd.append(master)
            else:
                wait = min(wait, 0.005)  # an open is seen only by looking: poll for it
            wr = [master] if self._out and self.connected else []
            try:
                ready, _, _ = select.select(rd, wr, [], wait)
            except (OSError, ValueError):  # closed under us by stop()
                break
            if self._wake_r in ready:
                self._drain_wake()
            if master in ready:
                try:
                    data = os.read(master, 4096)
                except (BlockingIOError, InterruptedError):
                    data = b""
                except OSError:  # the client went away: seen as a hang-up on the next turn
                    data = b""
                if data:
                    self._incoming(data, time.monotonic())
            self.cpu_s = time.thread_time() - cpu0

    def _flush(self) -> None:
        try:
            n = os.write(self._master, self._out)
        except (BlockingIOError, InterruptedError):
            return
        except OSError:
            self._out.clear()
            return
        self.bytes_out += n
        del self._out[:n]

    def _close_fds(self) -> None:
        try:
            os.close(self._master)
        except OSError:
            pass

    def __enter__(self) -> PtyServer:
        self.start()
        return self
