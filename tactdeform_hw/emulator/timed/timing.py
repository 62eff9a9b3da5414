"""Every timing constant of the emulated controller, named, sourced and changeable in one place.

Each field of :class:`TimingModel` carries its unit in its name and, in its metadata, where the number
comes from:

* ``firmware`` — read from the firmware's code (exact: a literal in an expression or a branch);
* ``firmware comment`` — a figure the firmware's authors wrote down next to the code;
* ``platform`` — a property of the ESP32-S3 / arduino-esp32 / FreeRTOS build the firmware runs on;
* ``assumption`` — a plausible value nobody has measured on a board yet.  These are the numbers to
  refine with a logic analyser; every report that depends on them says so through
  :meth:`TimingModel.describe`.

The simulation keeps time in integer nanoseconds (``*_ns`` properties round the µs fields to 1 ns), so
a scan that repeats for hours accumulates no floating-point drift and the event-exact engine and its
reference step-through agree to the nanosecond, not to a tolerance.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, fields, replace
from functools import cached_property
from typing import Any

from tactdeform_hw.errors import ConfigurationError, LimitError
from tactdeform_hw.protocol.firmware import (
    V1_2,
    FirmwareSpec,
    busy_wait_ticks,
    discharge_wait_arg,
    pulse_wait_arg,
)

_FW = V1_2.timing  # the defaults: the v1.2 firmware's constants (protocol.firmware holds each version's)

OVERRUN_POLICIES = ("immediate", "skip")
#: The model's constants that each firmware version's table (:class:`FirmwareTiming`) gives, under the
#: same names there (:meth:`TimingModel.for_firmware`); the others are the platform's or assumptions.
FIRMWARE_TIMING_FIELDS = (
    "spi_exchange_us",
    "dac_change_at_us",
    "gpio_write_us",
    "isr_entry_us",
    "pulse_wait_offset_us",
    "discharge_wait_offset_us",
    "delay_min_us",
    "delay_ticks_per_us",
    "delay_offset_ticks",
    "timer_tick_us",
    "watchdog_us",
    "rtos_tick_us",
    "parser_call_us",
    "parser_byte_us",
    "hv513_detect_us",
)
"""What follows a scan longer than the timer period.

