"""The frame chain of a real trial, in one place.

    base <- tcp (arm forward kinematics) <- cam (hand-eye) <- tag (AprilTag pose) <- object (registry)

and the table frame, defined by a table tag: ``T_base_table = T_base_cam @ T_cam_table``. Every
transform is ``T_parent_child`` (4x4, metres); functions are batch-first over leading dims.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from calibration.io import check_T
from sim.geometry import compose, invert_T

__all__ = ["T_base_cam", "T_base_object", "T_table_base", "FrameChain"]


def T_base_cam(T_base_tcp, T_tcp_cam) -> np.ndarray:
    """``(..., 4, 4)`` camera pose in the robot base frame."""
    return compose(T_base_tcp, T_tcp_cam)


def T_base_object(T_base_tcp, T_tcp_cam, T_cam_tag, T_tag_object) -> np.ndarray:
    """``(..., 4, 4)`` object pose in the base frame through the whole chain."""
    return compose(T_base_tcp, T_tcp_cam, T_cam_tag, T_tag_object)


def T_table_base(T_base_tcp, T_tcp_cam, T_cam_table) -> np.ndarray:
    """``(..., 4, 4)`` robot base pose in the table (world) frame, from one sighting of the table frame."""
    return invert_T(compose(T_base_tcp, T_tcp_cam, T_cam_table))


@dataclass(frozen=True)
class FrameChain:
    """The fixed links of a real setup: hand-eye ``T_tcp_cam`` and (once seen) ``T_base_table``.

    With the arm's ``T_base_tcp`` at the moment of an image, camera-frame measurements map to the
    base or table frame.
    """

    T_tcp_cam: np.ndarray
    T_base_table: np.ndarray | None = None

    def __post_init__(self):
        object.__setattr__(self, "T_tcp_cam", check_T(self.T_tcp_cam, "T_tcp_cam"))
        if self.T_base_table is not None:
            object.__setattr__(self, "T_base_table", check_T(self.T_base_table, "T_base_table"))

    def T_base_cam(self, T_base_tcp) -> np.ndarray:
        return T_base_cam(check_T(T_base_tcp, "T_base_tcp"), self.T_tcp_cam)

    def to_base(self, T_base_tcp, T_cam_x) -> np.ndarray:
        """``T_base_x`` of something the camera saw at arm pose ``T_base_tcp``."""
        return compose(self.T_base_cam(T_base_tcp), T_cam_x)

    def points_to_base(self, T_base_tcp, points_cam) -> np.ndarray:
        """Camera-frame points ``(..., 3)`` m -> base frame."""
        T = self.T_base_cam(T_base_tcp)
        p = np.asarray(points_cam, dtype=np.float64)
        return p @ T[:3, :3].T + T[:3, 3]

    def with_table(self, T_base_tcp, T_cam_table) -> "FrameChain":
        """This chain with the table frame fixed from one sighting of the table tag(s)."""
        return FrameChain(self.T_tcp_cam, self.to_base(T_base_tcp, check_T(T_cam_table, "T_cam_table")))

    def points_to_table(self, points_base) -> np.ndarray:
        """Base-frame points ``(..., 3)`` -> table frame; needs ``T_base_table``."""
        if self.T_base_table is None:
            raise ValueError("T_base_table: unknown; the table tag has not been seen (use with_table)")
        T = invert_T(self.T_base_table)
        return np.asarray(points_base, dtype=np.float64) @ T[:3, :3].T + T[:3, 3]
