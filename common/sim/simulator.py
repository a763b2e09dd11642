"""The simulated robot: motion, sensor schedule, and stereo rendering, stepped by the caller.

Usage (what services/sim.py does)::

    scn = load_scenario("recordings/scenarios/corridor.toml")
    sim = Simulator(scn, seed=0)                      # width/height/baseline/... override the scenario
    while not sim.finished:
        for ev in sim.advance(0.02):                  # events due in that interval, in stamp order
            if isinstance(ev, CameraDue):
                frame = sim.render(ev.stamp_ns)       # StereoImages at that stamp
            elif isinstance(ev, OdometryReading): ...
            elif isinstance(ev, SonarReading): ...
    sim.set_command(v, omega)                         # closed loop: drop the scripted path, follow (v, ω)

Time is integer nanoseconds of simulated time, starting at 0.  Motion is integrated in sub-steps of at
most 5 ms that land exactly on every sensor stamp.  Everything random draws from generators spawned from
``seed``, so a run is reproducible; the sensors each have their own stream, so rendering more or fewer
frames does not change odometry or sonar.
"""
from __future__ import annotations

from collections import deque
from dataclasses import dataclass, replace

import numpy as np

from common.camera import StereoCalibration
from common.geometry import R_BODY_OPTICAL, make_transform, planar_pose, rot_x, rot_y, rot_z
from common.sim.motion import CommandMotion, make_motion
from common.sim.render import Renderer, noise_table
from common.sim.scenario import Scenario
from common.sim.sensors import SonarRing, WheelOdometry
from common.sim.world import World

SUBSTEP_NS = 5_000_000
HISTORY_S = 3.0


@dataclass
class CameraDue:
    """A stereo frame is due at ``stamp_ns``: call ``sim.render(stamp_ns)``."""
    stamp_ns: int


@dataclass
class StereoImages:
    """Left/right RGB uint8 (H, W, 3), depth float32 (H, W) = Z in the left optical frame (inf = sky), and
    the ground-truth pose of base_link in map at the stamp."""
    stamp_ns: int
    left: np.ndarray
    right: np.ndarray
    depth: np.ndarray
    T_map_base: np.ndarray


class SimulationError(ValueError):
    """Bad use of the simulator (bad step, stamp outside the kept history, ...)."""


def _period_ns(rate_hz: float) -> int:
    return int(round(1e9 / rate_hz))


