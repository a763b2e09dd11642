"""A localiser killed with SIGKILL and started again keeps every pose it had written, picks up the map
it saved in the run folder and, near the map->odom the bus still latches, publishes poses again at
once and in the right place."""
from __future__ import annotations

import threading
import time

import numpy as np

from common import messages as m
from common.bus import BusOptions, Node
from common.geometry import planar_pose
from common.trajectory import read_tum
from common.slam.standin import LOADING_STATUS, StandInCore
from tests.helpers import hub, start_module, stop, wait_until
from tests.test_relocalise import CALIB, corridor, population


def test_a_killed_localiser_keeps_its_trajectory_and_map_and_resumes_at_once(tmp_path, zenoh_port):
    tum, saved = tmp_path / "estimated.tum", tmp_path / "map.mcap"
    args = ("--tum", str(tum), "--map-period-s", "0.3", "--tum-period-s", "0.5")
    rng = np.random.default_rng(3)
    world = corridor(rng)
    poses, lock = [], threading.Lock()
    step, seq = [0], [0]
    odom_offset = planar_pose(5.0, 2.0, 0.3)
    where = {}              # seq -> step: where the robot was

    def truth(k):
        return planar_pose(1.0 + 0.1 * k, 0.05, 0.02)

    def feed(pops, advance=True):
        k = step[0]
        seq[0] += 1
        where[seq[0]] = k
        pops.publish(population(truth(k), world, rng, seq[0], 10**9 + seq[0] * 10**8,
                                odom_offset @ planar_pose(0.1 * k, 0.0, 0.0)))
        step[0] += int(advance)

    with Node("feeder", BusOptions(hub=hub(zenoh_port)), handle_signals=False) as node:
        node.hold_latched("slam/map_to_odom")     # as the supervisor does for its launch file's latch streams
        node.subscribe("slam/pose", m.PoseEstimate, lambda p: (lock.acquire(), poses.append((time.monotonic(), p)),
                                                               lock.release()))
        node.publisher("stereo/calibration", latched=True).publish(m.calibration_to_msg(CALIB, 1, 1))
        pops = node.publisher("flies/population/@image", reliable=True)
        proc = start_module("services.localiser", *args, port=zenoh_port, log_path=tmp_path / "loc1.log")
        try:
            deadline = time.monotonic() + 90
            while not (saved.exists() and len(poses) >= 20):      # (populations before it is up are lost)
                assert time.monotonic() < deadline, (tmp_path / "loc1.log").read_text()[-2000:]
                n = len(poses)
                feed(pops)
                wait_until(lambda: len(poses) > n, 5)
            proc.kill()
            proc.wait(10)
        finally:
            stop(proc)
        before = [p for _, p in poses]
        assert saved.exists() and not any(p.status.startswith("relocalising") for p in before)
        written_stamps, _ = read_tum(tum)
        assert len(written_stamps) == len(before)                  # nothing lost to the kill
        t_killed = time.monotonic()

        proc = start_module("services.localiser", *args, port=zenoh_port, log_path=tmp_path / "loc2.log",
                            restarts=1)
        try:
            n0 = len(poses)
            restarted = time.monotonic()

            feed(pops)                  # the robot moved on while its localiser was down ...
            feed(pops)

            def resumed():
                feed(pops, advance=False)   # ... and waits for it (a loaded machine takes seconds to start one)
                time.sleep(0.1)
                with lock:
                    return any(not p.status.startswith("relocalising") for _, p in poses[n0:])
            assert wait_until(resumed, 60, poll=0.0), ((tmp_path / "loc2.log").read_text()[-3000:],
                                                       [p.status for _, p in poses[n0:]][-5:])
            with lock:
                t_first, first = next((t, p) for t, p in poses[n0:] if not p.status.startswith("relocalising"))
            k_first = where[first.source_seq]
            for _ in range(5):
                feed(pops)
                time.sleep(0.1)
        finally:
            assert stop(proc) == 0, (tmp_path / "loc2.log").read_text()[-3000:]
    with lock:
        t_any, _ = poses[n0]
        loading = [p for _, p in poses[n0:] if p.status == LOADING_STATUS]
    print(f"\nrestart: first pose {t_any - restarted:.2f} s after the process started ({len(loading)} while "
          f"loading), first registered one {t_first - restarted:.2f} s ({t_first - t_killed:.2f} s after the kill), "
          f"status {first.status!r}")
    log = (tmp_path / "loc2.log").read_text()
    assert "continuing the run's map" in log and "near the latched map->odom" in log, log[-2000:]
    # the first pose after the restart is where the robot is in the run's map (its frame is the killed
    # run's: the last pose before the kill, moved on by the true motion since), not a fresh map's origin
    last = before[-1]
    expected = m.transform_of(last) @ np.linalg.inv(truth(where[last.source_seq])) @ truth(k_first)
    assert np.linalg.norm(m.transform_of(first)[:2, 3] - expected[:2, 3]) < 0.1, first.status
    for p in loading:       # while its code loaded it said where the latched map->odom and odometry put it
        at = m.transform_of(last) @ np.linalg.inv(truth(where[last.source_seq])) @ truth(where[p.source_seq])
        assert np.linalg.norm(m.transform_of(p)[:2, 3] - at[:2, 3]) < 0.1 and p.covariance[0, 0] >= 1e3
    stamps, traj = read_tum(tum)
    assert set(written_stamps) <= set(stamps.tolist())          # 100 % of the poses before the kill kept
    assert np.all(np.diff(stamps) > 0) and stamps[-1] > written_stamps[-1]
    after = stamps[stamps > written_stamps[-1]]
    assert len(after) >= 5 and first.header.stamp_ns in after


