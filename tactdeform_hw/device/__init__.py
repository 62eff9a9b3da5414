"""The device interface, the eTactileKit driver, channel mapping and the safety guard."""

from tactdeform_hw.device.driver.base import ALLOWED_LEVELS, Device
from tactdeform_hw.device.driver.config import StimConfig
from tactdeform_hw.device.driver.serial_driver import EtactileKitDevice, open_device, open_port
from tactdeform_hw.device.participant.mapping import ChannelMapping
from tactdeform_hw.device.safety.guard import SafetyGuard

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
