"""Pictures: the electrode array (PNG, animated GIF) and timing diagrams of the stimulation scan.

matplotlib and Pillow (the ``plot`` extra) are imported only when a picture is drawn; without them the
drawing functions raise :class:`~tactdeform_hw.errors.MissingDependencyError` naming the extra.
"""

from .array_picture import (
    PictureFrame,
    PictureInfo,
    draw_array_gif,
    draw_array_png,
    draw_frames_gif,
    frames_from_frames,
    frames_from_sequence,
)
from .timing_diagram import Cycle, Pulse, TimingInfo, draw_reports_png, draw_timing_png, to_cycles, to_pulses

__all__ = [
    "Cycle",
    "PictureFrame",
    "PictureInfo",
    "Pulse",
    "TimingInfo",
    "draw_array_gif",
    "draw_array_png",
    "draw_frames_gif",
    "draw_reports_png",
    "draw_timing_png",
    "frames_from_frames",
    "frames_from_sequence",
    "to_cycles",
    "to_pulses",
]
