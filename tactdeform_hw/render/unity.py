"""Unity's hand tracking in the package's frame: the reference of ``examples/unity/TactDeformSender.cs``.

Unity's world is left-handed, Y up, in metres.  The package's world is right-handed, in millimetres, with
z up (the scenes' and the CSV's frame).  Swapping Unity's Y and Z turns one into the other — a mirror, so
handedness flips as it must — and the unit is 1000:

    x_mm = 1000 (x_u − anchor_x),  y_mm = 1000 (z_u − anchor_z),  z_mm = 1000 (y_u − anchor_y)

where the anchor is the Unity position of the scene's origin (the virtual object's placement), so poses
land where the scene's objects are.  The pad frame is built from two Unity directions of the fingertip —
toward the tip and out of the pad — each swapped the same way; the pad's right is y × z in the package's
frame, which is ``Vector3.Cross(padNormal, tipDirection)`` in Unity's numbers (a mirror reverses the cross
product).  A quaternion cannot be carried over by swapping its components alone, so the sender sends the
quaternion of those three axes, computed on the package's side of the mirror.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from .tracking import matrix_to_quat


def unity_vector(v: Sequence[float] | np.ndarray) -> np.ndarray:
    """A Unity direction in the package's axes (Y and Z swapped)."""
    return np.array([float(v[0]), float(v[2]), float(v[1])])


def unity_pad_pose(
    t_s: float,
    position_m: Sequence[float],
    tip_direction: Sequence[float],
    pad_normal: Sequence[float],
    anchor_m: Sequence[float] = (0.0, 0.0, 0.0),
) -> tuple[float, float, float, float, float, float, float, float]:
    """The sample the Unity sender sends for a fingertip pad at ``position_m`` (Unity world metres), pointing
    along ``tip_direction`` with its pad facing ``pad_normal`` (Unity world directions; need not be unit or
    exactly perpendicular: the normal is made perpendicular to the tip direction, as the sender does):
    ``(t_s, x_mm, y_mm, z_mm, qw, qx, qy, qz)``."""
    p = 1000.0 * unity_vector(np.subtract(position_m, anchor_m))
    y = unity_vector(tip_direction)
    y /= np.linalg.norm(y)
    z = unity_vector(pad_normal)
    z = z - np.dot(z, y) * y
    z /= np.linalg.norm(z)
    x = np.cross(y, z)
    q = matrix_to_quat(np.column_stack([x, y, z]))
    if q[0] < 0:
        q = -q
    return (float(t_s), float(p[0]), float(p[1]), float(p[2]), *(float(c) for c in q))  # type: ignore[return-value]


def unity_line(sample: Sequence[float]) -> str:
    """The datagram text of one sample, as the sender formats it (invariant culture, ``R`` precision)."""
    return ",".join(repr(float(v)) for v in sample)
