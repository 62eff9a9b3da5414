"""tactdeform_hw: the eTactileKit protocol, a byte-exact emulator of its firmware, device drivers with
participant safety, and the TactDeform renderer on top."""

__version__ = "0.1.0"
