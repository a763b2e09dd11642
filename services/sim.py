"""Simulator service: a simulated robot in a scenario's world, publishing what a real robot publishes.

Publishes ``stereo/frame`` (rectified pair), ``stereo/calibration`` (latched, repeated every 2 s),
``odom/wheels``, ``sonar/scan``, ``truth/pose`` (base_link in map, at the camera rate), optionally
``truth/depth``, and the scenario's ``planner/target`` (latched). Stamps are wall-clock nanoseconds
(start time + simulated time), so latencies measured downstream are real.

Runs in real time (``--rate`` scales it); in closed loop (``--closed-loop``) it drives by the newest
``planner/cmd_vel``, stops the robot when commands stop arriving for ``--cmd-timeout`` seconds, and with
``--end-on-target S`` exits 0 once the planner has said 'target reached' for S seconds.
Writes the ground-truth trajectory as TUM text with ``--truth-tum``.
"""
from __future__ import annotations

import logging
import sys
import threading
import time

import numpy as np

from common import messages as m
from common.sim import Simulator, load_scenario
from common.sim.bus_messages import camera_messages, odometry_message, sonar_message, target_message
from common.sim.scenario import ScenarioError, scenario_path
from common.sim.sensors import OdometryReading, SonarReading
from common.sim.simulator import CameraDue
from common.trajectory import write_tum
from services.base import run_service, service_parser

log = logging.getLogger("flyslam.sim")


def build_parser():
    p = service_parser("sim", __doc__.splitlines()[0])
    p.add_argument("--scenario", default="corridor", help="scenario name in recordings/scenarios/ or a TOML path")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--width", type=int, default=None, help="override the scenario's image width")
    p.add_argument("--height", type=int, default=None, help="override the scenario's image height")
    p.add_argument("--fps", type=float, default=None, help="override the scenario's camera rate")
    p.add_argument("--rate", type=float, default=1.0, help="simulated seconds per wall second")
    p.add_argument("--encoding", default="rgb8", choices=["rgb8", "jpeg", "png"], help="stereo frame encoding")
    p.add_argument("--closed-loop", action="store_true", help="drive by planner/cmd_vel instead of the scripted path")
    p.add_argument("--cmd-timeout", type=float, default=1.0, help="closed loop: stop when commands are this old")
    p.add_argument("--end-on-target", type=float, default=None, metavar="S",
                   help="closed loop: end (exit 0) once the planner has said 'target reached' for S simulated "
                        "seconds (with ends_run in a launch file, this ends the run)")
    p.add_argument("--depth", action="store_true", help="also publish the ground-truth depth map")
    p.add_argument("--duration", type=float, default=None, help="simulated seconds to run (default: until the path ends)")
    p.add_argument("--truth-tum", default=None, help="write the ground-truth trajectory (TUM) here on exit")
    return p


def _resolve_scenario(name: str):
    path = name if name.endswith(".toml") else scenario_path(name)
    return load_scenario(path)


class CommandInbox:
    """Newest velocity command, written by a Zenoh thread, read by the simulation loop."""

    def __init__(self):
        self._lock = threading.Lock()
        self.command: m.VelocityCommand | None = None
        self.received_at = 0.0

    def put(self, cmd: m.VelocityCommand) -> None:
        if not (np.isfinite(cmd.linear_mps) and np.isfinite(cmd.angular_radps)):
            return
        with self._lock:
            self.command, self.received_at = cmd, time.monotonic()

    def reason(self, timeout: float) -> str | None:
        """The newest command's reason, or None if there is none or it is older than ``timeout``."""
        with self._lock:
            cmd, age = self.command, time.monotonic() - self.received_at
        return None if cmd is None or age > timeout else cmd.reason

    def get(self, timeout: float) -> tuple[float, float]:
        with self._lock:
            cmd, age = self.command, time.monotonic() - self.received_at
        if cmd is None or cmd.stop or age > timeout:
            return 0.0, 0.0
        return cmd.linear_mps, cmd.angular_radps


