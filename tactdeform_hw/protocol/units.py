"""Value types with real units, and the checks that keep them inside what the wire can carry.

Every check raises :class:`~tactdeform_hw.errors.LimitError` naming the field, the value and the limit:
an out-of-range value is never wrapped, truncated or clamped silently on the host side.
"""

from __future__ import annotations

import math
import numbers
from dataclasses import dataclass

from ..errors import ConfigurationError, LimitError
from .constants import (
    CURRENT_STEP_UA,
    DAC_MAX_CODE,
    DEFAULT_UA_PER_CODE,
    MAX_CURRENT_UA,
)


def check_int(field: str, value: object, lo: int, hi: int, unit: str = "") -> int:
    """Return ``value`` as an int if it is an integer in ``[lo, hi]``; raise naming the field otherwise.

    Floats are accepted only when integral (``200.0``), because a study config read from JSON may carry
    them; ``True``/``False``, NaN, infinities and fractional values are refused.
    """
    if type(value) is int and lo <= value <= hi:  # the common case, without the abstract-class checks
        return value
    suffix = f" {unit}" if unit else ""
    if isinstance(value, bool) or not isinstance(value, numbers.Real):
        raise LimitError(field, value, f"an integer from {lo} to {hi}{suffix}")
    if isinstance(value, numbers.Integral):
        ivalue = int(value)
    else:
        fvalue = float(value)
        if not math.isfinite(fvalue) or not fvalue.is_integer():
            raise LimitError(field, value, f"an integer from {lo} to {hi}{suffix}")
        ivalue = int(fvalue)
    if ivalue < lo or ivalue > hi:
        raise LimitError(field, value, f"{lo} to {hi}{suffix}")
    return ivalue


@dataclass(frozen=True)
class CurrentTransfer:
    """DAC code ↔ current.  The default (1 code = 10 µA, so 10 mA = code 1000) is the TactDeform board's
    nominal transfer; a board calibration replaces it with measured ``ua_per_code`` and ``offset_ua``."""

    ua_per_code: float = DEFAULT_UA_PER_CODE
    offset_ua: float = 0.0
    max_current_ua: int = MAX_CURRENT_UA
    step_ua: int = CURRENT_STEP_UA

    def __post_init__(self) -> None:
        if not (math.isfinite(self.ua_per_code) and self.ua_per_code > 0):
            raise ConfigurationError(f"ua_per_code={self.ua_per_code!r} must be a positive finite number")
        if not math.isfinite(self.offset_ua):
            raise ConfigurationError(f"offset_ua={self.offset_ua!r} must be finite")

    def check_current(self, current_ua: object, field: str = "current_ua") -> int:
        """Validate a host-side current: an integer number of µA, a multiple of the step, ≤ the ceiling."""
        value = check_int(field, current_ua, 0, self.max_current_ua, "µA")
        if value % self.step_ua:
            raise LimitError(field, current_ua, f"a multiple of {self.step_ua} µA")
        return value

    def to_code(self, current_ua: object, field: str = "current_ua") -> int:
        """The DAC code that delivers ``current_ua`` (0 stays 0: off is exactly off)."""
        value = self.check_current(current_ua, field)
        if value == 0:
            return 0
        code = round((value - self.offset_ua) / self.ua_per_code)
        if code < 0 or code > DAC_MAX_CODE:
            raise LimitError(
                field, current_ua, f"a DAC code from 0 to {DAC_MAX_CODE} (this transfer gives {code})"
            )
        return code

    def to_ua(self, code: int) -> float:
        """The current a DAC code delivers under this transfer."""
        return 0.0 if code == 0 else code * self.ua_per_code + self.offset_ua


DEFAULT_TRANSFER = CurrentTransfer()
