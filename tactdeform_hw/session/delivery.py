"""What a stimulating session actually sent, for a command's console output and its ``--json``.

A researcher reading "at 1600 µA" must be able to trust that 1600 µA went into the finger.  The device
layer lowers a frame's pulse height to the lowest regional limit of the electrodes it activates, limits
every increase to the ramp step, and refuses what breaks a limit; each of those decisions is recorded by
the safety guard and sent to the session's audit log.  :class:`DeliveryLog` *is* that audit log (written
to ``--audit-log`` when given, nowhere otherwise), so it sees exactly what the device wrote — every pulse
height and pattern, after the guard and the interlock — and every clip and refusal with its reason.  The
report is built from those records, never recomputed from the request.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from typing import IO, Any

from tactdeform_hw.device.driver.audit import AuditLog
from tactdeform_hw.device.participant.regions import RegionMap, tactdeform_region_map
from tactdeform_hw.protocol.firmware import FirmwareSpec, get_firmware
from tactdeform_hw.protocol.units import DEFAULT_TRANSFER, CurrentTransfer

_ACTIVE = (1, 2)
#: At most this many successive pulse heights are listed (a long session changes height every frame).
HEIGHTS_SHOWN = 64


def per_electrode_heights(firmware: FirmwareSpec | str) -> bool:
    """Whether each electrode has its own pulse height, its pattern element (v2), rather than one
    pulse-height register for every electrode (v1.2): the height of each must then be read back and
    reported per electrode."""
    spec = get_firmware(firmware)
    return not any(c.register == "pulse_height" for c in spec.commands)


class _Discard:
    """A text stream that keeps nothing (the audit lines when no --audit-log was asked for)."""

    def write(self, text: str) -> int:
        return len(text)

    def flush(self) -> None:
        return None

    def close(self) -> None:
        return None


class DeliveryLog(AuditLog):
    """The session's audit log, also keeping what the console reports: the pulse heights written, the
    highest height each electrode received while active, and the guard's clips and refusals.

    ``mapping`` (hardware channel ↔ application electrode) and ``region_map`` (the electrode positions)
    go into the log's session line, so ``replay-log`` judges the session by the same positions; with
    ``region_of`` (the guard's regions, application order) they name electrodes and regions in the report.
    ``requested_ua`` is what the command was asked for."""

    def __init__(
        self,
        path: str | os.PathLike[str] | None,
        *,
        requested_ua: int | None = None,
        mapping: Any = None,
        region_map: RegionMap | None = None,
        region_of: Sequence[int] | None = None,
        transfer: CurrentTransfer = DEFAULT_TRANSFER,
        **session: Any,
    ) -> None:
        stream: str | os.PathLike[str] | IO[str] = path if path else _Discard()  # type: ignore[assignment]
        # the header keeps where each electrode sits, so replay-log judges the session by the same map
        if mapping is not None:
            session.setdefault("mapping", list(mapping.app_to_hw))
            session.setdefault("hw_channels", mapping.hw_channels)
        if region_map is not None:
            session.setdefault("positions_mm", [list(p) for p in region_map.positions_mm])
            # no mapping: electrode i on channel i
            session.setdefault("mapping", list(range(region_map.electrodes)))
            if region_of is None:
                region_of = region_map.resolve(None)
        super().__init__(stream, **session)
        self.requested_ua = requested_ua
        self.mapping = mapping
        self.region_of = tuple(region_of) if region_of is not None else None
        self.transfer = transfer
        self.heights_ua: list[int] = []  # successive distinct heights written (non-zero ones listed)
        self.height_changes = 0
        self.max_ua = 0
        self._height = 0
        self._pattern: bytes = b""
        self.channel_max_ua: dict[int, int] = {}
        self._events: dict[tuple[Any, ...], dict[str, Any]] = {}

    def __enter__(self) -> DeliveryLog:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # --- what the device wrote ---------------------------------------------------------------------------

    def sent(self, name: str, value: Any) -> None:
        """Keep what the report says of each command the device sent: the heights written and the highest
        height each active channel received."""
        if per_electrode_heights(self.firmware):  # each pattern element is its own height
            self._tx_heights(name, value)
            return
        if name == "PULSE_HEIGHT" and isinstance(value, int):
            self._height_written(int(round(self.transfer.to_ua(min(value, self.firmware.dac_max_code)))))
        elif name == "PATTERN" and isinstance(value, list):
            self._pattern = bytes(value)
        else:
            return
        if self._height:
            for ch, level in enumerate(self._pattern):
                if level in _ACTIVE and self.channel_max_ua.get(ch, 0) < self._height:
                    self.channel_max_ua[ch] = self._height

    def _tx_heights(self, name: str, value: Any) -> None:
        """Firmware v2: each pattern element is its channel's height (a DAC code, clamped at 4095)."""
        if name != "PATTERN" or not isinstance(value, list):
            return
        top = self.firmware.dac_max_code
        uas = [int(round(self.transfer.to_ua(min(int(v), top)))) for v in value]
        self._height_written(max(uas, default=0))
        for ch, ua in enumerate(uas):
            if ua and self.channel_max_ua.get(ch, 0) < ua:
                self.channel_max_ua[ch] = ua

    def _height_written(self, ua: int) -> None:
        """The pulse height in force is now ``ua`` (v1.2's register, or v2's highest pattern element):
        count a change, list a new non-zero height (up to :data:`HEIGHTS_SHOWN`), keep the highest."""
        if ua != self._height:
            self.height_changes += 1
            if (
                ua
                and len(self.heights_ua) < HEIGHTS_SHOWN
                and (not self.heights_ua or self.heights_ua[-1] != ua)
            ):
                self.heights_ua.append(ua)
        self._height = ua
        self.max_ua = max(self.max_ua, ua)

    def safety(self, entry: dict[str, Any]) -> None:
        super().safety(entry)
        key = (
            entry.get("event"),
            entry.get("rule"),
            entry.get("requested_ua"),
            entry.get("sent_ua"),
            entry.get("region") if "region" in entry else entry.get("electrode"),
        )
        hit = self._events.get(key)
        if hit is None:
            hit = {k: entry[k] for k in ("event", "rule", "message") if k in entry}
            for k in ("requested_ua", "sent_ua", "electrode", "region", "limit_ua", "channel"):
                if k in entry:
                    hit[k] = entry[k]
            hit["count"] = 0
            hit["electrodes"] = []
            self._events[key] = hit
        hit["count"] += 1
        e = entry.get("electrode")
        if isinstance(e, int) and e not in hit["electrodes"] and len(hit["electrodes"]) < 256:
            hit["electrodes"].append(e)

    # --- the report ----------------------------------------------------------------------------------------

    def _electrode_of(self, ch: int) -> int | None:
        if self.mapping is None:
            return ch
        for i, hw in enumerate(self.mapping.app_to_hw):
            if hw == ch:
                return i
        return None

    def report(self) -> dict[str, Any]:
        """The ``delivered`` block of a command's ``--json``."""
        electrodes = []
        for ch in sorted(self.channel_max_ua):
            e = self._electrode_of(ch)
            row: dict[str, Any] = {"electrode": e, "channel": ch, "max_ua": self.channel_max_ua[ch]}
            if e is not None and self.region_of is not None and e < len(self.region_of):
                row["region"] = self.region_of[e]
            electrodes.append(row)
        events = list(self._events.values())
        return {
            "requested_ua": self.requested_ua,
            # the highest height an active electrode received (a height written while every electrode is
            # off reaches none)
            "max_delivered_ua": max(self.channel_max_ua.values(), default=0),
            "max_height_ua": self.max_ua,
            "pulse_heights_ua": list(self.heights_ua),
            "pulse_height_changes": self.height_changes,
            "lowered": [e for e in events if e.get("event") == "clipped"],
            "refused": [e for e in events if e.get("event") == "refused"],
            "electrodes": electrodes,
        }


def session_region_map(array_file: Any, electrodes: int) -> RegionMap | None:
    """Where the session's electrodes sit: the array file's coordinates, else the TactDeform array's for
    32 electrodes, else unknown (None)."""
    if array_file is not None:
        rmap: RegionMap = array_file.region_map()
        return rmap
    return tactdeform_region_map() if electrodes == 32 else None
