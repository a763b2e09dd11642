"""TUM / KITTI trajectory text: exact round trips and clear errors on malformed rows."""
import numpy as np
import pytest

from common.geometry import make_transform, so3_exp
from common.trajectory import (TrajectoryFormatError, format_kitti, format_tum, parse_kitti, parse_tum,
                               read_kitti, read_tum, write_kitti, write_tum)


def _random_traj(n=20, seed=1):
    rng = np.random.default_rng(seed)
    stamps = np.cumsum(rng.integers(1, 10**8, n)).astype(np.int64) + 1_700_000_000_123_456_789
    poses = np.stack([make_transform(so3_exp(rng.normal(size=3)), rng.normal(size=3) * 10) for _ in range(n)])
    return stamps, poses


def test_tum_round_trip_is_exact_for_stamps_and_tight_for_poses(tmp_path):
    stamps, poses = _random_traj()
    path = tmp_path / "traj.txt"
    write_tum(path, stamps, poses)
    s2, p2 = read_tum(path)
    np.testing.assert_array_equal(s2, stamps)
    np.testing.assert_allclose(p2, poses, atol=1e-8)


def test_kitti_round_trip(tmp_path):
    _, poses = _random_traj()
    path = tmp_path / "traj.kitti"
    write_kitti(path, poses)
    np.testing.assert_allclose(read_kitti(path), poses, atol=1e-8)


def test_tum_skips_comments_and_accepts_commas():
    text = "# timestamp tx ty tz qx qy qz qw\n\n1.5,1,2,3,0,0,0,1\n"
    stamps, poses = parse_tum(text)
    assert stamps.tolist() == [1_500_000_000]
    np.testing.assert_allclose(poses[0][:3, 3], [1, 2, 3])


def test_tum_wrong_column_count_names_file_and_line(tmp_path):
    path = tmp_path / "bad.txt"
    path.write_text("0.0 0 0 0 0 0 0 1\n1.0 0 0 0 0 0 1\n")
    with pytest.raises(TrajectoryFormatError, match=r"bad\.txt:2: .*8 columns.*got 7"):
        read_tum(path)


def test_tum_non_numeric_and_zero_quaternion_rejected():
    with pytest.raises(TrajectoryFormatError, match="non-numeric"):
        parse_tum("0.0 0 0 x 0 0 0 1\n")
    with pytest.raises(TrajectoryFormatError, match="timestamp"):
        parse_tum("abc 0 0 0 0 0 0 1\n")
    with pytest.raises(TrajectoryFormatError, match="zero norm"):
        parse_tum("0.0 0 0 0 0 0 0 0\n")


def test_kitti_errors():
    with pytest.raises(TrajectoryFormatError, match="12 columns"):
        parse_kitti("1 0 0 0 0 1 0 0 0 0 1\n")
    with pytest.raises(TrajectoryFormatError, match="rotation"):
        parse_kitti("2 0 0 0 0 1 0 0 0 0 1 0\n")


def test_bad_arrays_rejected():
    stamps, poses = _random_traj(3)
    with pytest.raises(TrajectoryFormatError, match="one stamp per pose"):
        format_tum(stamps[:2], poses)
    with pytest.raises(TrajectoryFormatError, match="integer nanoseconds"):
        format_tum(stamps.astype(float), poses)
    with pytest.raises(TrajectoryFormatError, match=r"\(N, 4, 4\)"):
        format_kitti(poses[:, :3, :])
