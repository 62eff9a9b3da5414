"""The emulated board behind the seams a program opens: an in-process port, the ``etactile://`` pyserial
URL, a pseudo-terminal, TCP (the Wi-Fi build, with UDP discovery), and emulated USB, all on the wall
clock."""
