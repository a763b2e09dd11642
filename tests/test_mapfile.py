"""The fly map on disk: exact round trip (with the localiser's and the pose graph's own types), a saved
graph rebuilds the same trajectory, and a damaged file is one MapFileError line, never another exception."""
from __future__ import annotations

import numpy as np
import pytest

from common import messages as m
from common.geometry import invert, make_transform, planar_pose, so3_exp
from common.recording import RecordingReader, RecordingWriter
from common.slam import Keyframe
from common.slam.mapfile import GRAPH_KEY, KEYFRAMES_KEY, MapEdge, MapFileError, load_map, save_map
from common.slam.posegraph import PoseGraph, planar_covariance


def sample_map(n: int = 5, seed: int = 0):
    rng = np.random.default_rng(seed)
    kfs = []
    for i in range(n):
        T = make_transform(so3_exp(rng.normal(0, 0.5, 3)), rng.normal(0, 3.0, 3))
        k = int(rng.integers(50, 300))
        kfs.append(Keyframe(10 + i, 1_700_000_000_000_000_000 + i * 10**8, T,
                            rng.normal(0, 2.0, (k, 3)).astype(np.float32), rng.random(k).astype(np.float32)))
    kfs[1].image = rng.integers(0, 256, (12, 20), dtype=np.uint8)   # a camera-only keyframe's half image
    cov = np.diag(rng.random(6) + 0.1) * 1e-3
    edges = [MapEdge(kfs[0].id, kfs[0].id, kfs[0].T_map_base, np.eye(6) * 1e-4, "prior", False)]
    for a, b in zip(kfs[:-1], kfs[1:]):
        edges.append(MapEdge(a.id, b.id, invert(a.T_map_base) @ b.T_map_base, cov, "odometry", True))
    edges.append(MapEdge(kfs[0].id, kfs[-1].id, invert(kfs[0].T_map_base) @ kfs[-1].T_map_base, cov * 2,
                         "registration", True))
    return kfs, edges


def test_round_trip_is_exact(tmp_path):
    kfs, edges = sample_map()
    meta = {"robot": "sim", "keyframe_distance_m": 1.5, "nested": {"a": [1, 2]}}
    path = save_map(tmp_path / "map.mcap", kfs, edges, meta)
    assert path == tmp_path / "map.mcap" and not (tmp_path / "map.mcap.tmp").exists()
    data = load_map(path)
    assert data.meta == meta
    assert [k.id for k in data.keyframes] == [k.id for k in kfs]
    for a, b in zip(kfs, data.keyframes):
        assert b.stamp_ns == a.stamp_ns
        assert b.points.dtype == np.float32 and np.array_equal(b.points, a.points)
        assert b.fitness.dtype == np.float32 and np.array_equal(b.fitness, a.fitness)
        np.testing.assert_allclose(b.T_map_base, a.T_map_base, rtol=0, atol=1e-14)   # via a quaternion
        assert (b.image is None) == (a.image is None) and (a.image is None or np.array_equal(b.image, a.image))
    assert len(data.edges) == len(edges)
    for a, b in zip(edges, data.edges):
        assert (b.i, b.j, b.kind, b.robust) == (a.i, a.j, a.kind, a.robust)
        assert np.array_equal(b.cov, a.cov)
        np.testing.assert_allclose(b.T_i_j, a.T_i_j, rtol=0, atol=1e-14)
    # The keyframes are the bus's FlyMap schema: tools that read slam/map read this file too.
    msgs = list(RecordingReader(path).messages(keys={KEYFRAMES_KEY}))
    assert all(r.schema == m.FlyMap.SCHEMA for r in msgs) and len(msgs) == len(kfs)
    # An edge is a PoseEstimate of keyframe j in keyframe i (a prior: in the map).
    graph = [m.decode(r.payload) for r in RecordingReader(path).messages(keys={GRAPH_KEY})]
    assert [type(g) for g in graph] == [m.PoseEstimate] * len(edges)
    assert (graph[1].header.frame_id, graph[1].child_frame_id) == (f"keyframe/{kfs[0].id}", f"keyframe/{kfs[1].id}")
    assert graph[0].header.frame_id == m.MAP and graph[0].status == "prior quadratic"