def body(node, args) -> int:
    try:
        scenario = _resolve_scenario(args.scenario)
    except (ScenarioError, FileNotFoundError) as e:
        log.error("%s", e)
        return 2
    sim = Simulator(scenario, seed=args.seed, width=args.width, height=args.height, camera_rate_hz=args.fps)
    calib = sim.calibration
    pubs = {name: node.publisher(name) for name in ("stereo/frame", "odom/wheels", "sonar/scan", "truth/pose", "truth/depth")}
    calib_pub = node.publisher("stereo/calibration", latched=True)
    target_pub = node.publisher("planner/target", latched=True)
    inbox = CommandInbox()
    if args.closed_loop:
        node.subscribe("planner/cmd_vel", m.VelocityCommand, inbox.put)
        sim.set_command(0.0, 0.0)

    t0_ns = time.time_ns()
    t0_wall = time.monotonic()
    frame_seq = 0
    truth_stamps, truth_poses = [], []
    last_calib = -1e9

    def publish_static(now_ns: int) -> None:
        calib_pub.publish(m.calibration_to_msg(calib, 0, now_ns))
        target = target_message(scenario, now_ns)
        if target is not None:
            target_pub.publish(target)

    step = 0.01
    reached_since_ns = None     # simulated time since which the planner has said 'target reached'
    while not node.stopping:
        if args.duration is not None and sim.time_ns * 1e-9 >= args.duration:
            break
        if not args.closed_loop and sim.finished:
            log.info("scripted path finished after %.1f s", sim.time_ns * 1e-9)
            break
        if time.monotonic() - last_calib > 2.0:
            publish_static(t0_ns + sim.time_ns)
            last_calib = time.monotonic()
        if args.closed_loop:
            sim.set_command(*inbox.get(args.cmd_timeout))
            if args.end_on_target is not None:
                if inbox.reason(args.cmd_timeout) == "target reached":
                    reached_since_ns = sim.time_ns if reached_since_ns is None else reached_since_ns
                    if (sim.time_ns - reached_since_ns) * 1e-9 >= args.end_on_target:
                        log.info("target reached at %.1f s; ending", reached_since_ns * 1e-9)
                        break
                else:
                    reached_since_ns = None
        events = sim.advance(step)
        # Real-time pacing: publish each batch when the wall clock reaches the simulated time.
        if args.rate > 0:
            due = t0_wall + sim.time_ns * 1e-9 / args.rate
            delay = due - time.monotonic()
            if delay > 0 and not node.sleep(delay):
                break
        for ev in events:
            stamp = t0_ns + ev.stamp_ns
            if isinstance(ev, OdometryReading):
                pubs["odom/wheels"].publish(odometry_message(ev, stamp))
            elif isinstance(ev, SonarReading):
                pubs["sonar/scan"].publish(sonar_message(ev, stamp))
            elif isinstance(ev, CameraDue):
                images = sim.render(ev.stamp_ns)
                frame_seq += 1
                for stream, msg in camera_messages(images, frame_seq, stamp, args.encoding, args.depth).items():
                    pubs[stream].publish(msg)
                truth_stamps.append(stamp)
                truth_poses.append(images.T_map_base)
                node.progress += 1
        node.rates["sim_time_s"] = sim.time_ns * 1e-9
        node.rates["clearance_m"] = sim.clearance()
    if args.truth_tum and truth_stamps:
        write_tum(args.truth_tum, np.array(truth_stamps, np.int64), np.array(truth_poses))
        log.info("wrote ground truth (%d poses) to %s", len(truth_stamps), args.truth_tum)
    log.info("published %d frames; %d collisions", frame_seq, sim.collisions)
    return 0


def main(argv=None) -> int:
    return run_service("sim", build_parser(), body, argv)


if __name__ == "__main__":
    sys.exit(main())
