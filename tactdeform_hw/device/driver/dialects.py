"""The dialect of each firmware version the device layer drives, keyed by its spec.

A device speaks the dialect of the firmware its board proved (:mod:`.firmware_probe`); nothing else in
the driver asks which version it is: every difference is a method of the dialect or a field of the spec.
"""

from __future__ import annotations

from collections.abc import Mapping
from types import MappingProxyType

from tactdeform_hw.device.driver.dialect import Dialect
from tactdeform_hw.device.driver.v1_2 import V12Dialect
from tactdeform_hw.device.driver.v2 import V2Dialect
from tactdeform_hw.protocol.firmware import V1_2, V2, FirmwareSpec

#: One stateless dialect per firmware spec (each device keeps its own state in force).
DIALECTS: Mapping[FirmwareSpec, Dialect] = MappingProxyType({V1_2: V12Dialect(), V2: V2Dialect()})

__all__ = ["DIALECTS"]