def test_saved_pose_graph_rebuilds_the_same_trajectory(tmp_path):
    cov = planar_covariance(np.diag([0.05, 0.05, 0.02]) ** 2)
    g = PoseGraph(planar=True)
    truth = [planar_pose(2.0 * i, 0.3 * i, 0.1 * i) for i in range(6)]
    for i, T in enumerate(truth):
        g.add_keyframe(i, T @ planar_pose(0.1, -0.05, 0.02))
    g.add_prior(0, truth[0], np.eye(6) * 1e-6)
    for i in range(5):
        g.add_odometry(i, i + 1, invert(truth[i]) @ truth[i + 1] @ planar_pose(0.02, 0, 0.01), cov)
    g.add_registration(0, 5, invert(truth[0]) @ truth[5], cov)
    g.optimise()
    pts = np.zeros((4, 3), np.float32)
    kfs = [Keyframe(i, i, T, pts, np.ones(4, np.float32)) for i, T in g.poses().items()]
    save_map(tmp_path / "map.mcap", kfs, g.edges())          # the dict PoseGraph.edges() returns
    data = load_map(tmp_path / "map.mcap")
    h = PoseGraph(planar=True)
    for kf in data.keyframes:
        h.add_keyframe(kf.id, kf.T_map_base)
    for e in data.edges:
        h.add_edge(e)
    h.optimise()
    for i, T in g.poses().items():
        assert np.abs(h.pose(i) - T).max() < 1e-4     # both converged (iSAM2 stops at a relative tol)


def assert_one_line_error(path, match=None):
    with pytest.raises(MapFileError) as info:
        load_map(path)
    text = str(info.value)
    assert text and "\n" not in text
    if match:
        assert match in text
    return text


def test_truncated_and_corrupt_files_are_one_map_file_error(tmp_path):
    kfs, edges = sample_map(n=3)
    good = save_map(tmp_path / "map.mcap", kfs, edges, {"x": 1}).read_bytes()
    reference = load_map(tmp_path / "map.mcap")
    bad = tmp_path / "bad.mcap"
    for cut in (0, 5, 8, 100, len(good) // 2, len(good) - 40, len(good) - 1):
        bad.write_bytes(good[:cut])
        assert_one_line_error(bad)
    assert_one_line_error(tmp_path / "missing.mcap", "no such")
    bad.write_bytes(b"not a map at all, just text\n" * 10)
    assert_one_line_error(bad, "not an MCAP")
    # Any flipped byte: the same map or the error, never another exception, never a different map.
    rng = np.random.default_rng(1)
    errors = 0
    for pos in rng.choice(len(good), size=150, replace=False):
        damaged = bytearray(good)
        damaged[pos] ^= 0x5A
        bad.write_bytes(bytes(damaged))
        try:
            data = load_map(bad)
        except MapFileError as e:
            assert "\n" not in str(e)
            errors += 1
            continue
        assert data.meta == reference.meta and len(data.keyframes) == len(reference.keyframes)
        for a, b in zip(reference.keyframes, data.keyframes):
            assert a.id == b.id and np.array_equal(a.points, b.points) and np.array_equal(a.T_map_base, b.T_map_base)
        assert all(np.array_equal(a.T_i_j, b.T_i_j) and a.kind == b.kind for a, b in zip(reference.edges, data.edges))
    assert errors > 50


def test_a_recording_that_is_not_a_map_is_refused(tmp_path):
    path = tmp_path / "run.mcap"
    with RecordingWriter(path) as w:
        w.write("rig/target", m.encode(m.Target(x=1.0, header=m.header(0, 5, m.MAP))), 5)
    assert_one_line_error(path, "not a flyslam map")


def test_bad_input_to_save_is_an_error_and_keeps_the_previous_map(tmp_path):
    kfs, edges = sample_map(n=3)
    path = save_map(tmp_path / "map.mcap", kfs, edges)
    before = path.read_bytes()
    broken = [Keyframe(kfs[0].id, 0, np.eye(4), np.zeros((3, 3), np.float32), np.zeros(2, np.float32))]
    cases = [
        (broken, []),                                                         # fitness length
        (kfs + kfs[:1], edges),                                               # duplicate id
        (kfs, edges + [MapEdge(0, 999, np.eye(4), np.eye(6), "odometry")]),   # unknown keyframe
        (kfs, [MapEdge(kfs[0].id, kfs[1].id, np.eye(4), np.eye(6), "gps")]),  # unknown kind
        (kfs, [(0, 1)]),                                                      # not an edge
        (kfs, [MapEdge(kfs[0].id, kfs[1].id, np.eye(4), np.eye(6), "prior")]),  # a prior between two
    ]
    for k, e in cases:
        with pytest.raises(MapFileError):
            save_map(path, k, e)
    with pytest.raises(MapFileError, match="JSON"):
        save_map(path, kfs, edges, {"bad": object()})
    assert path.read_bytes() == before
    assert load_map(path).edges[-1].kind == "registration"
