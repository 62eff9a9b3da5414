"""tactdeform_hw: the eTactileKit protocol, a byte-exact emulator of its firmware, device drivers with
participant safety, and the TactDeform renderer on top.

The front door (see ``docs/quickstart.md``)::

    from tactdeform_hw import Renderer, StimConfig, load_scene, open_device

    with open_device("emulator") as dev:
        dev.configure(StimConfig(electrode_count=32, current_ua=1200))
        dev.send_pattern([1] * 32)

``open_device``, ``open_port``, ``StimConfig``, ``Renderer``, ``load_scene``, ``ElectrodeArray``,
``make_trajectory``, ``Approach`` and every error of :mod:`tactdeform_hw.errors` are importable from
here.  Importing the package does one thing only: it appends the emulator's URL-handler package to
pyserial's ``serial.protocol_handler_packages``, so ``serial.serial_for_url("etactile://")`` works in any
program that has imported it.  Nothing else is imported until a name is used (the device layer, the
renderer and numpy are loaded lazily by ``__getattr__``); no port is opened, no thread started, no file
read.
"""

from __future__ import annotations

from importlib import import_module
from typing import TYPE_CHECKING, Any

__version__ = "0.1.0"

URL_HANDLER_PACKAGE = "tactdeform_hw.emulator.serving.urlhandler"

#: Public name → the module that defines it, imported on first use.
_LAZY = {
    "open_device": "tactdeform_hw.device.driver.serial_driver",
    "open_port": "tactdeform_hw.device.driver.serial_driver",
    "StimConfig": "tactdeform_hw.device.driver.config",
    "Device": "tactdeform_hw.device.driver.base",
    "SafetyGuard": "tactdeform_hw.device.safety.guard",
    "ChannelMapping": "tactdeform_hw.device.participant.mapping",
    "Renderer": "tactdeform_hw.render.pipeline",
    "load_scene": "tactdeform_hw.render.scene",
    "ElectrodeArray": "tactdeform_hw.render.array",
    "make_trajectory": "tactdeform_hw.render.trajectories",
    "Approach": "tactdeform_hw.render.approach",
    "register_transport": "tactdeform_hw.transports",
}

_ERRORS = (
    "TactDeformError",
    "ConfigurationError",
    "LimitError",
    "ProfileError",
    "MissingDependencyError",
    "ProtocolError",
    "DecodeError",
    "ReplyLengthError",
    "ShortReplyError",
    "LongReplyError",
    "ProtocolMisuseError",
    "TransportError",
    "PortNotOpenError",
    "DeviceTimeoutError",
    "TransportUnavailableError",
    "DeviceGoneError",
    "DeviceBusyError",
    "SafetyError",
)

if TYPE_CHECKING:
    from tactdeform_hw.device.driver.base import Device as Device
    from tactdeform_hw.device.driver.config import StimConfig as StimConfig
    from tactdeform_hw.device.driver.serial_driver import open_device as open_device
    from tactdeform_hw.device.driver.serial_driver import open_port as open_port
    from tactdeform_hw.device.participant.mapping import ChannelMapping as ChannelMapping
    from tactdeform_hw.device.safety.guard import SafetyGuard as SafetyGuard

    from .errors import ConfigurationError as ConfigurationError
    from .errors import DecodeError as DecodeError
    from .errors import DeviceBusyError as DeviceBusyError
    from .errors import DeviceGoneError as DeviceGoneError
    from .errors import DeviceTimeoutError as DeviceTimeoutError
    from .errors import LimitError as LimitError
    from .errors import LongReplyError as LongReplyError
    from .errors import MissingDependencyError as MissingDependencyError
    from .errors import PortNotOpenError as PortNotOpenError
    from .errors import ProfileError as ProfileError
    from .errors import ProtocolError as ProtocolError
    from .errors import ProtocolMisuseError as ProtocolMisuseError
    from .errors import ReplyLengthError as ReplyLengthError
    from .errors import SafetyError as SafetyError
    from .errors import ShortReplyError as ShortReplyError
    from .errors import TactDeformError as TactDeformError
    from .errors import TransportError as TransportError
    from .errors import TransportUnavailableError as TransportUnavailableError
    from .render.approach import Approach as Approach
    from .render.array import ElectrodeArray as ElectrodeArray
    from .render.pipeline import Renderer as Renderer
    from .render.scene import load_scene as load_scene
    from .render.trajectories import make_trajectory as make_trajectory
    from .transports import register_transport as register_transport


def __getattr__(name: str) -> Any:
    module = _LAZY.get(name) or ("tactdeform_hw.errors" if name in _ERRORS else None)
    if module is None:
        raise AttributeError(f"module 'tactdeform_hw' has no attribute {name!r}")
    value = getattr(import_module(module), name)
    globals()[name] = value  # later lookups skip this function
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_LAZY) | set(_ERRORS))


def register_url_handlers() -> None:
    """Make ``serial.serial_for_url("etactile://…")`` reach the emulator (pyserial looks up
    ``protocol_<scheme>`` modules in ``serial.protocol_handler_packages``)."""
    import serial

    if URL_HANDLER_PACKAGE not in serial.protocol_handler_packages:
        serial.protocol_handler_packages.append(URL_HANDLER_PACKAGE)


register_url_handlers()

__all__ = [*sorted(_LAZY), *_ERRORS, "URL_HANDLER_PACKAGE", "__version__", "register_url_handlers"]
