"""The device's refusals before any byte: a configuration and a frame checked whole, so that a refused
call writes nothing and supersedes nothing.

Every refusal is noted with the guard (its sink: the audit log) before it is raised, so the session's log
shows what was refused and why.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import TYPE_CHECKING

from tactdeform_hw.device.driver.config import StimConfig, robust_refusal
from tactdeform_hw.errors import LimitError, ProtocolMisuseError
from tactdeform_hw.protocol.constants import PATTERN_BIPHASIC, PATTERN_MONOPHASIC, PATTERN_SENSE

if TYPE_CHECKING:
    from tactdeform_hw.device.driver.dialect import Dialect
    from tactdeform_hw.device.participant.mapping import ChannelMapping
    from tactdeform_hw.device.safety.guard import SafetyGuard
    from tactdeform_hw.protocol.units import CurrentTransfer

#: Pattern levels a host may send: off (a sense pulse, 0 µA while sense current is 0), mono, biphasic.
ALLOWED_LEVELS = frozenset({PATTERN_SENSE, PATTERN_MONOPHASIC, PATTERN_BIPHASIC})
_INT_ONLY = frozenset({int})


def checked_config(
    config: StimConfig,
    *,
    dialect: Dialect,
    guard: SafetyGuard,
    transfer: CurrentTransfer,
    mapping: ChannelMapping | None,
    robust: bool,
    stimulating: bool,
    polarity_in_force: str | None,
) -> StimConfig:
    """``config`` as it will be sent (the guard may lower it), or the refusal: a value this firmware
    cannot encode, a limit, a count other than the mapping's channels, a payload byte that looks like a
    command under robust encoding, or an idle scan that starves the parser."""
    try:
        config = dialect.validated(config, transfer)
    except LimitError as exc:
        guard.note_refusal(exc)
        raise
    config = guard.check_config(
        config, stimulating=stimulating, polarity_in_force=polarity_in_force, transfer=transfer
    )
    if mapping is not None and mapping.hw_channels != config.electrode_count:
        raise LimitError(
            "electrode_count",
            config.electrode_count,
            f"the channel mapping's hardware channel count {mapping.hw_channels}",
        )
    refusal = robust_refusal(config, transfer) if robust else None
    if refusal is not None:
        guard.note_refusal(refusal)
        raise refusal
    dialect.check_idle_scan(guard, config)
    return config


def check_levels(levels: Sequence[int], expected: int, dialect: Dialect, guard: SafetyGuard) -> None:
    """Refuse a frame that is not ``expected`` levels of 0, 1 or 2, or one this firmware cannot express."""
    try:
        try:
            count = len(levels)
        except TypeError as exc:
            raise LimitError("pattern", levels, "a sequence of levels") from exc
        if count != expected:
            raise ProtocolMisuseError(
                f"pattern has {count} level(s) but the device is configured for {expected} electrode(s); "
                "a short pattern would swallow the next command and a long one would leak into it"
            )
        # every frame passes through here: plain ints of allowed values are told at C speed, and only a
        # frame with something else is walked level by level to name the first wrong one
        if not (set(map(type, levels)) <= _INT_ONLY and ALLOWED_LEVELS.issuperset(levels)):
            for i, v in enumerate(levels):
                if isinstance(v, bool) or not isinstance(v, int) or v not in ALLOWED_LEVELS:
                    raise LimitError(f"pattern[{i}]", v, "0 (off), 1 (monophasic) or 2 (biphasic)")
        dialect.check_levels(levels)
    except (LimitError, ProtocolMisuseError) as exc:
        guard.note_refusal(exc)
        raise


__all__ = ["ALLOWED_LEVELS", "check_levels", "checked_config"]
