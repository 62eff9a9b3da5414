"""One interface for the three rendering approaches the paper compares: TactDeform, UA and CAM.

Every approach turns one tracking sample (time, pad position, pad orientation, the scene's surface query
for the pad centre, the scene itself) into a :class:`~.manager.ManagerOutput`, keeps
:class:`~.manager.ManagerStats`, counts a sample the renderer judged unusable without looking at it, and can
forget the finger.  The renderer holds approaches only through
this protocol; the names users type (``--approach``, a scene's ``approach`` key) pick a factory from
:data:`APPROACH_FACTORIES`.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, Protocol, runtime_checkable

from ..errors import LimitError
from .array import ElectrodeArray
from .manager import ManagerConfig, ManagerOutput, ManagerStats, PatternManager
from .patterns import PatternParams, PatternSet


@runtime_checkable
class Approach(Protocol):
    """What the renderer needs of a rendering approach."""

    name: str
    stats: ManagerStats

    @property
    def state(self) -> str:
        """ "idle", "approaching" or "interacting" (read only: the approach alone moves it)."""
        ...

    def update(
        self, t_s: float, position_mm: Any, orientation_wxyz: Any, query: Any, scene: Any = None
    ) -> ManagerOutput: ...

    def drop(self, t_s: Any, reason: str) -> ManagerOutput:
        """Count a sample the renderer judged unusable (``reason``); change nothing, report what is held."""
        ...

    def reset(self) -> None: ...


ApproachFactory = Callable[[ElectrodeArray, ManagerConfig, "PatternParams | None"], Approach]


def _tactdeform(array: ElectrodeArray, config: ManagerConfig, params: PatternParams | None) -> Approach:
    return PatternManager(array, config, patterns=PatternSet(array, params))


def _baseline(name: str) -> ApproachFactory:
    def make(array: ElectrodeArray, config: ManagerConfig, params: PatternParams | None) -> Approach:
        from .baselines import make_baseline

        return make_baseline(name, array, on_level=params.on_level if params is not None else 1)

    return make


#: The approaches by the name a user gives.
APPROACH_FACTORIES: dict[str, ApproachFactory] = {
    "tactdeform": _tactdeform,
    "ua": _baseline("ua"),
    "cam": _baseline("cam"),
}


def make_approach(
    name: str,
    array: ElectrodeArray | None = None,
    config: ManagerConfig | None = None,
    pattern_params: PatternParams | None = None,
) -> Approach:
    """The approach called ``name`` (``tactdeform``, ``ua`` or ``cam``) on ``array``."""
    factory = APPROACH_FACTORIES.get(name)
    if factory is None:
        names = [repr(n) for n in APPROACH_FACTORIES]
        raise LimitError("approach", name, ", ".join(names[:-1]) + " or " + names[-1])
    return factory(
        array if array is not None else ElectrodeArray.tactdeform(), config or ManagerConfig(), pattern_params
    )


__all__ = ["APPROACH_FACTORIES", "Approach", "ApproachFactory", "make_approach"]
