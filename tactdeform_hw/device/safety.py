"""The one guard every current passes on its way to the device.

:class:`~tactdeform_hw.device.base.Device` calls the guard inside the methods that set a current or send
a pattern, before the bytes are built, so no caller above the device layer can skip it.  The base guard
enforces the hardware ceiling (10 mA); participant profiles tighten it.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

from ..errors import SafetyError
from ..protocol.constants import MAX_CURRENT_UA
from .config import StimConfig


@dataclass
class SafetyGuard:
    """Limits in µA.  ``check_*`` return the value that may be sent or raise :class:`SafetyError`."""

    cap_ua: int = MAX_CURRENT_UA
    log: list[dict[str, object]] = field(default_factory=list)

    def __post_init__(self) -> None:
        if not 0 <= self.cap_ua <= MAX_CURRENT_UA:
            raise SafetyError(f"cap_ua={self.cap_ua} is out of range: 0 to {MAX_CURRENT_UA} µA")

    def check_config(self, config: StimConfig) -> StimConfig:
        self._check_current("current_ua", config.current_ua)
        self._check_current("sense_current_ua", config.sense_current_ua)
        return config

    def check_current(self, current_ua: int, levels: Sequence[int] | None = None) -> int:
        self._check_current("current_ua", current_ua)
        return current_ua

    def check_pattern(self, levels: Sequence[int], current_ua: int) -> None:
        self._check_current("current_ua", current_ua)

    def _check_current(self, name: str, current_ua: int) -> None:
        if current_ua > self.cap_ua:
            self.log.append({"event": "refused", "field": name, "value": current_ua, "limit": self.cap_ua})
            raise SafetyError(f"{name}={current_ua} µA exceeds the cap of {self.cap_ua} µA; nothing was sent")