def test_a_fresh_start_sets_an_earlier_runs_files_aside_instead_of_continuing_them(tmp_path, monkeypatch):
    """`flyslam run --out` into an old run's folder: the new robot is not relocalised in the old map,
    and the old trajectory and map are kept beside the new ones."""
    from services.localiser import build_parser, set_aside_earlier_run, starting_map
    from common.config_args import config_from_args
    from common.slam.core import LocaliserServiceConfig
    from common.slam.mapfile import save_map
    from common.slam.localiser import Keyframe

    tum, saved = tmp_path / "estimated.tum", tmp_path / "map.mcap"
    tum.write_text("1.0 0 0 0 0 0 0 1\n")
    save_map(saved, [Keyframe(0, 1, np.eye(4), np.zeros((200, 3), np.float32), np.ones(200, np.float32))], [])
    run = config_from_args(LocaliserServiceConfig, build_parser().parse_args(["--tum", str(tum)]))
    monkeypatch.setenv("FLYSLAM_RESTARTS", "1")
    assert starting_map(run, saved)[1] is True                       # a restart continues the map
    monkeypatch.setenv("FLYSLAM_RESTARTS", "0")
    assert starting_map(run, saved) == (None, False)                 # a fresh start does not
    set_aside_earlier_run(tum, saved)
    assert not tum.exists() and not saved.exists()
    assert (tmp_path / "estimated.previous.tum").read_text().startswith("1.0")
    assert (tmp_path / "map.previous.mcap").exists()


def test_the_stand_in_publishes_the_latched_pose_moved_by_odometry_and_nothing_without_it():
    """While a restarted localiser's code loads: the pose map->odom · odometry gives, marked as
    relocalising with a covariance that fusion cannot mistake for a fix; nothing it cannot back."""
    hint, T_base_camera = planar_pose(5.0, 2.0, 0.3), CALIB.T_base_camera
    nothing = StandInCore(None)
    assert nothing.on_population(population(planar_pose(1, 0, 0), np.zeros((0, 3)), np.random.default_rng(0), 1, 10**9,
                                            planar_pose(1, 0, 0))) is None
    stand_in = StandInCore(hint)
    stand_in.on_calibration(m.calibration_to_msg(CALIB, 1, 1))
    odom = planar_pose(1.5, 0.2, 0.1)
    pop = m.FlyPopulation(positions=np.zeros((1, 3), np.float32), fitness=np.ones(1, np.float32), generation=10,
                          source_seq=7, T_odom_camera=odom @ T_base_camera, header=m.header(0, 2 * 10**9, m.CAMERA_LEFT_OPTICAL))
    pose = stand_in.on_population(pop)
    assert pose.status == LOADING_STATUS and pose.source_seq == 7 and pose.covariance[0, 0] >= 1e3
    np.testing.assert_allclose(m.transform_of(pose), hint @ odom, atol=1e-6)
    pop.T_odom_camera = None                          # no odometry on the population: the odometry stream's
    assert stand_in.on_population(pop) is None        # (none received yet: nothing to say)
    stand_in.on_odometry(2 * 10**9, odom)
    np.testing.assert_allclose(m.transform_of(stand_in.on_population(pop)), hint @ odom, atol=1e-6)
