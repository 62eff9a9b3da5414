"""The emulated board on a TCP port, as the firmware's Wi-Fi build serves it.

The Wi-Fi build is a TCP server (port 8080 on the board's own access point) that serves one client at a
time: a later client waits in the listen backlog until the current one has gone.  Its parser reads the
TCP stream directly, so TCP flow control holds the host back where the serial build's queue would drop
bytes.  :class:`TcpServer` does the same on loopback (by default): with flow-controlled
:class:`~.realtime.BuildRules` it takes bytes from the socket only while the board's receive path has
room, so a fast host blocks in ``send`` instead of losing bytes; replies are written only while a client
is connected.  The build's rules are a parameter: ``rules=SERIAL_USB`` serves the serial build's link and
256-byte queue over TCP instead (every byte taken at once, the queue discards what does not fit).
``firmware="v2"`` serves the v2 model under the same rules (the v2 Wi-Fi build is the one that also answers
UDP discovery, :mod:`.udp_discovery`).
"""

from __future__ import annotations

import select
import socket
import time
from typing import Any

from tactdeform_hw.emulator.serving.realtime import (
    WIFI_TCP,
    BoardServer,
    BuildRules,
    RealtimeEmulator,
    check_served_firmware,
)
from tactdeform_hw.errors import TransportError


class TcpServer(BoardServer):
    """Serve ``board`` (default: a :class:`~.realtime.RealtimeEmulator` under ``rules`` running
    ``firmware``, ``"v1.2"`` or ``"v2"``) on ``host:port`` (port 0: any free port; :attr:`address` says
    which).  ``firmware`` names the default board's version; with an explicit ``board`` it must agree
    with the board's own, so a server never claims a version it does not serve."""

    thread_name = "etactile-tcp"

    def __init__(
        self,
        board: Any = None,
        *,
        host: str = "127.0.0.1",
        port: int = 8080,
        rules: BuildRules = WIFI_TCP,
        backlog: int = 4,
        firmware: str | None = None,
        **kwargs: Any,
    ) -> None:
        if board is None:
            board = RealtimeEmulator(rules=rules, firmware=firmware or "v1.2")
        check_served_firmware(board, firmware)
        super().__init__(board, **kwargs)
        self.rules = rules
        try:
            self._listen = socket.create_server((host, port), backlog=backlog)
        except OSError as exc:
            raise TransportError(f"cannot listen on {host}:{port}: {exc}") from exc
        self._listen.setblocking(False)
        self.address: tuple[str, int] = self._listen.getsockname()[:2]
        self._client: socket.socket | None = None
        self.peer: tuple[str, int] | None = None

    @property
    def url(self) -> str:
        """``socket://host:port``, the pyserial URL of this server."""
        return f"socket://{self.address[0]}:{self.address[1]}"

    def _room(self) -> int:
        if self.rules.flow_control and self.timed:
            return int(self.board.room())
        return 65536

    def serve_forever(self) -> None:
        cpu0 = time.thread_time()
        self._begin()
        while not self._stop.is_set():
            wait = self._tick()
            client = self._client
            if client is not None and self._out:
                self._flush(client)
            rd: list[Any] = [self._wake_r]
            wr: list[Any] = []
            room = 0
            if client is None:
                rd.append(self._listen)
            else:
                room = self._room()
                if room > 0:
                    rd.append(client)
                if self._out:
                    wr.append(client)
            try:
                ready, writable, _ = select.select(rd, wr, [], wait)
            except (OSError, ValueError):
                break
            if self._wake_r in ready:
                self._drain_wake()
            if self._listen in ready:
                self._accept()
            elif client is not None and client in ready:
                try:
                    data = client.recv(min(room, 4096))
                except (BlockingIOError, InterruptedError):
                    data = None
                except OSError:
                    data = b""
                if data == b"":
                    self._drop_client()
                elif data:
                    self._incoming(data, time.monotonic())
            self.cpu_s = time.thread_time() - cpu0
        self._drop_client()

    def _accept(self) -> None:
        try:
            sock, peer = self._listen.accept()
        except (BlockingIOError, InterruptedError, OSError):
            return
        sock.setblocking(False)
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        self._client = sock
        self.peer = peer
        self._client_opened()

    def _drop_client(self) -> None:
        if self._client is not None:
            try:
                self._client.close()
            except OSError:
                pass
            self._client = None
            self.peer = None
            self._client_closed()

    def _flush(self, client: socket.socket) -> None:
        try:
            n = client.send(self._out)
        except (BlockingIOError, InterruptedError):
            return
        except OSError:
            self._drop_client()
            return
        self.bytes_out += n
        del self._out[:n]

    def _close_fds(self) -> None:
        self._drop_client()
        try:
            self._listen.close()
        except OSError:
            pass

    def __enter__(self) -> TcpServer:
        self.start()
        return self
