"""pyserial URL handlers for the emulator (``etactile://``); found through
``serial.protocol_handler_packages``, which importing :mod:`tactdeform_hw` extends."""
