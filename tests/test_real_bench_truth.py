"""bench/real.py names the stretches where the ground truth disagrees with every method while the methods
agree with each other (KITTI 00 starts with a constant 0.860 m/frame that no visual method sees)."""
import numpy as np

from bench.real import disputed_truth


def straight(steps):
    poses = [np.eye(4)]
    for s in steps:
        T = poses[-1].copy()
        T[0, 3] += s
        poses.append(T)
    return poses


def test_a_stretch_where_both_methods_agree_against_the_truth_is_named():
    stamps = np.arange(12) * 100_000_000
    truth = np.array(straight([1.0] * 11))
    both_short = straight([0.8] * 5 + [1.0] * 6)
    tracks = {"a": (stamps, both_short), "b": (stamps, straight([0.81] * 5 + [1.0] * 6))}
    assert disputed_truth(stamps, truth, tracks) == [[1, 5, 1.0, 0.805]]


def test_methods_that_disagree_with_each_other_dispute_nothing():
    stamps = np.arange(12) * 100_000_000
    truth = np.array(straight([1.0] * 11))
    tracks = {"a": (stamps, straight([0.8] * 11)), "b": (stamps, straight([1.2] * 11))}
    assert disputed_truth(stamps, truth, tracks) == []
