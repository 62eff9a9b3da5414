"""The finger-pad electrode array: layout, application order, calibration regions, channel mapping."""

from __future__ import annotations

import math

import numpy as np
import pytest

from tactdeform_hw.device import ChannelMapping
from tactdeform_hw.errors import ConfigurationError, LimitError
from tactdeform_hw.render.array import CENTRE_REGION, ElectrodeArray


@pytest.fixture
def pad() -> ElectrodeArray:
    return ElectrodeArray.tactdeform()


def test_tactdeform_array_is_6x6_without_corners_at_2mm_pitch(pad: ElectrodeArray) -> None:
    assert pad.count == len(pad) == 32
    assert pad.pitch_mm == pytest.approx(2.0)
    assert pad.radius_mm == pytest.approx(0.7)  # 1.4 mm electrodes
    xs = sorted({round(float(x), 6) for x in pad.positions_mm[:, 0]})
    ys = sorted({round(float(y), 6) for y in pad.positions_mm[:, 1]})
    assert xs == ys == [-5.0, -3.0, -1.0, 1.0, 3.0, 5.0]
    corners = {(-5.0, 5.0), (5.0, 5.0), (-5.0, -5.0), (5.0, -5.0)}
    present = {(float(x), float(y)) for x, y in pad.positions_mm}
    assert not corners & present
    assert len(present) == 32
    np.testing.assert_allclose(pad.centre_mm, [0.0, 0.0])


def test_application_order_is_row_major_from_the_fingertip_left_to_right(pad: ElectrodeArray) -> None:
    pos = pad.positions_mm
    # Fingertip row (y = +5) first: 4 electrodes, then four rows of 6, then the last row of 4.
    assert [tuple(p) for p in pos[:4]] == [(-3, 5), (-1, 5), (1, 5), (3, 5)]
    assert [tuple(p) for p in pos[4:10]] == [(-5, 3), (-3, 3), (-1, 3), (1, 3), (3, 3), (5, 3)]
    assert [tuple(p) for p in pos[28:]] == [(-3, -5), (-1, -5), (1, -5), (3, -5)]
    # y never increases along the order; within a row x increases.
    for a, b in zip(pos[:-1], pos[1:]):
        assert b[1] < a[1] or (b[1] == a[1] and b[0] > a[0])


def test_calibration_regions_are_3x3_row_major_from_the_fingertip(pad: ElectrodeArray) -> None:
    counts = [len(pad.region_members(r)) for r in range(9)]
    # Corner regions lose the grid corner; the others hold a 2 × 2 block.
    assert counts == [3, 4, 3, 4, 4, 4, 3, 4, 3]
    centre = {tuple(pad.positions_mm[i]) for i in pad.region_members(CENTRE_REGION)}
    assert centre == {(-1.0, 1.0), (1.0, 1.0), (-1.0, -1.0), (1.0, -1.0)}
    top_left = {tuple(pad.positions_mm[i]) for i in pad.region_members(0)}
    assert top_left == {(-3.0, 5.0), (-5.0, 3.0), (-3.0, 3.0)}
    bottom_right = {tuple(pad.positions_mm[i]) for i in pad.region_members(8)}
    assert bottom_right == {(3.0, -5.0), (5.0, -3.0), (3.0, -3.0)}
    with pytest.raises(LimitError, match="region"):
        pad.region_members(9)


def test_channel_mapping_goes_through_the_device_type(pad: ElectrodeArray) -> None:
    m = pad.channel_mapping()
    assert isinstance(m, ChannelMapping)
    assert m.app_to_hw == tuple(range(32)) and m.hw_channels == 32
    rev = ElectrodeArray.tactdeform(mapping=list(range(31, -1, -1)))
    rm = rev.channel_mapping()
    levels = [1 if i == 0 else 0 for i in range(32)]
    assert rm.to_hardware(levels)[31] == 1  # application electrode 0 sits on hardware channel 31
    wide = ElectrodeArray.tactdeform(mapping=[2 * i for i in range(32)], hw_channels=64)
    assert wide.channel_mapping().hw_channels == 64


def test_bad_mappings_are_refused_with_the_field_named() -> None:
    with pytest.raises(ConfigurationError, match="mapping"):
        ElectrodeArray.tactdeform(mapping=[0] * 32)
    with pytest.raises(LimitError, match="mapping"):
        ElectrodeArray.tactdeform(mapping=list(range(31)))
    with pytest.raises(LimitError, match="mapping"):
        ElectrodeArray.tactdeform(mapping=list(range(32)), hw_channels=16)


def test_general_constructor_takes_any_layout() -> None:
    # The eTactileKit main-board layout (8 electrodes, 10 mm apart, radius 1 mm).
    pos = np.array([(-5, 15), (5, 15), (-10, 5), (0, 5), (10, 5), (-10, -5), (0, -5), (10, -5)], dtype=float)
    arr = ElectrodeArray(pos, 1.0, (0, 1, 2, 3, 4, 5, 6, 7), "main-board")
    assert arr.count == 8 and arr.name == "main-board"
    assert arr.pitch_mm == pytest.approx(10.0)
    np.testing.assert_allclose(arr.centre_mm, [0.0, 5.0])
    assert arr.regions.tolist() == [0, 2, 3, 4, 5, 6, 7, 8]
    assert arr.index_at(0.0, 5.2) == 3
    assert arr.index_at(0.0, 9.0) == -1
    # The constructor copies and freezes the positions.
    pos[0, 0] = 99.0
    assert arr.positions_mm[0, 0] == -5.0
    with pytest.raises(ValueError):
        arr.positions_mm[0, 0] = 1.0


@pytest.mark.parametrize(
    ("positions", "radius", "match"),
    [
        ([[0.0, 0.0], [math.nan, 1.0]], 1.0, r"positions_mm\[1\]"),
        ([[0.0, 0.0], [0.0, 0.0]], 1.0, "same point"),
        ([[0.0, 0.0, 0.0]], 1.0, "positions_mm"),
        ([[0.0, 0.0]], 0.0, "radius_mm"),
        ([[0.0, 0.0]], math.inf, "radius_mm"),
    ],
)
def test_bad_layouts_are_refused(positions: list[list[float]], radius: float, match: str) -> None:
    with pytest.raises(ConfigurationError, match=match):
        ElectrodeArray(np.array(positions), radius, None, "bad")


def test_grid_builder_makes_other_sizes() -> None:
    g = ElectrodeArray.grid(8, 8, pitch_mm=2.5, radius_mm=0.75)
    assert g.count == 64 and g.pitch_mm == pytest.approx(2.5)
    # 8 columns split 3-2-3 by thirds of the span.
    assert [len(g.region_members(r)) for r in range(9)] == [9, 6, 9, 6, 4, 6, 9, 6, 9]