class Simulator:
    """A robot with a stereo rig, wheel odometry and a sonar ring moving through a scenario's world.

    Overrides (all optional) replace the scenario's [camera] values: ``width``, ``height``, ``baseline``,
    ``hfov_deg``, ``camera_rate_hz``, ``motion_blur_samples``.
    """

    def __init__(self, scenario: Scenario, seed: int = 0, width: int | None = None, height: int | None = None,
                 baseline: float | None = None, hfov_deg: float | None = None,
                 camera_rate_hz: float | None = None, motion_blur_samples: int | None = None,
                 world: World | None = None):
        cam = scenario.camera
        over = {k: v for k, v in dict(width=width, height=height, baseline=baseline, hfov_deg=hfov_deg,
                                        rate_hz=camera_rate_hz, motion_blur_samples=motion_blur_samples).items()
                if v is not None}
        for k, v in over.items():
            if not (np.isfinite(v) and v > 0):
                raise SimulationError(f"camera override {k} must be positive, got {v}")
        self.camera_config = cam = replace(cam, **over)
        self.scenario = scenario
        self.seed = int(seed)
        self.world = world if world is not None else World(scenario)

        # Left optical frame in base_link: rig centred on the robot's x axis, optionally pitched down.
        R_base_cam = rot_y(np.deg2rad(cam.pitch_deg)) @ R_BODY_OPTICAL
        T_base_camera = make_transform(R_base_cam, [cam.forward_m, cam.baseline / 2, cam.height_m])
        self.calibration = StereoCalibration.ideal(int(cam.width), int(cam.height), baseline=cam.baseline,
                                                   hfov_deg=cam.hfov_deg, T_base_camera=T_base_camera)
        c = self.calibration
        self.renderer = Renderer(self.world, c.width, c.height, c.fx, c.fy, c.cx_left, c.cy)
        self._T_left_right = make_transform(None, [cam.baseline, 0.0, 0.0])
        self._vignette = self.renderer.vignette(cam.vignetting)
        self._rad_buffer = np.empty((c.height, c.width, 3), np.float32)

        ss = np.random.SeedSequence(self.seed)
        r_odo, r_sonar, r_cam = (np.random.default_rng(s) for s in ss.spawn(3))
        self._cam_rng = r_cam
        self._noise_table = noise_table(self.seed)
        self.odometry = WheelOdometry(scenario.odometry, r_odo)
        self.sonar = SonarRing(scenario.sonar, r_sonar)
        self._sonar_segments = self.world.obstacle_segments(scenario.sonar.height_m, scenario.sonar.height_m)

        self.pose = tuple(float(v) for v in scenario.start)     # x, y, yaw of base_link in map
        self.T_map_odom = planar_pose(*self.pose)  # odometry's dead reckoning starts at 0 in this frame
        self.motion = make_motion(scenario.path, self.pose)
        self.time_ns = 0
        self.collisions = 0
        self._periods = {"odometry": _period_ns(scenario.odometry.rate_hz),
                         "sonar": _period_ns(scenario.sonar.rate_hz),
                         "camera": _period_ns(cam.rate_hz)}
        self._next = dict.fromkeys(self._periods, 0)
        self._next["odometry"] = self._periods["odometry"]  # the first odometry sample covers one period
        self._history = deque([(0, *self.pose)])
        self._swaying = cam.sway_deg > 0 or cam.bob_m > 0

    # ------------------------------------------------------------------------------------ control
    @property
    def finished(self) -> bool:
        """True when the scripted path is done (never for command-driven scenarios)."""
        return not isinstance(self.motion, CommandMotion) and self.motion.finished

    def set_command(self, v: float, omega: float) -> None:
        """Drive by velocity command from now on (m/s forward, rad/s counter-clockwise); drops any
        scripted path.  In this mode the robot stops short of obstacles and counts ``collisions``."""
        if not (np.isfinite(v) and np.isfinite(omega)):
            raise SimulationError(f"command must be finite, got v={v}, omega={omega}")
        if not isinstance(self.motion, CommandMotion):
            self.motion = CommandMotion()
        self.motion.v, self.motion.omega = float(v), float(omega)

    def truth_pose(self) -> np.ndarray:
        """4×4 T_map_base now."""
        return self.truth_at(self.time_ns)

    def truth_at(self, stamp_ns: int) -> np.ndarray:
        """4×4 T_map_base at a stamp within the last few seconds (linear interpolation of the history),
        with the hand-held sway when the camera has one."""
        T = planar_pose(*self._pose_at(stamp_ns))
        return T @ self._sway(stamp_ns) if self._swaying else T

    def _sway(self, stamp_ns: int) -> np.ndarray:
        """The hand-held rig's motion about the planar path at ``stamp_ns``: roll, pitch and yaw
        oscillations of incommensurate periods (so they never line up), and a bob at twice the rate."""
        cam = self.camera_config
        w = 2 * np.pi * stamp_ns * 1e-9 / cam.sway_period_s
        a = np.deg2rad(cam.sway_deg)
        R = rot_z(0.5 * a * np.sin(0.73 * w + 2.0)) @ rot_y(a * np.sin(1.37 * w + 1.0)) @ rot_x(a * np.sin(w))
        return make_transform(R, [0.0, 0.0, cam.bob_m * np.sin(2 * w)])

    def clearance(self) -> float:
        """Distance from the robot body (its radius) to the nearest obstacle now; ≤ 0 is a collision."""
        return self.world.min_clearance(self.pose[0], self.pose[1])

    # ------------------------------------------------------------------------------------ stepping
    def advance(self, dt_s: float) -> list:
        """Move the world forward by dt_s seconds; return the sensor events due in that interval (stamps
        in (t, t + dt]), in time order: OdometryReading, SonarReading, CameraDue."""
        if not (np.isfinite(dt_s) and dt_s >= 0):
            raise SimulationError(f"advance needs a finite dt_s ≥ 0, got {dt_s}")
        end = self.time_ns + int(round(dt_s * 1e9))
        events = []
        if self.time_ns == 0 and self._next["camera"] == 0:  # sensors due at t = 0
            events += self._fire(0)
        while self.time_ns < end:
            nxt = min(end, self.time_ns + SUBSTEP_NS, *(t for t in self._next.values() if t > self.time_ns))
            self._step((nxt - self.time_ns) * 1e-9)
            self.time_ns = nxt
            events += self._fire(nxt)
        return events

    def _step(self, dt: float):
        new_pose, (vx, vy, omega) = self.motion.step(self.pose, dt)
        if isinstance(self.motion, CommandMotion) and (vx != 0 or omega != 0):
            r = self.scenario.robot_radius
            d_new = self.world.clearance(np.array([new_pose[:2]]))[0]
            if d_new < r and d_new < self.world.clearance(np.array([self.pose[:2]]))[0]:
                # would move into (or deeper into) an obstacle: blocked
                self.collisions += 1
                new_pose, vx, vy, omega = self.pose, 0.0, 0.0, 0.0
        self.odometry.move(vx, omega, dt)
        self.pose = tuple(float(p) for p in new_pose)
        self._history.append((self.time_ns + int(round(dt * 1e9)), *self.pose))
        horizon = self.time_ns - int(HISTORY_S * 1e9)
        while len(self._history) > 2 and self._history[1][0] < horizon:
            self._history.popleft()

    def _fire(self, t: int) -> list:
        out = []
        for name in ("odometry", "sonar", "camera"):
            if self._next[name] != t:
                continue
            period = self._periods[name]
            if name == "odometry":
                out.append(self.odometry.sample(t, period * 1e-9))
            elif name == "sonar":
                out.append(self.sonar.measure(t, self.pose, self._sonar_segments))
            else:
                out.append(CameraDue(t))
            self._next[name] = t + period
        return out

    def _pose_at(self, stamp_ns: int) -> tuple[float, float, float]:
        h = np.array(self._history, dtype=float)
        if not (h[0, 0] <= stamp_ns <= h[-1, 0]):
            raise SimulationError(f"stamp {stamp_ns} ns is outside the kept history "
                                  f"[{int(h[0, 0])}, {int(h[-1, 0])}] ns")
        yaw = np.unwrap(h[:, 3])
        return (float(np.interp(stamp_ns, h[:, 0], h[:, 1])), float(np.interp(stamp_ns, h[:, 0], h[:, 2])),
                float(np.interp(stamp_ns, h[:, 0], yaw)))

    # ------------------------------------------------------------------------------------ rendering
    def render(self, stamp_ns: int | None = None) -> StereoImages:
        """Stereo pair and depth at ``stamp_ns`` (default: now).  With motion blur the exposure window
        ends at the stamp."""
        stamp = self.time_ns if stamp_ns is None else int(stamp_ns)
        cam = self.camera_config
        T_map_base = self.truth_at(stamp)
        T_base_left = self.calibration.T_base_camera
        n = max(1, int(cam.motion_blur_samples))
        if n == 1:
            bases = [T_map_base]
        else:
            t0 = max(self._history[0][0], stamp - int(cam.exposure_time_s * 1e9))
            bases = [self.truth_at(int(t)) for t in np.linspace(t0, stamp, n)]
        if n == 1:  # fast path: both views traced and exposed in one pass
            T_map_left = T_map_base @ T_base_left
            left, right, depth = self.renderer.stereo(
                T_map_left, T_map_left @ self._T_left_right, (cam.exposure, cam.exposure * cam.gain_right),
                (0.0, cam.offset_right), self._vignette, self._noise_table, self._cam_rng,
                cam.read_noise, cam.shot_noise)
            return StereoImages(stamp, left, right, depth, T_map_base)
        images, depth = [], None
        for side, T_left_side in (("left", np.eye(4)), ("right", self._T_left_right)):
            # Radiance goes to a reused scratch buffer; depth and images are fresh (handed to the caller).
            rad, d = self.renderer.radiance(bases[0] @ T_base_left @ T_left_side, out_rad=self._rad_buffer)
            if n > 1:  # motion blur: average the radiance over the exposure window
                scratch = np.empty_like(d)
                for Tb in bases[1:]:
                    self.renderer.radiance(Tb @ T_base_left @ T_left_side, out_rad=rad, out_depth=scratch,
                                           accumulate=True)
                rad /= n
                if side == "left":
                    d = self.renderer.radiance(T_map_base @ T_base_left)[1]
            if side == "left":
                depth = d
            gain = 1.0 if side == "left" else cam.gain_right
            offset = 0.0 if side == "left" else cam.offset_right
            images.append(self.renderer.expose(rad, cam.exposure, gain, offset, self._vignette,
                                               self._noise_table, self._cam_rng,
                                               cam.read_noise, cam.shot_noise))
        return StereoImages(stamp, images[0], images[1], depth, T_map_base)
