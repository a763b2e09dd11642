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


def test_extrapolation_carries_the_motion_on_without_amplifying_a_close_pair():
    """Visual odometry only knows past frames: with extrapolate=True the newest pose is carried on at the
    velocity of the last readings; a reading 1 ms after the previous one does not multiply its noise."""
    import numpy as np
    from common.geometry import planar_from_transform, planar_pose
    from common.pose_buffer import PoseBuffer
    held = PoseBuffer(max_extrapolation_ns=10**9)
    moving = PoseBuffer(max_extrapolation_ns=10**9, extrapolate=True)
    for k in range(10):     # 1 m/s along x, 0.1 rad/s
        for b in (held, moving):
            b.add(k * 10**8, planar_pose(0.1 * k, 0.0, 0.01 * k))
    assert np.allclose(planar_from_transform(held.at(10**9)), (0.9, 0.0, 0.09))
    x, y, yaw = planar_from_transform(moving.at(10**9))
    assert abs(x - 1.0) < 1e-3 and abs(yaw - 0.10) < 1e-9
    moving.add(9 * 10**8 + 10**6, planar_pose(0.9 + 0.01, 0.005, 0.09))    # 1 ms later, 1 cm of noise
    x, y, _ = planar_from_transform(moving.at(10**9))
    assert abs(x - 1.0) < 0.03 and abs(y) < 0.02
    assert moving.at(3 * 10**9) is None       # beyond max_extrapolation_ns
