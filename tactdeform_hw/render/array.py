"""The electrode array on the finger pad: where each electrode sits, in which order the renderer numbers
them, which calibration region each belongs to, and how that order reaches the hardware channels.

Everything the renderer draws is computed from positions in millimetres in the finger-pad frame (x to
the right, y toward the fingertip), never from grid indices, so the same patterns run on the TactDeform
6 × 6 array and on any other layout (an eTactileKit array file, a 64-electrode board).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from tactdeform_hw.device.participant.mapping import ChannelMapping

from ..errors import ConfigurationError, LimitError
from ..protocol.constants import MAX_ELECTRODES

#: TactDeform finger-pad array: 6 × 6 grid without its four corners, 2.0 mm pitch, 1.4 mm electrodes.
TACTDEFORM_ROWS = 6
TACTDEFORM_COLS = 6
TACTDEFORM_PITCH_MM = 2.0
TACTDEFORM_ELECTRODE_DIAMETER_MM = 1.4

#: Calibration regions: 3 × 3, numbered row-major from the fingertip side, left to right; 4 is the centre.
REGION_ROWS = 3
REGION_COLS = 3
CENTRE_REGION = 4


class ElectrodeArray:
    """Electrode positions (application order), electrode radius and the application → hardware mapping.

    ``mapping[i]`` is the hardware channel of application electrode ``i`` (eTactileKit's
    ``Mapping_func``); ``None`` means the identity.  ``hw_channels`` is the channel count the firmware
    scans (defaults to the highest mapped channel + 1).  Positions are copied and frozen.
    """

    __slots__ = (
        "name",
        "positions_mm",
        "radius_mm",
        "mapping",
        "hw_channels",
        "pitch_mm",
        "centre_mm",
        "regions",
        "_index",
    )

    def __init__(
        self,
        positions_mm: np.ndarray | Sequence[Sequence[float]],
        radius_mm: float,
        mapping: tuple[int, ...] | Sequence[int] | None = None,
        name: str = "array",
        *,
        hw_channels: int | None = None,
    ) -> None:
        pos = np.array(positions_mm, dtype=float)
        if pos.ndim != 2 or pos.shape[1] != 2:
            raise LimitError("positions_mm", pos.shape, "an (N, 2) array of x, y in mm")
        n = pos.shape[0]
        if not 1 <= n <= MAX_ELECTRODES:
            raise LimitError("positions_mm", f"{n} electrode(s)", f"1 to {MAX_ELECTRODES} electrodes")
        if not np.all(np.isfinite(pos)):
            bad = int(np.argwhere(~np.isfinite(pos))[0][0])
            raise LimitError(f"positions_mm[{bad}]", pos[bad].tolist(), "finite coordinates in mm")
        radius = float(radius_mm)
        if not (math.isfinite(radius) and radius > 0.0):
            raise LimitError("radius_mm", radius_mm, "a finite radius > 0 mm")
        if n > 1:
            d = np.linalg.norm(pos[:, None, :] - pos[None, :, :], axis=-1)
            np.fill_diagonal(d, np.inf)
            nearest = d.min(axis=1)
            if float(nearest.min()) <= 1e-9:
                i, j = np.unravel_index(int(np.argmin(d)), d.shape)
                raise ConfigurationError(f"positions_mm[{i}] and positions_mm[{j}] are the same point")
            # The pitch is the typical centre-to-centre distance; the median resists a stray electrode.
            pitch = float(np.median(nearest))
        else:
            pitch = 2.0 * radius
        if mapping is None:
            chans = tuple(range(n))
        else:
            chans = tuple(int(c) for c in mapping)
            if len(chans) != n:
                raise LimitError(
                    "mapping", f"{len(chans)} channel(s)", f"one hardware channel per electrode ({n})"
                )
        hw = hw_channels if hw_channels is not None else (max(chans) + 1)
        # Validate through the device's own type so the errors read the same everywhere.
        ChannelMapping(chans, hw)
        pos.setflags(write=False)
        self.name = str(name)
        self.positions_mm = pos
        self.radius_mm = radius
        self.mapping = None if mapping is None else chans
        self.hw_channels = int(hw)
        self.pitch_mm = pitch
        lo = pos.min(axis=0)
        hi = pos.max(axis=0)
        # The bounding-box centre, not the centroid: removing corners or a side row must not move it.
        centre = (lo + hi) / 2.0
        centre.setflags(write=False)
        self.centre_mm = centre
        self.regions = _regions(pos, lo, hi)
        self._index = {(round(float(x), 6), round(float(y), 6)): i for i, (x, y) in enumerate(pos)}

    # --- the TactDeform array ----------------------------------------------------------------------------

    @classmethod
    def tactdeform(
        cls,
        *,
        pitch_mm: float = TACTDEFORM_PITCH_MM,
        diameter_mm: float = TACTDEFORM_ELECTRODE_DIAMETER_MM,
        mapping: Sequence[int] | None = None,
        hw_channels: int | None = None,
    ) -> ElectrodeArray:
        """The 32-electrode finger-pad array, centred on the pad: rows from the fingertip (y = +5 mm)
        down, electrodes left to right in each row, the four grid corners absent."""
        return cls.grid(
            TACTDEFORM_ROWS,
            TACTDEFORM_COLS,
            pitch_mm=pitch_mm,
            radius_mm=diameter_mm / 2.0,
            drop_corners=True,
            mapping=mapping,
            hw_channels=hw_channels,
            name="tactdeform-32",
        )

    @classmethod
    def grid(
        cls,
        rows: int,
        cols: int,
        *,
        pitch_mm: float,
        radius_mm: float,
        drop_corners: bool = False,
        mapping: Sequence[int] | None = None,
        hw_channels: int | None = None,
        name: str | None = None,
    ) -> ElectrodeArray:
        """A rectangular grid centred on the pad, in application order (fingertip row first)."""
        if rows < 1 or cols < 1:
            raise LimitError("rows×cols", (rows, cols), "at least 1 × 1")
        if not (math.isfinite(pitch_mm) and pitch_mm > 0):
            raise LimitError("pitch_mm", pitch_mm, "a finite pitch > 0 mm")
        pts: list[tuple[float, float]] = []
        corners = {(0, 0), (0, cols - 1), (rows - 1, 0), (rows - 1, cols - 1)} if drop_corners else set()
        for r in range(rows):
            y = ((rows - 1) / 2.0 - r) * pitch_mm
            for c in range(cols):
                if (r, c) in corners:
                    continue
                pts.append(((c - (cols - 1) / 2.0) * pitch_mm, y))
        return cls(
            np.array(pts),
            radius_mm,
            None if mapping is None else tuple(mapping),
            name or f"grid-{rows}x{cols}",
            hw_channels=hw_channels,
        )

    # --- queries -------------------------------------------------------------------------------------------

    @property
    def count(self) -> int:
        return int(self.positions_mm.shape[0])

    def __len__(self) -> int:
        return self.count

    def channel_mapping(self) -> ChannelMapping:
        """The device layer's application → hardware mapping for this array."""
        chans = self.mapping if self.mapping is not None else tuple(range(self.count))
        return ChannelMapping(chans, self.hw_channels)

    def region_members(self, region: int) -> np.ndarray:
        """Application indices of the electrodes in one calibration region (0–8)."""
        if not 0 <= region < REGION_ROWS * REGION_COLS:
            raise LimitError("region", region, f"0 to {REGION_ROWS * REGION_COLS - 1}")
        return np.flatnonzero(self.regions == region)

    def index_at(self, x_mm: float, y_mm: float, tolerance_mm: float | None = None) -> int:
        """The electrode whose centre is within ``tolerance_mm`` (default a quarter pitch) of a point,
        or -1.  Used at build time to shift patterns by whole spacings on any layout."""
        key = (round(float(x_mm), 6), round(float(y_mm), 6))
        hit = self._index.get(key)
        if hit is not None:
            return hit
        tol = self.pitch_mm / 4.0 if tolerance_mm is None else tolerance_mm
        d = np.hypot(self.positions_mm[:, 0] - x_mm, self.positions_mm[:, 1] - y_mm)
        i = int(np.argmin(d))
        return i if float(d[i]) <= tol else -1

    def world_offsets(self) -> np.ndarray:
        """Positions relative to the array centre, (N, 2) mm — what the pose's position refers to."""
        rel: np.ndarray = self.positions_mm - self.centre_mm
        return rel

    def __repr__(self) -> str:
        return (
            f"ElectrodeArray({self.name!r}, {self.count} electrodes, pitch {self.pitch_mm:g} mm, "
            f"radius {self.radius_mm:g} mm, hw_channels {self.hw_channels})"
        )


def _regions(pos: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """3 × 3 calibration regions from the bounding box split in thirds; row 0 is the fingertip side.

    A small tolerance keeps electrodes sitting on a third-line (as in a 3-column array) in the region a
    person would name, independent of floating-point rounding."""
    span = hi - lo
    eps = 1e-6
    out = np.empty(pos.shape[0], dtype=np.int8)
    for i, (x, y) in enumerate(pos):
        col = 1 if span[0] <= eps else min(REGION_COLS - 1, int((x - lo[0]) / span[0] * REGION_COLS + eps))
        row = 1 if span[1] <= eps else min(REGION_ROWS - 1, int((hi[1] - y) / span[1] * REGION_ROWS + eps))
        out[i] = row * REGION_COLS + col
    out.setflags(write=False)
    return out
