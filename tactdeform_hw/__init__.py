"""tactdeform_hw: the eTactileKit protocol, a byte-exact emulator of its firmware, device drivers with
participant safety, and the TactDeform renderer on top."""

__version__ = "0.1.0"

URL_HANDLER_PACKAGE = "tactdeform_hw.emulator.urlhandler"


def register_url_handlers() -> None:
    """Make ``serial.serial_for_url("etactile://…")`` reach the emulator (pyserial looks up
    ``protocol_<scheme>`` modules in ``serial.protocol_handler_packages``)."""
    import serial

    if URL_HANDLER_PACKAGE not in serial.protocol_handler_packages:
        serial.protocol_handler_packages.append(URL_HANDLER_PACKAGE)


register_url_handlers()