``immediate`` (the default, Espressif's documented behaviour): the auto-reload alarm is re-enabled when
the handler returns, the counter has already passed it, so it fires at once and scans run back to back.
``skip``: the missed alarm is dropped and the next scan starts on the original period grid (what a timer
that ignores passed alarms would do); offered to compare against, not because the chip does it.
"""


def _f(default: Any, unit: str, source: str, doc: str) -> Any:
    return field(default=default, metadata={"unit": unit, "source": source, "doc": doc})


#: When the DAC output changes within an exchange: 3.3 µs in (the firmware comment) or when DA_CS rises
#: (the converter's datasheet).
DAC_LOADS = ("mid_exchange", "cs_rise")


def _reading(default: Any, doc: str) -> Any:
    """A reading of the exchange that the firmware's code leaves open: chosen by ``timing --cs-writes`` /
    ``--dac-load``, which list it themselves, so it is kept out of :meth:`TimingModel.describe`."""
    return field(default=default, metadata={"unit": "", "source": "option", "doc": doc, "reading": True})


@dataclass(frozen=True)
class TimingModel:
    """The controller's timing, from the SPI exchange to the interrupt watchdog.

    The defaults reproduce the worked figure of the protocol reference: 32 electrodes at pattern 1,
    200 µs pulses, 45 µs discharge, 125 Hz → 245.25 µs per channel, a 7850.2 µs scan inside the 8000 µs
    period; 50 µs discharge → 8010.2 µs, an overrun.
    """

    # --- the scan interrupt -------------------------------------------------------------------------------
    spi_exchange_us: float = _f(_FW.spi_exchange_us, "µs", "firmware comment", "one DAC/ADC SPI exchange")
    dac_change_at_us: float = _f(
        _FW.dac_change_at_us, "µs", "firmware comment", "when the DAC output changes within an exchange"
    )
    adc_sample_at_us: float = _f(
        0.0, "µs", "assumption", "when the ADC samples within the exchange that returns the reading"
    )
    gpio_write_us: float = _f(
        _FW.gpio_write_us, "µs", "assumption", "one fast GPIO write (LE, DIN, CLK, POL, BL)"
    )
    isr_entry_us: float = _f(
        _FW.isr_entry_us, "µs", "assumption", "from the timer alarm to the first statement of the handler"
    )
    isr_exit_us: float = _f(
        0.0, "µs", "assumption", "from the handler's last statement to the alarm re-enable"
    )
    pulse_wait_offset_us: int = _f(
        _FW.pulse_wait_offset_us, "µs", "firmware", "monophasic: busy-wait w - 7 µs only if w >= 7"
    )
    discharge_wait_offset_us: int = _f(
        _FW.discharge_wait_offset_us, "µs", "firmware", "discharge: busy-wait d - 7 µs only if d > 7"
    )
    delay_min_us: int = _f(_FW.delay_min_us, "µs", "firmware", "delay(us) raises us below this to this")
    delay_ticks_per_us: float = _f(
        _FW.delay_ticks_per_us, "ticks/µs", "firmware", "delay target = int(us * this - offset)"
    )
    delay_offset_ticks: float = _f(
        _FW.delay_offset_ticks, "ticks", "firmware", "delay target = int(us * scale - this)"
    )
    timer_tick_us: float = _f(
        _FW.timer_tick_us, "µs", "platform", "stimulation timer tick: 80 MHz APB / 40 = 2 MHz"
    )
    overrun_policy: str = _f("immediate", "", "platform", "what follows a scan longer than the period")
    watchdog_us: float | None = _f(
        _FW.watchdog_us, "µs", "platform", "interrupt watchdog (arduino-esp32, ESP32-S3); None disables it"
    )
    boot_us: float = _f(0.0, "µs", "assumption", "reboot to a running main loop after a watchdog reset")
    timer_start_us: float = _f(0.0, "µs", "assumption", "from boot to the stimulation timer's start")

    # --- the main loop and the parser ---------------------------------------------------------------------
    rtos_tick_us: float = _f(
        _FW.rtos_tick_us, "µs", "platform", "FreeRTOS tick (1 kHz); vTaskDelay(1) waits for the next"
    )
    tick_phase_us: float = _f(0.0, "µs", "assumption", "first RTOS tick after boot, modulo the tick period")
    parser_call_us: float = _f(
        _FW.parser_call_us,
        "µs",
        "assumption",
        "one Serial.available() call (v1.2's parser makes one per check)",
    )
    parser_byte_us: float = _f(
        _FW.parser_byte_us, "µs", "assumption", "reading one byte from the receive queue"
    )
    hv513_detect_us: float = _f(
        _FW.hv513_detect_us, "µs", "assumption", "0xF5: 50 analogRead() calls to count the boards"
    )
    rx_queue_bytes: int = _f(
        V1_2.rx_queue_bytes, "bytes", "firmware", "receive queue; the rest of a packet is discarded"
    )

    # --- the exchange's readings (the same scan statements, timed two ways each) -------------------------
    cs_writes_costed: bool = _reading(
        False,
        "whether each chip-select write around an exchange costs one GPIO write on top of the exchange "
        "(the firmware's host build) or lies inside it (the firmware comment's reading, the default)",
    )
    dac_load: str = _reading("mid_exchange", "when the DAC output changes: " + " or ".join(DAC_LOADS))
    chip_select_writes: int = _reading(
        _FW.chip_select_writes_per_exchange, "chip-select writes around one exchange (lowered, then raised)"
    )

    def __post_init__(self) -> None:
        if not isinstance(self.cs_writes_costed, bool):
            raise LimitError("cs_writes_costed", self.cs_writes_costed, "True or False")
        if self.dac_load not in DAC_LOADS:
            raise LimitError("dac_load", self.dac_load, " or ".join(DAC_LOADS))
        if not isinstance(self.chip_select_writes, int) or self.chip_select_writes not in (2, 4):
            raise LimitError("chip_select_writes", self.chip_select_writes, "2 (one write per edge) or 4")
        for f in fields(self):
            if f.metadata.get("reading"):
                continue
            value = getattr(self, f.name)
            if f.name == "overrun_policy":
                if value not in OVERRUN_POLICIES:
                    raise LimitError(f.name, value, " or ".join(OVERRUN_POLICIES))
                continue
            if f.name == "watchdog_us" and value is None:
                continue
            if (
                isinstance(value, bool)
                or not isinstance(value, (int, float))
                or not math.isfinite(value)
                or value < 0
            ):
                raise LimitError(f.name, value, "a finite number >= 0")
        if self.timer_tick_us <= 0:
            raise LimitError("timer_tick_us", self.timer_tick_us, "a positive number")
        if self.rtos_tick_us <= 0:
            raise LimitError("rtos_tick_us", self.rtos_tick_us, "a positive number")
        if not self.adc_sample_at_us <= self.dac_change_at_us <= self.spi_exchange_us:
            raise ConfigurationError(
                "the exchange must sample the ADC before the DAC changes, within the exchange: "
                f"adc_sample_at_us={self.adc_sample_at_us} <= dac_change_at_us={self.dac_change_at_us} "
                f"<= spi_exchange_us={self.spi_exchange_us}"
            )
        if self.watchdog_us is not None and self.watchdog_us <= 0:
            raise LimitError("watchdog_us", self.watchdog_us, "a positive number or None")
        if not isinstance(self.rx_queue_bytes, int) or self.rx_queue_bytes < 1:
            raise LimitError("rx_queue_bytes", self.rx_queue_bytes, "an integer >= 1")

    @classmethod
    def for_firmware(cls, firmware: FirmwareSpec, **changes: Any) -> TimingModel:
        """The model with a firmware version's own constants (its table in :mod:`..protocol.firmware`)."""
        base: dict[str, Any] = {name: getattr(firmware.timing, name) for name in FIRMWARE_TIMING_FIELDS}
        base["rx_queue_bytes"] = firmware.rx_queue_bytes
        base["chip_select_writes"] = firmware.timing.chip_select_writes_per_exchange
        base.update(changes)
        return cls(**base)

    # --- integer-nanosecond views (the simulation's clock) ------------------------------------------------

    @cached_property
    def spi_ns(self) -> int:
        return _ns(self.spi_exchange_us)

    @cached_property
    def dac_at_ns(self) -> int:
        return _ns(self.dac_change_at_us)

    @cached_property
    def adc_at_ns(self) -> int:
        return _ns(self.adc_sample_at_us)

    @cached_property
    def cs_write_ns(self) -> int:
        """What one chip-select write adds to an exchange: a GPIO write when costed, else nothing."""
        return self.gpio_ns if self.cs_writes_costed else 0

    @cached_property
    def exchange_ns(self) -> int:
        """One ``DAAD`` call: the SPI exchange and the chip-select writes around it (lowered before,
        raised after; they cost nothing apart under the default reading)."""
        return self.spi_ns + self.chip_select_writes * self.cs_write_ns

    @cached_property
    def exchange_lead_ns(self) -> int:
        """From a ``DAAD`` call to the start of its SPI exchange: the chip selects lowered."""
        return self.chip_select_writes // 2 * self.cs_write_ns

    @cached_property
    def dac_in_exchange_ns(self) -> int:
        """From a ``DAAD`` call to the DAC output's change: ``dac_change_at_us`` into the SPI exchange,
        or (``dac_load="cs_rise"``) when DA_CS, raised first, rises after it."""
        if self.dac_load == "cs_rise":
            return self.exchange_lead_ns + self.spi_ns + self.cs_write_ns
        return self.exchange_lead_ns + self.dac_at_ns

    @cached_property
    def adc_in_exchange_ns(self) -> int:
        """From a ``DAAD`` call to the ADC's sample: ``adc_sample_at_us`` into the SPI exchange."""
        return self.exchange_lead_ns + self.adc_at_ns

    @cached_property
    def gpio_ns(self) -> int:
        return _ns(self.gpio_write_us)

    @cached_property
    def isr_entry_ns(self) -> int:
        return _ns(self.isr_entry_us)

    @cached_property
    def isr_exit_ns(self) -> int:
        return _ns(self.isr_exit_us)

    @cached_property
    def tick_ns(self) -> int:
        """One stimulation-timer tick (0.5 µs by default)."""
        return _ns(self.timer_tick_us)

    @cached_property
    def watchdog_ns(self) -> int | None:
        return None if self.watchdog_us is None else _ns(self.watchdog_us)

    @cached_property
    def boot_ns(self) -> int:
        return _ns(self.boot_us)

    @cached_property
    def timer_start_ns(self) -> int:
        return _ns(self.timer_start_us)

    @cached_property
    def rtos_tick_ns(self) -> int:
        return _ns(self.rtos_tick_us)

    @cached_property
    def tick_phase_ns(self) -> int:
        return _ns(self.tick_phase_us) % self.rtos_tick_ns

    @cached_property
    def call_ns(self) -> int:
        return _ns(self.parser_call_us)

    @cached_property
    def byte_ns(self) -> int:
        return _ns(self.parser_byte_us)

    @cached_property
    def hv513_detect_ns(self) -> int:
        return _ns(self.hv513_detect_us)

    # --- the firmware's arithmetic ------------------------------------------------------------------------

    def delay_ticks(self, us: int) -> int:
        """``delay(us)``: raise to the minimum, then wait ``int(us * 2.0 - 5.4)`` timer ticks.

        Computed in double precision like the firmware's C expression (``2.0`` and ``5.4`` are doubles).
        A negative target (impossible with the defaults) waits nothing.
        """
        return busy_wait_ticks(us, self.delay_min_us, self.delay_ticks_per_us, self.delay_offset_ticks)

    def delay_ns(self, us: int) -> int:
        return self.delay_ticks(us) * self.tick_ns

    def pulse_wait_ns(self, width_us: int) -> int:
        """The busy-wait inside a monophasic pulse of ``width_us`` (none below the offset)."""
        arg = pulse_wait_arg(width_us, self.pulse_wait_offset_us)
        return 0 if arg is None else self.delay_ns(arg)

    def discharge_wait_ns(self, discharge_us: int) -> int:
        """The busy-wait with BL low during the discharge (only above the offset)."""
        arg = discharge_wait_arg(discharge_us, self.discharge_wait_offset_us)
        return 0 if arg is None else self.delay_ns(arg)

    def pulse_width_ns(self, width_us: int) -> int:
        """Time the current flows in one monophasic pulse: DAC change to DAC change.

        One full exchange plus the busy-wait: never shorter than the exchange (6.6 µs by default, its
        chip-select writes added when costed), and about ``w - 3.4`` µs for long pulses (200 µs →
        196.6 µs)."""
        return self.exchange_ns + self.pulse_wait_ns(width_us)

    def alarm_period_ns(self, alarm_ticks: int) -> int:
        return alarm_ticks * self.tick_ns

    # --- documentation ------------------------------------------------------------------------------------

    def describe(self) -> list[dict[str, Any]]:
        """One row per constant: name, value, unit, source and meaning (for reports and ``--json``); the
        exchange's readings are in :meth:`readings`."""
        return [
            {
                "name": f.name,
                "value": getattr(self, f.name),
                "unit": f.metadata.get("unit", ""),
                "source": f.metadata.get("source", ""),
                "doc": f.metadata.get("doc", ""),
            }
            for f in _constants()
        ]

    def readings(self) -> dict[str, Any]:
        """The exchange's readings: whether chip-select writes are costed, when the DAC loads."""
        return {f.name: getattr(self, f.name) for f in fields(self) if f.metadata.get("reading")}

    def assumptions(self) -> list[str]:
        """Names of the constants that are assumptions, not read from the firmware or the platform."""
        return [f.name for f in _constants() if f.metadata.get("source") == "assumption"]

    def with_(self, **changes: Any) -> TimingModel:
        """A copy with some constants changed (validated like the original)."""
        unknown = set(changes) - {f.name for f in fields(self)}
        if unknown:
            raise ConfigurationError(f"unknown timing constant(s): {', '.join(sorted(unknown))}")
        return replace(self, **changes)

    def to_dict(self) -> dict[str, Any]:
        """The constants (the readings apart: :meth:`readings`)."""
        return {f.name: getattr(self, f.name) for f in _constants()}


def _constants() -> list[Any]:
    """The model's constants: its fields without the exchange's readings."""
    return [f for f in fields(TimingModel) if not f.metadata.get("reading")]


def _ns(us: float) -> int:
    return int(round(us * 1000.0))


DEFAULT_MODEL = TimingModel()
