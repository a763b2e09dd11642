"""The localiser as a process: poses and map->odom from populations, the map on request, TUM on exit."""
from __future__ import annotations

import time

import numpy as np

from common import messages as m
from common.bus import BusOptions, Node
from common.camera import StereoCalibration
from common.geometry import planar_pose
from common.trajectory import read_tum
from tests.helpers import hub, resend_until, start_module, stop, wait_until
from tests.test_slam import T_BASE_CAMERA, corridor_points, seen_from


def test_localiser_service_publishes_poses_serves_its_map_and_writes_tum(tmp_path, zenoh_port):
    tum = tmp_path / "estimated.tum"
    proc = start_module("services.localiser", "--tum", str(tum), port=zenoh_port, log_path=tmp_path / "loc.log")
    rng = np.random.default_rng(2)
    world = corridor_points(rng, 40000, length=25.0)
    calib = StereoCalibration.ideal(320, 240, T_base_camera=T_BASE_CAMERA)
    poses, transforms = [], []
    try:
        with Node("feeder", BusOptions(hub=hub(zenoh_port)), handle_signals=False) as node:
            node.subscribe("slam/pose", m.PoseEstimate, poses.append)
            node.subscribe("slam/map_to_odom", m.TransformMsg, transforms.append)
            node.publisher("stereo/calibration", latched=True).publish(m.calibration_to_msg(calib, 1, 1))
            pops = node.publisher("flies/population/@image", reliable=True)
            time.sleep(1.5)
            for k in range(8):
                T_odom_base = planar_pose(0.6 * k, 0.0, 0.0)
                cam = seen_from(T_odom_base, world).astype(np.float32)
                pop = m.FlyPopulation(positions=cam, fitness=np.ones(len(cam), np.float32), generation=500,
                                      source_seq=k + 1, T_odom_camera=T_odom_base @ T_BASE_CAMERA,
                                      header=m.header(0, (k + 1) * 10**8, m.CAMERA_LEFT_OPTICAL))
                if k == 0:
                    # A localiser still starting (loading its kernels, asking for the calibration) drops
                    # what comes meanwhile, as it would a camera's frames: the first population again
                    # until it answers (a repeat of one it has localised is ignored).
                    assert resend_until(lambda: pops.publish(pop), lambda: bool(poses), every=0.5), \
                        (tmp_path / "loc.log").read_text()[-2000:]
                else:
                    pops.publish(pop)
                assert wait_until(lambda: len(poses) >= k + 1, 30), (tmp_path / "loc.log").read_text()[-2000:]
            fly_map = node.query_latest("slam/map", m.FlyMap, timeout=5.0)
    finally:
        assert stop(proc) == 0
    assert [p.source_seq for p in poses] == list(range(1, 9))
    assert poses[0].status == "initialised" and poses[0].header.frame_id == "map"
    assert sum(p.status == "ok" for p in poses) >= 5, [p.status for p in poses]
    final = m.transform_of(poses[-1])
    assert abs(final[0, 3] - 4.2) < 0.1 and abs(final[1, 3]) < 0.05
    assert transforms and transforms[-1].child_frame_id == "odom"
    assert fly_map is not None and len(fly_map.keyframes) >= 2
    assert all(len(kf.points) > 100 for kf in fly_map.keyframes)
    stamps, traj = read_tum(tum)
    assert len(stamps) == 8 and np.allclose(traj[-1][:3, 3], final[:3, 3], atol=1e-6)
