"""Firmware in the loop: an eTactileKit firmware's own C++ source, built on the host, run in virtual time.

:func:`build` compiles a PlatformIO tree against the package's Arduino/ESP32 shim (``shim/``);
:class:`HostBuildEmulator` loads the result and drives it like the Python timed model: bytes written at a
time, virtual time advanced, replies, GPIO/DAC events and the firmware's variables read back.  See
``docs/firmware-host-build.md``.
"""

from tactdeform_hw.emulator.hostbuild.build import BuildResult, build, cache_dir, find_compiler
from tactdeform_hw.emulator.hostbuild.statemap import UPSTREAM_V1_2, UPSTREAM_V2, StateMap

__all__ = ["BuildResult", "StateMap", "UPSTREAM_V1_2", "UPSTREAM_V2", "build", "cache_dir", "find_compiler"]
