"""Finding eTactileKit Wi-Fi boards (firmware v2) by UDP discovery, and refusing an ambiguous one.

The host sends ``ETK?`` to UDP 8888 and collects ``ETK!;key=value;…`` replies for a while.  Upstream's
discoverers keep one reply per id; but the firmware derives the id from the MAC's manufacturer bytes, so
boards sharing an Espressif OUI share an id, and "the kit with id X" may be either.  Here every reply is
kept (by id, address and port), and :func:`resolve` refuses an id that more than one board answers to:
the driver never connects to a board it cannot tell apart.
"""

from __future__ import annotations

import socket
import time
from collections.abc import Iterable
from dataclasses import dataclass

from tactdeform_hw.errors import ConfigurationError, TransportError

DISCOVERY_PORT = 8888
QUERY = b"ETK?"


@dataclass(frozen=True)
class Kit:
    """One discovery reply."""

    id: str
    name: str
    ip: str
    port: int
    mode: str
    fw: str
    sender: tuple[str, int]

    @property
    def url(self) -> str:
        """pyserial's own TCP handler for the board's control port."""
        return f"socket://{self.ip}:{self.port}"


def parse_reply(data: bytes, sender: tuple[str, int] = ("", 0)) -> Kit | None:
    """A :class:`Kit` from an ``ETK!;key=value;…`` datagram (None for anything else)."""
    if not data.startswith(b"ETK!"):
        return None
    fields: dict[str, str] = {}
    for token in data[4:].decode("ascii", "replace").split(";"):
        if "=" in token:
            k, v = token.split("=", 1)
            fields[k.strip()] = v.strip()
    try:
        return Kit(
            fields["id"],
            fields.get("name", ""),
            fields.get("ip", sender[0]),
            int(fields.get("port", "8080")),
            fields.get("mode", ""),
            fields.get("fw", ""),
            sender,
        )
    except (KeyError, ValueError):
        return None


class WifiDiscovery(list[Kit]):
    """The distinct replies of one :func:`discover` (a list of :class:`Kit`), and where and how long it
    asked, so a caller that finds no kit can say so (:meth:`asked`)."""

    def __init__(
        self, kits: Iterable[Kit], targets: list[tuple[str, int]], listen_s: float, bursts: int
    ) -> None:
        super().__init__(kits)
        self.targets = targets
        self.listen_s = listen_s
        self.bursts = bursts

    def asked(self) -> str:
        """Where discovery asked and how long it listened, in words."""
        where = ", ".join(f"UDP {h}:{p}" for h, p in self.targets) or "no address"
        return (
            f"sent ETK? to {where} {self.bursts} time(s), listening {self.listen_s:g} s after each "
            f"({self.bursts * self.listen_s:g} s in all)"
        )


def discover(
    targets: Iterable[tuple[str, int]] = (("127.0.0.1", DISCOVERY_PORT),),
    *,
    listen_s: float = 0.3,
    bursts: int = 2,
) -> WifiDiscovery:
    """Send ``ETK?`` to each target (``bursts`` times, listening ``listen_s`` after each) and return the
    distinct replies (with where it asked: :class:`WifiDiscovery`).  Loopback by default; pass a broadcast
    address to search a network."""
    found: dict[tuple[str, str, int], Kit] = {}
    try:
        sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    except OSError as exc:
        raise TransportError(f"cannot open a UDP socket for discovery: {exc}") from exc
    with sock:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_BROADCAST, 1)
        targets = list(targets)
        for _ in range(bursts):
            for target in targets:
                try:
                    sock.sendto(QUERY, target)
                except OSError as exc:
                    raise TransportError(f"cannot send discovery to {target[0]}:{target[1]}: {exc}") from exc
            end = time.monotonic() + listen_s
            while (left := end - time.monotonic()) > 0:
                sock.settimeout(left)
                try:
                    data, sender = sock.recvfrom(2048)
                except TimeoutError:
                    break
                kit = parse_reply(data, sender[:2])
                if kit is not None:
                    found.setdefault((kit.id, kit.ip, kit.port), kit)
    return WifiDiscovery(found.values(), targets, listen_s, bursts)


def resolve(kit_id: str, kits: Iterable[Kit]) -> Kit:
    """The one kit answering to ``kit_id``; refuses none and refuses several (ids can collide)."""
    kits = kits if isinstance(kits, WifiDiscovery) else list(kits)
    matches = [k for k in kits if k.id.upper() == kit_id.upper()]
    if not matches:
        others = sorted({k.id for k in kits})
        heard = f"kits answered with id(s) {', '.join(others)}" if others else "no kit answered at all"
        if isinstance(kits, WifiDiscovery):
            heard = f"{kits.asked()}; {heard}"
        raise ConfigurationError(
            f"etactilekit://{kit_id}: no kit with id {kit_id!r} answered discovery ({heard}); a kit on "
            "another network or port is asked with etactilekit://ID?discovery=HOST:PORT, or connect "
            "with socket://IP:PORT"
        )
    if len(matches) > 1:
        where = ", ".join(f"{k.ip}:{k.port}" for k in matches)
        raise ConfigurationError(
            f"etactilekit://{kit_id}: {len(matches)} kits answer to id {kit_id!r} ({where}); the firmware "
            "derives the id from the MAC's manufacturer bytes, so boards can share it — connect with "
            "socket://IP:PORT"
        )
    return matches[0]
