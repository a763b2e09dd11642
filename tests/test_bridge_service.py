"""The bridge as a real process on a unique Zenoh port: messages in, SIGTERM, a verified .rrd out."""
from __future__ import annotations

import socket
import subprocess
import time

import numpy as np

from common.bus import BusOptions, Node
from common.messages import Heartbeat
from common.viz import paths as P
from tests import bridge_scene
from tests.bridge_scene import rrd_rows, trajectory_points
from tests.conftest import free_port
from tests.helpers import ROOT, hub, start_module, stop, wait_until

RERUN = ROOT / ".venv" / "bin" / "rerun"
LATCHED = ("stereo/calibration", "slam/map", "planner/target")


def _bridge_progress(node: Node):
    """A callable returning the bridge's last reported progress (messages logged)."""
    last = {"progress": -1}

    def on_heartbeat(hb: Heartbeat):
        if hb.service == "bridge":
            last["progress"] = hb.progress

    node.subscribe("status/bridge", Heartbeat, on_heartbeat)
    return lambda: last["progress"]


def _publish_scene(node: Node, frames: int, skip=()):
    """Publish the synthetic scene at ~20 Hz; returns how many messages went out."""
    pubs, n = {}, 0
    for stream, msg in bridge_scene.messages(frames=frames, flies=1500):
        if stream.startswith("status/") or stream in skip:
            continue
        if stream not in pubs:
            pubs[stream] = node.publisher(stream, latched=stream in LATCHED)
        pubs[stream].publish(msg)
        n += 1
        if stream == "planner/cmd_vel":
            time.sleep(0.05)
    return n


def _verify(path):
    result = subprocess.run([str(RERUN), "rrd", "verify", str(path)], capture_output=True, text=True, timeout=60)
    assert result.returncode == 0, result.stdout + result.stderr


def test_bridge_logs_the_bus_live_and_to_a_file_that_verifies_after_sigterm(zenoh_port, tmp_path):
    rrd, grpc_port = tmp_path / "run.rrd", free_port()
    proc = start_module("services.bridge", "--rrd", str(rrd), "--grpc-port", str(grpc_port), "--web-port", "0",
                        "--map-period-s", "0.5", port=zenoh_port, log_path=tmp_path / "bridge.log")
    try:
        opts = BusOptions(hub=hub(zenoh_port))
        with Node("watcher", opts, handle_signals=False) as watcher:
            progress = _bridge_progress(watcher)
            assert wait_until(lambda: progress() >= 0, 20), "the bridge never sent a heartbeat"
            # The live server listens on loopback while the bridge runs.
            with socket.create_connection(("127.0.0.1", grpc_port), timeout=2):
                pass
            with Node("feeder", opts, handle_signals=False) as node:
                _publish_scene(node, frames=20)
                # Every pose/command arrives by callback (4 poses + 1 command per frame), the map by query.
                assert wait_until(lambda: progress() >= 20 * 5, 15), f"bridge progress {progress()}"
                time.sleep(1.0)  # another map query
            time.sleep(1.0)  # the feeder's liveliness token is withdrawn; the bridge should log that
            assert stop(proc) == 0
    finally:
        stop(proc)
    _verify(rrd)
    rows = rrd_rows(rrd)
    for entity in (P.LEFT, P.RIGHT, P.FLIES, P.LEFT_FLIES, P.ROBOT, P.MAP_POINTS, P.FIELD, P.TARGET_3D, P.SONAR_POINTS,
                   f"{P.CMD}/linear_mps", f"{P.PROGRESS}/feeder", f"{P.ALIVE}/feeder",
                   *(P.trajectory_segment_path(s, 0) for s in P.TRAJECTORY_STYLE)):
        assert f"/{entity}" in rows, f"{entity} missing from the .rrd"
    assert rows[f"/{P.LEFT}"]["static:Pinhole:resolution"], "calibration logged as a static Pinhole"
    assert 1 <= len(rows[f"/{P.LEFT}"]["EncodedImage:blob"]) <= 20
    assert len(trajectory_points(rows, "truth/pose")) == 20, "every truth pose reached the trajectory"
    assert [v[0] for v in rows[f"/{P.ALIVE}/feeder"]["Scalars:scalars"]][-1] == 0.0, "the feeder left"
    cloud = np.array(rows[f"/{P.MAP_POINTS}"]["Points3D:positions"][-1])
    assert np.allclose(cloud[:, 0], bridge_scene.WALL_X, atol=1e-4)


def test_a_busy_live_port_still_gives_a_complete_file(zenoh_port, tmp_path):
    rrd = tmp_path / "run.rrd"
    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen()
        proc = start_module("services.bridge", "--rrd", str(rrd), "--grpc-port", str(busy.getsockname()[1]),
                            "--web-port", "0", port=zenoh_port, log_path=tmp_path / "bridge.log")
        try:
            with Node("feeder", BusOptions(hub=hub(zenoh_port)), handle_signals=False) as node:
                progress = _bridge_progress(node)
                assert wait_until(lambda: progress() >= 0, 20), "the bridge never sent a heartbeat"
                _publish_scene(node, frames=6, skip=("slam/map",))
                assert wait_until(lambda: progress() >= 6 * 5, 15), f"bridge progress {progress()}"
            assert stop(proc) == 0
        finally:
            stop(proc)
    assert "busy" in (tmp_path / "bridge.log").read_text()
    _verify(rrd)
    assert f"/{P.FLIES}" in rrd_rows(rrd)


def test_a_pose_flood_is_thinned_on_arrival_to_exactly_what_the_viewer_logs():
    """1,000 fused poses in one second of sensor time, with status flips, rejections and a stamp going
    back: the bridge's inbox gets ~30 of them (a stalled main loop cannot fill memory with the rest),
    and the viewer logs the same robot poses and events from those as from all 1,000."""
    from common import messages as m
    from common.bus import Counters
    from common.viz import RerunLogger
    from services.bridge import Inbox, PoseThinning

    class Spy:
        """A RecordingStream stand-in noting the robot transforms and events logged."""
        def __init__(self):
            self.logged = []

        def log(self, path, *args, **kwargs):
            if path in (P.ROBOT, P.EVENTS) and not kwargs.get("static"):
                self.logged.append((path, self.t))

        def set_time(self, timeline, **kwargs):
            self.t = kwargs.get("timestamp", kwargs.get("sequence"))

        def disable_timeline(self, timeline):
            pass

    class _Node:
        counters = Counters()

    def poses():
        for i in range(1000):
            T = np.eye(4)
            T[0, 3] = i * 1e-3
            msg = m.pose_msg(T, seq=i + 1, stamp_ns=10**9 + (i if i != 700 else 650) * 10**6)
            msg.status = ("odometry only" if i in (500, 510) else "rejected: jump" if 800 <= i < 805 else "ok")
            yield msg

    everything, thinned = Spy(), Spy()
    all_logger, thin_logger = RerunLogger(everything), RerunLogger(thinned)
    inbox, thinning = Inbox(_Node()), PoseThinning(1 / 30)
    for msg in poses():
        all_logger.handle("fusion/pose", msg)
        if thinning.keep("fusion/pose", msg):
            inbox.put("fusion/pose", msg)
    queued = [msg for _, msg in inbox.drain()]
    for msg in queued:
        thin_logger.handle("fusion/pose", msg)
    assert len(queued) < 60
    assert thinned.logged == everything.logged
    assert sum(path == P.ROBOT for path, _ in everything.logged) >= 28
