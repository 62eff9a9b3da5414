"""Stimulation settings in physical units, checked against the wire and the hardware before any write."""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Literal, cast

from tactdeform_hw import protocol as p
from tactdeform_hw.device.driver.pacing import command_like_payload
from tactdeform_hw.errors import LimitError
from tactdeform_hw.protocol.constants import MAX_ELECTRODES, SENSE_HEIGHT_SHIFT, U8_MAX, U16_MAX
from tactdeform_hw.protocol.units import CurrentTransfer, check_int

Polarity = Literal["anodic", "cathodic"]
POLARITY_CODE: dict[str, int] = {"anodic": 1, "cathodic": 0}


@dataclass(frozen=True)
class StimConfig:
    """Everything ``configure`` sends.  Defaults are the TactDeform setting: 32 electrodes, 200 µs
    anodic pulses, 45 µs discharge, 125 Hz, and a current of 0 until a participant's level is set.

    ``sense_current_ua`` is the small pulse the firmware delivers on every channel whose pattern value is
    neither 1 nor 2 — an "off" channel is only truly off while it is 0, so it defaults to 0.
    """

    electrode_count: int = 32
    current_ua: int = 0
    pulse_width_us: int = 200
    discharge_us: int = 45
    rate_hz: int = 125
    polarity: Polarity = "anodic"
    sense_current_ua: int = 0
    sense_width_us: int = 0

    def validated(self, transfer: CurrentTransfer) -> StimConfig:
        """The configuration with every field checked (raises :class:`LimitError` naming the field) and
        held as the integers it is sent as: an integral float read from JSON (``32.0``) becomes ``32``,
        so nothing downstream computes with a float where the firmware holds an integer.  Each field is
        stored as its own check returns it, so no field can be checked and then sent unconverted; the
        fields are checked in their order, so the first bad one is the one named."""
        return replace(
            self,
            electrode_count=check_int("electrode_count", self.electrode_count, 1, MAX_ELECTRODES),
            current_ua=transfer.check_current(self.current_ua, "current_ua"),
            pulse_width_us=check_int("pulse_width_us", self.pulse_width_us, 1, U16_MAX, "µs"),
            discharge_us=check_int("discharge_us", self.discharge_us, 0, U8_MAX, "µs"),
            rate_hz=check_int("rate_hz", self.rate_hz, 1, U16_MAX, "Hz"),
            polarity=_checked_polarity(self.polarity),
            sense_current_ua=_checked_sense_current(self.sense_current_ua, transfer),
            sense_width_us=check_int("sense_width_us", self.sense_width_us, 0, U8_MAX, "µs"),
        )

    def with_current(self, current_ua: int) -> StimConfig:
        return replace(self, current_ua=current_ua)


def _checked_polarity(polarity: object) -> Polarity:
    """``polarity`` when the firmware has a code for it (:data:`POLARITY_CODE`), else the refusal naming
    the field."""
    if not isinstance(polarity, str) or polarity not in POLARITY_CODE:
        raise LimitError("polarity", polarity, "'anodic' or 'cathodic'")
    return cast(Polarity, polarity)


def _checked_sense_current(sense_current_ua: int, transfer: CurrentTransfer) -> int:
    """``sense_current_ua`` as an integer when the 0xF9 byte can carry it (:func:`sense_code`: every
    fourth DAC code) and it is a current ``transfer`` allows, else the refusal naming the field."""
    sense_code(sense_current_ua, transfer)
    return transfer.check_current(sense_current_ua, "sense_current_ua")


def sense_code(sense_current_ua: int, transfer: CurrentTransfer) -> int:
    """The 0xF9 byte for a sense current: the firmware stores ``byte << 2`` as the DAC code, so only
    every fourth code is reachable."""
    code = transfer.to_code(sense_current_ua, "sense_current_ua")
    step = 1 << SENSE_HEIGHT_SHIFT
    if code % step or code // step > U8_MAX:
        raise LimitError(
            "sense_current_ua",
            sense_current_ua,
            f"a current whose DAC code is a multiple of {step} up to {U8_MAX * step} (this one is code "
            f"{code})",
        )
    return code // step


def robust_refusal(config: StimConfig, transfer: CurrentTransfer) -> LimitError | None:
    """Under robust encoding no payload byte may look like a command byte: the refusal naming the first
    field of ``config`` whose command would carry one (None when every one is clean)."""
    cmds = {
        "electrode_count": p.encode_electrode_num(config.electrode_count),
        "pulse_width_us": p.encode_pulse_width(config.pulse_width_us),
        "discharge_us": p.encode_discharge(config.discharge_us),
        "rate_hz": p.encode_frequency(config.rate_hz),
        "sense_width_us": p.encode_sense_width(config.sense_width_us),
        "sense_current_ua": p.encode_sense_height(sense_code(config.sense_current_ua, transfer)),
    }
    for name, data in cmds.items():
        if command_like_payload(data) is not None:
            return LimitError(
                name,
                getattr(config, name),
                "a value whose bytes are all below 0xF5 (robust encoding: a payload byte must never look "
                "like a command byte)",
            )
    return None
