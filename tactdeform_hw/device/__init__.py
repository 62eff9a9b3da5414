"""The device interface, the eTactileKit driver, channel mapping and the safety guard."""

from .base import ALLOWED_LEVELS, Device
from .config import StimConfig
from .mapping import ChannelMapping
from .safety import SafetyGuard
from .serial_driver import EtactileKitDevice, open_device, open_port

__all__ = [
    "ALLOWED_LEVELS",
    "ChannelMapping",
    "Device",
    "EtactileKitDevice",
    "SafetyGuard",
    "StimConfig",
    "open_device",
    "open_port",
]
