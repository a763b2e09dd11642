import numpy as np

from common.geometry import planar_pose
from common.pose_buffer import PoseBuffer


def test_interpolates_translation_and_heading_and_refuses_bad_input():
    buf = PoseBuffer(max_extrapolation_ns=100)
    assert buf.at(5) is None
    assert buf.add(0, planar_pose(0, 0, 0))
    assert buf.add(1000, planar_pose(2, 0, 1.0))
    assert not buf.add(500, planar_pose(9, 9, 0))          # out of order
    assert not buf.add(2000, np.full((4, 4), np.nan))       # NaN
    T = buf.at(250)
    assert np.allclose(T[:3, 3], [0.5, 0, 0])
    assert np.isclose(np.arctan2(T[1, 0], T[0, 0]), 0.25)
    assert np.allclose(buf.at(1050), planar_pose(2, 0, 1.0))  # small extrapolation: nearest end
    assert buf.at(5000) is None                                # too far
