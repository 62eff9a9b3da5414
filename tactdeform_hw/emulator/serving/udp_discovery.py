"""The v2 Wi-Fi build's UDP discovery responder, as the firmware answers it (``comm.cpp:68-83``).

It listens on UDP 8888; a datagram of at least 4 bytes whose first 4 bytes are ``ETK?`` gets one unicast
reply to its sender, ``ETK!;id=<ID>;name=etactilekit-<ID>;ip=<IP>;port=8080;mode=STA|AP;fw=1.0``;
anything else is ignored.  The ID is ``"%06X" % (ESP.getEfuseMac() & 0xFFFFFF)``, and because
``getEfuseMac`` copies the six MAC bytes in memory order into a little-endian integer, those are MAC
bytes 0-2 reversed: the manufacturer's OUI, the same on every board with an Espressif OUI.
:func:`device_id_from_mac` reproduces that, so two emulated kits can collide as real ones do.

Loopback only by default: the responder binds 127.0.0.1 and tests pass port 0 (any free port).  Bound
to every interface (``0.0.0.0``), it advertises in ``ip=`` the address of the interface facing each
requester (what the firmware's ``WiFi.localIP()`` is to a host on its network), never ``0.0.0.0``, which
no host can connect to.
"""

from __future__ import annotations

import socket
import threading

from tactdeform_hw.errors import ConfigurationError, TransportError

DISCOVERY_PORT = 8888
TCP_PORT = 8080
QUERY = b"ETK?"
REPLY_PREFIX = b"ETK!"
FIRMWARE_FIELD = "1.0"  # the firmware's own fw= value (not the package's version name)


def device_id_from_mac(mac: bytes) -> str:
    """The firmware's device id from a 6-byte MAC (bytes 0-2 reversed: the OUI)."""
    if len(mac) != 6:
        raise ConfigurationError(f"mac={mac.hex(':')!r} is not 6 bytes")
    efuse = int.from_bytes(mac, "little")
    return f"{efuse & 0xFFFFFF:06X}"


def facing_address(peer: str) -> str | None:
    """The local address this host uses to reach ``peer`` (the interface facing it; None if no route).
    A UDP socket's ``connect`` only picks the route: nothing is sent."""
    try:
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as probe:
            probe.connect((peer, DISCOVERY_PORT))
            local = probe.getsockname()[0]
    except OSError:
        return None
    return str(local) if local not in ("0.0.0.0", "") else None


def reply_for(device_id: str, ip: str, *, tcp_port: int = TCP_PORT, mode: str = "AP") -> bytes:
    if mode not in ("STA", "AP"):
        raise ConfigurationError(f"mode={mode!r} is not STA or AP")
    return (
        f"ETK!;id={device_id};name=etactilekit-{device_id};ip={ip};port={tcp_port};mode={mode};"
        f"fw={FIRMWARE_FIELD}"
    ).encode("ascii")


class DiscoveryResponder:
    """Answer ``ETK?`` datagrams on ``host:port`` from a background thread until :meth:`close`."""

    def __init__(
        self,
        device_id: str,
        *,
        host: str = "127.0.0.1",
        port: int = DISCOVERY_PORT,
        tcp_port: int = TCP_PORT,
        mode: str = "AP",
        advertised_ip: str | None = None,
    ) -> None:
        self.device_id = device_id
        try:
            self._sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
            self._sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            self._sock.bind((host, port))
        except OSError as exc:
            raise TransportError(f"cannot listen for discovery on UDP {host}:{port}: {exc}") from exc
        self.address: tuple[str, int] = self._sock.getsockname()[:2]
        self._advertised_ip = advertised_ip
        self._tcp_port = tcp_port
        self._mode = mode
        reply_for(device_id, advertised_ip or self.address[0], tcp_port=tcp_port, mode=mode)  # checks mode
        self.queries = 0
        self.ignored = 0
        self._sock.settimeout(0.05)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._serve, name=f"etk-discovery-{device_id}", daemon=True)
        self._thread.start()

    def _serve(self) -> None:
        while not self._stop.is_set():
            try:
                data, sender = self._sock.recvfrom(2048)
            except TimeoutError:
                continue
            except OSError:
                return
            if len(data) >= 4 and data[:4] == QUERY:
                self.queries += 1
                try:
                    self._sock.sendto(self.reply_to(sender[0]), sender)
                except OSError:
                    pass
            else:
                self.ignored += 1

    def reply_to(self, peer: str) -> bytes:
        """The reply to a query from ``peer``: ``ip=`` is the advertised address if one was given, else
        the bound one, else (bound to every interface) the address of the interface facing ``peer``."""
        ip = self._advertised_ip or self.address[0]
        if ip in ("0.0.0.0", ""):
            ip = facing_address(peer) or ip
        return reply_for(self.device_id, ip, tcp_port=self._tcp_port, mode=self._mode)

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=1.0)
        self._sock.close()

    def __enter__(self) -> DiscoveryResponder:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
