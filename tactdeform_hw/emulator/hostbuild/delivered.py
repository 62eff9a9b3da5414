"""The pulses the emulated board delivered, read from the host-built firmware's pin and DAC events.

Safety is judged on what reached the electrodes, not on what the firmware meant: this decoder follows the
HV513 chain the firmware clocks (DIN shifted in on each CLK rising edge, outputs following the shift
register while LE is high and holding while it is low, all outputs off while BL is low), the polarity pin
and the DAC code, and reports every stretch in which current flows: a DAC code above 0, BL high and at
least one output on.  A stretch ends at any change of the code, the outputs, the polarity or BL.

The chain is as long as the board's outputs (8 per HV513 chip physically present), whatever count the
firmware detected: a 1 clocked past the last output is gone, and outputs that stay latched stay on.
"""

from __future__ import annotations

from dataclasses import dataclass

from tactdeform_hw.errors import LimitError


@dataclass(frozen=True)
class BoardPins:
    """The board's control pins (the eTactileKit's configuration.h)."""

    bl: int = 1
    le: int = 2
    pol: int = 3
    clk: int = 4
    din: int = 5


ETACTILEKIT_PINS = BoardPins()


@dataclass(frozen=True)
class DeliveredPulse:
    """Current through ``outputs`` at DAC ``code`` from ``start_us`` to ``end_us``; ``polarity`` is the POL
    pin (1 anodic, 0 cathodic)."""

    start_us: float
    end_us: float
    code: int
    outputs: tuple[int, ...]
    polarity: int

    @property
    def width_us(self) -> float:
        return self.end_us - self.start_us


class ChainDecoder:
    """Fed the firmware's events in time order (``feed``); collects :class:`DeliveredPulse` records."""

    def __init__(
        self, chain_outputs: int, pins: BoardPins = ETACTILEKIT_PINS, levels: dict[int, int] | None = None
    ) -> None:
        """``levels``: the pins' levels before the first event (all low: a board from power-on)."""
        if chain_outputs < 0:
            raise LimitError("chain_outputs", chain_outputs, ">= 0")
        self.pins = pins
        self.shift = [0] * chain_outputs
        self.latched = [0] * chain_outputs
        self.level = {pins.bl: 0, pins.le: 0, pins.pol: 0, pins.clk: 0, pins.din: 0}
        for pin, level in (levels or {}).items():
            if pin in self.level:
                self.level[pin] = level
        self.code = 0
        self.pulses: list[DeliveredPulse] = []
        self._open: tuple[int, int, tuple[int, ...], int] | None = None  # start ns, code, outputs, polarity

    def _flowing(self) -> tuple[int, tuple[int, ...], int] | None:
        if self.code <= 0 or not self.level[self.pins.bl]:
            return None
        outputs = tuple(i for i, bit in enumerate(self.latched) if bit)
        return (self.code, outputs, self.level[self.pins.pol]) if outputs else None

    def _update(self, t_ns: int) -> None:
        now = self._flowing()
        if self._open is not None and (now is None or now != self._open[1:]):
            start, code, outputs, pol = self._open
            if t_ns > start:
                self.pulses.append(DeliveredPulse(start / 1000.0, t_ns / 1000.0, code, outputs, pol))
            self._open = None
        if now is not None and self._open is None:
            self._open = (t_ns, *now)

    def gpio(self, t_ns: int, pin: int, level: int) -> None:
        if pin not in self.level:
            return
        p = self.pins
        if pin == p.clk and level and not self.level[p.clk] and self.shift:
            self.shift = [self.level[p.din], *self.shift[:-1]]
        self.level[pin] = level
        if self.level[p.le]:
            self.latched = list(self.shift)
        self._update(t_ns)

    def dac(self, t_ns: int, code: int) -> None:
        self.code = code
        self._update(t_ns)
