"""The Unity sender's conversion (``examples/unity/TactDeformSender.cs``), through its Python reference
:func:`tactdeform_hw.render.unity.unity_pad_pose`, against poses whose answer is known by hand: Unity's
left-handed, Y-up metres into the package's right-handed, Z-up millimetres."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from tactdeform_hw.render.live import parse_sample
from tactdeform_hw.render.tracking import quat_to_matrix
from tactdeform_hw.render.unity import unity_line, unity_pad_pose

CS = Path(__file__).resolve().parents[1] / "examples" / "unity" / "TactDeformSender.cs"


def axes(q: tuple[float, ...]) -> np.ndarray:
    return quat_to_matrix(q)


def test_position_metres_to_millimetres_y_and_z_swapped_from_the_anchor() -> None:
    s = unity_pad_pose(2.5, (0.1, 1.2, 0.3), (0, 0, 1), (0, -1, 0), anchor_m=(0.0, 1.0, 0.0))
    assert s[:4] == pytest.approx((2.5, 100.0, 300.0, 200.0))


def test_finger_forward_pad_down() -> None:
    # Unity: the finger points forward (+z), the pad faces the floor (-y).  Package: the tip along +y, the
    # pad out along -z (down), and its right y × z = -x.
    s = unity_pad_pose(0.0, (0.0, 0.5, 0.4), (0, 0, 1), (0, -1, 0))
    m = axes(s[4:])
    assert m[:, 0] == pytest.approx([-1, 0, 0], abs=1e-12)
    assert m[:, 1] == pytest.approx([0, 1, 0], abs=1e-12)
    assert m[:, 2] == pytest.approx([0, 0, -1], abs=1e-12)
    # a half turn about y: (w, x, y, z) = (0, 0, 1, 0)
    assert [abs(c) for c in s[4:]] == pytest.approx([0, 0, 1, 0], abs=1e-12)


def test_finger_to_the_right_pad_forward_is_a_third_turn() -> None:
    # Unity: tip toward +x, pad facing forward (+z).  Package: y = (1,0,0), z = (0,1,0), x = y × z = (0,0,1):
    # the rotation x→z, y→x, z→y is -120° about (1,1,1): (w, x, y, z) = (1/2, -1/2, -1/2, -1/2).
    s = unity_pad_pose(0.0, (1.0, 0.0, 0.0), (1, 0, 0), (0, 0, 1))
    assert s[4:] == pytest.approx((0.5, -0.5, -0.5, -0.5), abs=1e-12)


def test_tilted_normal_is_made_perpendicular_and_frame_is_right_handed() -> None:
    rng = np.random.default_rng(3)
    for _ in range(50):
        tip = rng.normal(size=3)
        normal = rng.normal(size=3)
        s = unity_pad_pose(0.0, (0.2, 0.3, 0.4), tip, normal)
        m = axes(s[4:])
        assert np.linalg.det(m) == pytest.approx(1.0)
        y_expected = np.array([tip[0], tip[2], tip[1]]) / np.linalg.norm(tip)
        assert m[:, 1] == pytest.approx(y_expected)
        n = np.array([normal[0], normal[2], normal[1]])
        assert float(np.dot(m[:, 2], n)) > 0  # the pad still faces the way Unity said
        assert math.isclose(sum(c * c for c in s[4:]), 1.0)


def test_the_sent_line_is_a_valid_sample_and_a_metres_sender_is_caught() -> None:
    s = unity_pad_pose(1.0, (0.1, 1.2, 0.3), (0, 0, 1), (0, -1, 0))
    got = parse_sample(unity_line(s).encode(), 0.0)
    assert not isinstance(got, str) and got.position_mm == pytest.approx((100.0, 300.0, 1200.0))
    forgot = (s[0], 0.1, 0.3, 1.2, *s[4:])  # the factor 1000 left out
    assert parse_sample(unity_line(forgot).encode(), 0.0) == "metres"


def test_the_csharp_sender_does_the_same_conversion() -> None:
    text = CS.read_text(encoding="utf-8")
    assert "(fingertip.position - anchor) * 1000f" in text
    assert "Vector3.Cross(normal, tip)" in text
    assert "{ right.x, right.z, right.y }" in text and "{ tip.x, tip.z, tip.y }" in text
    assert "((double)p.x)" in text and text.index("((double)p.z)") < text.index("((double)p.y)")
