"""A stimulating session: profile, guard, wiring, delivery log, device and renderer, built in the order
that refuses what it can before anything is sent (:mod:`.builder`), and the log of what it delivered
(:mod:`.delivery`)."""

from .builder import Session, Wiring, guard_for, read_participant, regions_by_electrode
from .delivery import DeliveryLog, session_region_map

__all__ = [
    "DeliveryLog",
    "Session",
    "Wiring",
    "guard_for",
    "read_participant",
    "regions_by_electrode",
    "session_region_map",
]
