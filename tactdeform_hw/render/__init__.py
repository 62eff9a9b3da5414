"""The TactDeform renderer: scenes, the electrode array, the three approaches (TactDeform, UA, CAM) and
the pipeline from poses to device patterns.  Names are imported on first use, so importing one
submodule does not load the rest."""

from __future__ import annotations

from importlib import import_module
from typing import TYPE_CHECKING, Any

_LAZY = {
    "Renderer": "pipeline",
    "FrameRecord": "pipeline",
    "RunSummary": "pipeline",
    "LOST_TRACKING_S": "pipeline",
    "LiveRun": "live",
    "UdpTrackingSource": "live",
    "open_tracking": "live",
    "Approach": "approach",
    "APPROACH_FACTORIES": "approach",
    "make_approach": "approach",
    "PatternManager": "manager",
    "ManagerConfig": "manager",
    "ManagerOutput": "manager",
    "UniformActivation": "baselines",
    "ContactAreaMapping": "baselines",
    "ElectrodeArray": "array",
    "PatternSet": "patterns",
    "PatternParams": "patterns",
    "Scene": "scene",
    "RenderOptions": "scene",
    "APPROACHES": "scene",
    "load_scene": "scene",
    "Pose": "tracking",
    "read_pose_csv": "tracking",
    "TRAJECTORIES": "trajectories",
    "make_trajectory": "trajectories",
}

if TYPE_CHECKING:
    from .approach import APPROACH_FACTORIES as APPROACH_FACTORIES
    from .approach import Approach as Approach
    from .approach import make_approach as make_approach
    from .array import ElectrodeArray as ElectrodeArray
    from .baselines import ContactAreaMapping as ContactAreaMapping
    from .baselines import UniformActivation as UniformActivation
    from .live import LiveRun as LiveRun
    from .live import UdpTrackingSource as UdpTrackingSource
    from .live import open_tracking as open_tracking
    from .manager import ManagerConfig as ManagerConfig
    from .manager import ManagerOutput as ManagerOutput
    from .manager import PatternManager as PatternManager
    from .patterns import PatternParams as PatternParams
    from .patterns import PatternSet as PatternSet
    from .pipeline import LOST_TRACKING_S as LOST_TRACKING_S
    from .pipeline import FrameRecord as FrameRecord
    from .pipeline import Renderer as Renderer
    from .pipeline import RunSummary as RunSummary
    from .scene import APPROACHES as APPROACHES
    from .scene import RenderOptions as RenderOptions
    from .scene import Scene as Scene
    from .scene import load_scene as load_scene
    from .tracking import Pose as Pose
    from .tracking import read_pose_csv as read_pose_csv
    from .trajectories import TRAJECTORIES as TRAJECTORIES
    from .trajectories import make_trajectory as make_trajectory


def __getattr__(name: str) -> Any:
    module = _LAZY.get(name)
    if module is None:
        raise AttributeError(f"module 'tactdeform_hw.render' has no attribute {name!r}")
    value = getattr(import_module(f"{__name__}.{module}"), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_LAZY))


__all__ = sorted(_LAZY)
