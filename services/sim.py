"""Simulator service: a simulated robot in a scenario's world, publishing what a real robot publishes.

Publishes ``stereo/frame`` (rectified pair), ``stereo/calibration`` (latched, repeated every 2 s),
``odom/wheels``, ``sonar/scan``, ``truth/pose`` (base_link in map, at the camera rate), optionally
``truth/depth``, and the scenario's ``planner/target`` (latched). Stamps are wall-clock nanoseconds
(start time + simulated time), so latencies measured downstream are real.

Runs in real time (``--rate`` scales it); in closed loop (``--closed-loop``) it drives by the newest
``planner/cmd_vel``, stops the robot when commands stop arriving for ``--cmd-timeout`` seconds, and with
``--end-on-target S`` exits 0 once the planner has said 'target reached' for S seconds.
Writes the ground-truth trajectory as TUM text with ``--truth-tum``: rewritten atomically every second
and on exit, so a simulator killed with SIGKILL leaves it too, at most a second short.
"""
from __future__ import annotations

import logging
import sys
import threading
import time

import numpy as np

from common import messages as m
from common import streams as S
from common.sim import Simulator, load_scenario
from common.sim.bus_messages import camera_messages, odometry_message, sonar_message, target_message
from common.sim.scenario import ScenarioError, scenario_path
from common.sim.sensors import OdometryReading, SonarReading
from common.sim.simulator import CameraDue
from common.trajectory import TumFile
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
                   help="closed loop: exit 0 once the planner has said 'target reached' for S simulated seconds")
    p.add_argument("--depth", action="store_true", help="also publish the ground-truth depth map")
    p.add_argument("--duration", type=float, default=None, help="simulated seconds to run (default: until the path ends)")
    p.add_argument("--truth-tum", default=None, help="write the ground-truth trajectory (TUM) here, every second and on exit")
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


class TargetHold:
    """Ends a closed-loop run once the planner has said 'target reached' for ``seconds`` of simulated time."""

    def __init__(self, seconds: float | None):
        self.seconds = seconds
        self.since_ns: int | None = None

    def reached(self, reason: str | None, sim_time_ns: int) -> bool:
        if self.seconds is None or reason != "target reached":
            self.since_ns = None
            return False
        self.since_ns = sim_time_ns if self.since_ns is None else self.since_ns
        return (sim_time_ns - self.since_ns) * 1e-9 >= self.seconds


def publish_events(node, pubs: dict, sim: Simulator, events, t0_ns: int, args, truth: TumFile | None) -> None:
    """Publish one batch of simulator events stamped with wall-clock start + simulated time."""
    for ev in events:
        stamp = t0_ns + ev.stamp_ns
        if isinstance(ev, OdometryReading):
            pubs[S.ODOM_WHEELS].publish(odometry_message(ev, stamp))
        elif isinstance(ev, SonarReading):
            pubs[S.SONAR_SCAN].publish(sonar_message(ev, stamp))
        elif isinstance(ev, CameraDue):
            images = sim.render(ev.stamp_ns)
            node.progress += 1
            for stream, msg in camera_messages(images, node.progress, stamp, args.encoding, args.depth).items():
                pubs[stream].publish(msg)
            if truth is not None:
                truth.append(stamp, images.T_map_base)


def body(node, args) -> int:
    try:
        scenario = _resolve_scenario(args.scenario)
    except (ScenarioError, FileNotFoundError) as e:
        log.error("%s", e)
        return 2
    sim = Simulator(scenario, seed=args.seed, width=args.width, height=args.height, camera_rate_hz=args.fps)
    pubs = {s: node.publisher(s) for s in (S.ODOM_WHEELS, S.SONAR_SCAN, S.STEREO_CALIBRATION, S.PLANNER_TARGET)}
    pubs.update({s.key: node.publisher(s) for s in (S.STEREO_FRAME, S.TRUTH_POSE, S.TRUTH_DEPTH)})
    inbox, hold = CommandInbox(), TargetHold(args.end_on_target)
    if args.closed_loop:
        node.subscribe(S.PLANNER_CMD_VEL, callback=inbox.put)
        sim.set_command(0.0, 0.0)
    t0_ns, t0_wall, last_static = time.time_ns(), time.monotonic(), -1e9
    truth = TumFile(args.truth_tum) if args.truth_tum else None
    while not node.stopping:
        if args.duration is not None and sim.time_ns * 1e-9 >= args.duration:
            break
        if not args.closed_loop and sim.finished:
            log.info("scripted path finished after %.1f s", sim.time_ns * 1e-9)
            break
        if time.monotonic() - last_static > 2.0:
            pubs[S.STEREO_CALIBRATION].publish(m.calibration_to_msg(sim.calibration, 0, t0_ns + sim.time_ns))
            if (target := target_message(scenario, t0_ns + sim.time_ns)) is not None:
                pubs[S.PLANNER_TARGET].publish(target)
            last_static = time.monotonic()
        if args.closed_loop:
            sim.set_command(*inbox.get(args.cmd_timeout))
            if hold.reached(inbox.reason(args.cmd_timeout), sim.time_ns):
                log.info("target reached at %.1f s; ending", hold.since_ns * 1e-9)
                break
        events = sim.advance(0.01)
        # Real-time pacing: publish each batch when the wall clock reaches the simulated time.
        delay = t0_wall + sim.time_ns * 1e-9 / args.rate - time.monotonic() if args.rate > 0 else 0.0
        if delay > 0 and not node.sleep(delay):
            break
        publish_events(node, pubs, sim, events, t0_ns, args, truth)
        node.rates.update(sim_time_s=sim.time_ns * 1e-9, clearance_m=sim.clearance())
    if truth is not None and len(truth):
        truth.flush()
        log.info("wrote ground truth (%d poses) to %s", len(truth), args.truth_tum)
    log.info("published %d frames; %d collisions", node.progress, sim.collisions)
    return 0


def main(argv=None) -> int:
    return run_service("sim", build_parser(), body, argv)


if __name__ == "__main__":
    sys.exit(main())
