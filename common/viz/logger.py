"""Turn flyslam messages into Rerun log calls (no bus, no I/O beyond the RecordingStream's sinks).

Timelines: every message is logged on ``stamp`` (its envelope ``stamp_ns``, a timestamp timeline);
stereo images and the flies evaluated on them also on ``frame_seq``. Heartbeats and liveliness carry
wall-clock stamps, which would stretch the sensor timeline when replaying a dataset, so they are put at
the newest *sensor* stamp seen so far (they are also on Rerun's automatic ``log_time``).

Costs are kept low for a bridge that shares two cores: JPEG frames pass through undecoded, raw frames
are JPEG-encoded once, populations and maps are subsampled, poses are logged at a bounded rate per
stream, trajectories are decimated by distance and logged in segments of bounded size, the open one
re-logged at a bounded rate.
"""
from __future__ import annotations

import re

import cv2
import numpy as np
import rerun as rr

from common import messages as m
from common.geometry import matrix_from_quat
from common.viz import paths as P
from common.viz.colours import field_image, field_pixels, fitness_colours

# Which pose stream moves world/robot, best first: the fused pose, then the localiser, then odometry,
# then ground truth (so a simulator-only run still shows the robot).
BEST_POSE_ORDER = ("fusion/pose", "slam/pose", "fusion/odom", "truth/pose")
PROBLEM_COUNTER = re.compile(r"reject|skip|drop|error|fail|timeout|lost", re.IGNORECASE)
_MEDIA_TYPES = {"jpeg": "image/jpeg", "png": "image/png"}
# Distinct series colours per service, in order of first appearance (Rerun's hash colours can collide).
SERVICE_PALETTE = [(230, 159, 0), (86, 180, 233), (0, 158, 115), (240, 228, 66), (213, 94, 0), (204, 121, 167),
                   (0, 114, 178), (200, 200, 200), (150, 90, 255), (120, 220, 120)]


def finite_pose(msg: m.PoseEstimate) -> bool:
    """Whether a pose's position and orientation are finite (what the viewer can draw)."""
    return bool(np.all(np.isfinite(msg.position)) and np.all(np.isfinite(msg.orientation)))


class PoseRate:
    """At most one pose per ``period_ns`` of sensor time per stream (a stamp going back starts again):
    the rule of :meth:`RerunLogger.pose`, shared with the bridge's thinning on arrival. Not thread-safe."""

    def __init__(self, period_ns: int):
        self.period_ns = int(period_ns)
        self._last: dict[str, int] = {}

    def due(self, stream: str, stamp_ns: int) -> bool:
        """True (and the stream's clock moves to ``stamp_ns``) when this pose is to be logged."""
        last = self._last.get(stream)
        if last is not None and 0 <= stamp_ns - last < self.period_ns:
            return False
        self._last[stream] = stamp_ns
        return True


class Trail:
    """A trajectory decimated by distance and cut into segments of at most ``segment_points`` points.

    A point is kept when it is ``min_step_m`` from the last kept one. Only the open (last) segment is
    ever re-logged, so the cost of growing a trajectory stays constant however long the run: closed
    segments stay on screen from the time they were logged (Rerun's latest-at), and scrubbing back in
    time shows the trajectory as it was then. Each segment starts at the previous one's last point.
    """

    def __init__(self, min_step_m: float = 0.01, segment_points: int = 200):
        if segment_points < 2:
            raise ValueError(f"segment_points must be at least 2, got {segment_points}")
        self.min_step_m, self.segment_points = min_step_m, segment_points
        self.segment = 0
        self._points: list[np.ndarray] = []
        self.last_logged_ns: int | None = None
        self.dirty = False  # points added since the last log

    def add(self, p: np.ndarray) -> bool:
        """Append ``p`` if it moved far enough; returns whether it was kept."""
        if self._points and np.linalg.norm(p - self._points[-1]) < self.min_step_m:
            return False
        self._points.append(np.asarray(p, np.float64).copy())
        self.dirty = True
        return True

    @property
    def full(self) -> bool:
        return len(self._points) >= self.segment_points

    def points(self) -> np.ndarray:
        """The open segment's points."""
        return np.array(self._points).reshape(-1, 3)

    def roll(self) -> None:
        """Close the open segment; the next starts at its last point."""
        self.segment += 1
        self._points = self._points[-1:]
        self.dirty = False


def subsample(n: int, k: int, rng: np.random.Generator) -> np.ndarray | slice:
    """Indices of a uniform random subset of ``k`` out of ``n`` (in order), or all when n ≤ k."""
    if n <= k:
        return slice(None)
    return np.sort(rng.choice(n, size=k, replace=False))


class RerunLogger:
    """Logs flyslam messages into one :class:`rerun.RecordingStream`. Call :meth:`handle` per message.

    ``planner_layout``: whether the stream's layout already has the planner's views; when not, the
    planner's first sign of life (its liveliness token, a field, a command) sends the layout that has.
    Not thread-safe: feed it from one thread (the bridge's main loop).
    """

    def __init__(self, rec: rr.RecordingStream, *, max_flies: int = 20_000, max_map_points: int = 100_000,
                 jpeg_quality: int = 80, trail_min_step_m: float = 0.01, trail_period_s: float = 0.2,
                 trail_segment_points: int = 200, pose_period_s: float = 1 / 30, seed: int = 0,
                 planner_layout: bool = True):
        if max_flies <= 0 or max_map_points <= 0:
            raise ValueError("max_flies and max_map_points must be positive")
        if not 1 <= jpeg_quality <= 100:
            raise ValueError(f"jpeg_quality must be in 1..100, got {jpeg_quality}")
        self.rec = rec
        self.max_flies, self.max_map_points, self.jpeg_quality = max_flies, max_map_points, jpeg_quality
        self.trail_period_ns = int(trail_period_s * 1e9)
        self._pose_rate = PoseRate(int(pose_period_s * 1e9))
        self._trail_min_step, self._trail_segment_points = trail_min_step_m, trail_segment_points
        self._rng = np.random.default_rng(seed)
        self.calibration_msg: m.StereoCalibrationMsg | None = None
        self._calib = None  # common.camera.StereoCalibration for projecting flies
        self.sensor_ns = 0
        self._trails: dict[str, Trail] = {}
        self._pose_source: str | None = None
        self._map_signature = None
        self._last_status: dict[str, str] = {}
        self._last_state: dict[str, str] = {}
        self._last_stop: tuple[bool, str] | None = None
        self._series_styled: set[str] = set()
        self._service_colour: dict[str, tuple] = {}
        self.counts: dict[str, int] = {}
        self.planner_layout = planner_layout
        self._handlers = {
            m.StereoCalibrationMsg: self.calibration, m.StereoFrame: self.frame, m.FlyPopulation: self.population,
            m.FlyMap: self.fly_map, m.HarmonicField: self.field, m.Target: self.target,
            m.VelocityCommand: self.command, m.Heartbeat: self.heartbeat,
        }
        self._log_setup()

    # ---------------------------------------------------------------------------------- plumbing
    def _at(self, stamp_ns: int | None, frame_seq: int | None = None) -> None:
        """Set this thread's timelines for the next log calls."""
        if stamp_ns and stamp_ns > 0:
            self.rec.set_time(P.STAMP, timestamp=np.datetime64(int(stamp_ns), "ns"))
        else:
            self.rec.disable_timeline(P.STAMP)
        if frame_seq is not None:
            self.rec.set_time(P.FRAME_SEQ, sequence=int(frame_seq))
        else:
            self.rec.disable_timeline(P.FRAME_SEQ)

    def _sensor(self, stamp_ns: int) -> None:
        self.sensor_ns = max(self.sensor_ns, int(stamp_ns))

    def _event(self, text: str, level: str = "INFO") -> None:
        self.rec.log(P.EVENTS, rr.TextLog(text, level=level))

    def _log_setup(self) -> None:
        self.rec.log(P.WORLD, rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
        self.rec.log(P.ROBOT, rr.TransformAxes3D(0.3), static=True)
        for stream, (name, colour) in P.TRAJECTORY_STYLE.items():
            self._trails[stream] = Trail(self._trail_min_step, self._trail_segment_points)
        self.rec.log(f"{P.CMD}/linear_mps", rr.SeriesLines(names="linear m/s", colors=[(60, 160, 255)]), static=True)
        self.rec.log(f"{P.CMD}/angular_radps", rr.SeriesLines(names="angular rad/s", colors=[(255, 120, 60)]),
                     static=True)

    def handle(self, stream: str, msg) -> None:
        """Log one message that arrived on ``stream`` (the key without the robot prefix)."""
        self.counts[stream] = self.counts.get(stream, 0) + 1
        if isinstance(msg, m.PoseEstimate):
            self.pose(stream, msg)
            return
        if stream == "fusion/sonar_points" and isinstance(msg, m.FlyPopulation):
            self.sonar_points(msg)
            return
        handler = self._handlers.get(type(msg))
        if handler is None:
            raise ValueError(f"the bridge has no view for {type(msg).__name__} on {stream!r}")
        handler(msg)

    # ----------------------------------------------------------------------------- calibration
    def calibration(self, msg: m.StereoCalibrationMsg) -> None:
        """Static: the left optical frame in base_link and a Pinhole per image (camera convention RDF)."""
        old = self.calibration_msg
        if old is not None and (old.width, old.height) == (msg.width, msg.height) and np.array_equal(
                old.left.P, msg.left.P) and np.array_equal(old.T_base_camera, msg.T_base_camera):
            return  # the same latched calibration again (subscription and query both deliver it)
        self._calib = m.calibration_from_msg(msg)  # raises CalibrationError when inconsistent
        self.calibration_msg = msg
        T = np.asarray(msg.T_base_camera, float)
        self.rec.log(P.CAMERA, rr.Transform3D(translation=T[:3, 3], mat3x3=T[:3, :3]), static=True)
        size = [msg.width, msg.height]
        self.rec.log(P.LEFT, rr.Pinhole(image_from_camera=msg.left.P[:, :3], resolution=size,
                                        camera_xyz=rr.ViewCoordinates.RDF, image_plane_distance=0.3), static=True)
        self._event(f"calibration {msg.width}×{msg.height}, baseline {msg.baseline_m:.3f} m")

    # ---------------------------------------------------------------------------------- images
    def _encoded(self, data: np.ndarray, encoding: str) -> rr.EncodedImage:
        if encoding in _MEDIA_TYPES:  # already compressed: pass the bytes through
            return rr.EncodedImage(contents=np.ascontiguousarray(data).tobytes(), media_type=_MEDIA_TYPES[encoding])
        img = cv2.cvtColor(data, cv2.COLOR_RGB2BGR) if data.ndim == 3 else data
        ok, buf = cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, self.jpeg_quality])
        if not ok:
            raise ValueError(f"could not JPEG-encode a {data.shape} image")
        return rr.EncodedImage(contents=buf.tobytes(), media_type="image/jpeg")

    def frame(self, msg: m.StereoFrame) -> None:
        """Left and right rectified images, compressed, on both timelines."""
        if msg.encoding not in _MEDIA_TYPES and msg.encoding not in ("rgb8", "mono8"):
            raise ValueError(f"unknown image encoding {msg.encoding!r}")
        self._sensor(msg.header.stamp_ns)
        self._at(msg.header.stamp_ns, msg.header.seq)
        self.rec.log(P.LEFT, self._encoded(msg.left, msg.encoding))
        self.rec.log(P.RIGHT, self._encoded(msg.right, msg.encoding))

    # ----------------------------------------------------------------------------------- flies
    def population(self, msg: m.FlyPopulation) -> None:
        """Flies in 3-D (optical frame) coloured by fitness, and their projections on both images."""
        pos, fit = msg.positions, msg.fitness
        if len(pos) != len(fit):
            raise ValueError(f"population has {len(pos)} positions but {len(fit)} fitness values")
        self._sensor(msg.header.stamp_ns)
        idx = subsample(len(pos), self.max_flies, self._rng)
        pos, fit = pos[idx], fit[idx]
        colours = fitness_colours(fit)
        self._at(msg.header.stamp_ns, msg.source_seq)
        self.rec.log(P.FLIES, rr.Points3D(pos, colors=colours, radii=-2.0))
        if self._calib is None:
            return
        ul, ur, v = self._calib.project(pos)
        w, h = self._calib.width, self._calib.height
        in_left = np.isfinite(ul) & (ul >= 0) & (ul < w) & (v >= 0) & (v < h)
        in_right = np.isfinite(ur) & (ur >= 0) & (ur < w) & (v >= 0) & (v < h)
        self.rec.log(P.LEFT_FLIES, rr.Points2D(np.stack([ul[in_left], v[in_left]], 1), colors=colours[in_left],
                                               radii=-1.5, draw_order=10.0))
        self.rec.log(P.RIGHT_FLIES, rr.Points2D(np.stack([ur[in_right], v[in_right]], 1),
                                                colors=colours[in_right], radii=-1.5, draw_order=10.0))

    def sonar_points(self, msg: m.FlyPopulation) -> None:
        """Fusion's sonar echo points (a FlyPopulation in base_link) under the robot."""
        if msg.header.frame_id not in ("", m.BASE_LINK):
            raise ValueError(f"sonar points in frame {msg.header.frame_id!r}, expected {m.BASE_LINK}")
        self._sensor(msg.header.stamp_ns)
        self._at(msg.header.stamp_ns)
        self.rec.log(P.SONAR_POINTS, rr.Points3D(msg.positions, colors=[(255, 80, 160)], radii=-3.0))

    # ------------------------------------------------------------------------------------ poses
    def pose(self, stream: str, msg: m.PoseEstimate) -> None:
        """Grow the stream's trajectory; the best pose stream seen so far also moves ``world/robot``.
        At most one pose per ``pose_period_s`` of sensor time is logged per stream (status changes are
        always noted), so the viewer's memory grows with time, not with the publishers' rate."""
        if stream not in P.TRAJECTORY_STYLE:
            raise ValueError(f"no trajectory view for pose stream {stream!r}")
        stamp = msg.header.stamp_ns
        self._sensor(stamp)
        self._at(stamp)
        if msg.status != self._last_status.get(stream, "ok"):
            self._event(f"{stream}: {msg.status}", "INFO" if msg.status == "ok" else "WARN")
        self._last_status[stream] = msg.status
        if msg.status.startswith("rejected"):
            return
        if not finite_pose(msg):
            raise ValueError(f"{stream}: non-finite pose")
        if not self._pose_rate.due(stream, stamp):
            return          # a viewer needs no more than pose_period_s; a flood must not fill its buffer
        rank = BEST_POSE_ORDER.index(stream)
        if self._pose_source is None or rank <= BEST_POSE_ORDER.index(self._pose_source):
            if self._pose_source != stream:
                self._event(f"robot pose now from {stream}")
            self._pose_source = stream
            q = msg.orientation / np.linalg.norm(msg.orientation)
            self.rec.log(P.ROBOT, rr.Transform3D(translation=msg.position, quaternion=rr.Quaternion(xyzw=q)))
        trail = self._trails[stream]
        if not trail.add(msg.position):
            return
        if trail.full:
            self.log_trail(stream, stamp)
            trail.roll()
        elif (trail.last_logged_ns is None or stamp - trail.last_logged_ns >= self.trail_period_ns
              or stamp < trail.last_logged_ns):
            self.log_trail(stream, stamp)

    def log_trail(self, stream: str, stamp_ns: int | None = None) -> None:
        """(Re-)log the open segment of a trajectory as a line strip."""
        trail = self._trails[stream]
        pts = trail.points()
        if len(pts) < 2:
            return
        name, colour = P.TRAJECTORY_STYLE[stream]
        stamp = self.sensor_ns if stamp_ns is None else stamp_ns
        self._at(stamp)
        self.rec.log(P.trajectory_segment_path(stream, trail.segment),
                     rr.LineStrips3D([pts], colors=[colour], radii=-2.5, labels=[name] if trail.segment == 0 else None))
        trail.last_logged_ns = stamp
        trail.dirty = False

    def finish(self) -> None:
        """Log the trajectory points not yet logged (the rate limit may have held them back)."""
        for stream, trail in self._trails.items():
            if trail.dirty:
                self.log_trail(stream)

    # -------------------------------------------------------------------------------------- map
    def fly_map(self, msg: m.FlyMap) -> None:
        """Keyframe populations transformed into the map frame (one point cloud) and keyframe positions.
        Re-logged only when the keyframe set changed."""
        signature = tuple((k.id, len(k.points)) for k in msg.keyframes)
        if signature == self._map_signature:
            return
        self._map_signature = signature
        stamp = msg.header.stamp_ns or self.sensor_ns
        self._at(stamp)
        if not msg.keyframes:
            self.rec.log(P.MAP_POINTS, rr.Clear(recursive=False))
            self.rec.log(P.MAP_KEYFRAMES, rr.Clear(recursive=False))
            return
        clouds, fits = [], []
        for kf in msg.keyframes:  # a loop over keyframes; the points of each are transformed at once
            if len(kf.points) != len(kf.fitness):
                raise ValueError(f"keyframe {kf.id}: {len(kf.points)} points but {len(kf.fitness)} fitness values")
            R = matrix_from_quat(kf.orientation)
            clouds.append(kf.points.astype(np.float64) @ R.T + kf.position)
            fits.append(kf.fitness)
        cloud, fit = np.concatenate(clouds), np.concatenate(fits)
        idx = subsample(len(cloud), self.max_map_points, self._rng)
        cloud, fit = cloud[idx], fit[idx]
        colours = (fitness_colours(fit).astype(np.float32) * 0.5 + np.array([70, 110, 160]) * 0.5).astype(np.uint8)
        self.rec.log(P.MAP_POINTS, rr.Points3D(cloud, colors=colours, radii=-1.5))
        kf_pos = np.array([k.position for k in msg.keyframes])
        self.rec.log(P.MAP_KEYFRAMES, rr.Points3D(kf_pos, colors=[(255, 200, 0)], radii=-4.0,
                                                  labels=[str(k.id) for k in msg.keyframes], show_labels=False))

    # ------------------------------------------------------------------------------- planning
    def _planner_seen(self) -> None:
        if not self.planner_layout:
            self.planner_layout = True
            self.rec.send_blueprint(P.blueprint(planner=True))

    def field(self, msg: m.HarmonicField) -> None:
        """The harmonic field as a heat-map image (map +y up) with the planned path on it and in 3-D."""
        self._planner_seen()
        stamp = msg.header.stamp_ns or self.sensor_ns
        self._at(stamp)
        img = field_image(msg.values)
        ok, buf = cv2.imencode(".png", cv2.cvtColor(img, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_PNG_COMPRESSION, 1])
        if not ok:
            raise ValueError("could not PNG-encode the harmonic field")
        self.rec.log(P.FIELD, rr.EncodedImage(contents=buf.tobytes(), media_type="image/png"))
        path = msg.path_xy
        if path is None or len(path) < 2:
            self.rec.log(P.FIELD_PATH, rr.Clear(recursive=False))
            self.rec.log(P.PLANNED_PATH_3D, rr.Clear(recursive=False))
            return
        px = field_pixels(path, msg.origin_xy, msg.resolution_m, img.shape[0])
        self.rec.log(P.FIELD_PATH, rr.LineStrips2D([px], colors=[(80, 255, 255)], radii=-1.5, draw_order=10.0))
        xyz = np.column_stack([path, np.full(len(path), 0.02)])
        self.rec.log(P.PLANNED_PATH_3D, rr.LineStrips3D([xyz], colors=[(80, 255, 255)], radii=-2.0))

    def target(self, msg: m.Target) -> None:
        self._at(msg.header.stamp_ns or self.sensor_ns)
        self.rec.log(P.TARGET_3D, rr.Points3D([[msg.x, msg.y, 0.0]], radii=[msg.radius_m], colors=[(255, 60, 200)],
                                             labels=["target"]))

    def command(self, msg: m.VelocityCommand) -> None:
        """Commanded speeds as scalars; stops (and their reason) as events."""
        self._planner_seen()
        stamp = msg.header.stamp_ns or self.sensor_ns
        self._at(stamp)
        self.rec.log(f"{P.CMD}/linear_mps", rr.Scalars(msg.linear_mps))
        self.rec.log(f"{P.CMD}/angular_radps", rr.Scalars(msg.angular_radps))
        stop = (msg.stop, msg.reason)
        if stop != self._last_stop and (msg.stop or self._last_stop is not None):
            self._event(f"planner: {'stop: ' + msg.reason if msg.stop else 'moving'}", "WARN" if msg.stop else "INFO")
        self._last_stop = stop

    # ---------------------------------------------------------------------------------- health
    def _series(self, path: str, service: str, label: str, value: float) -> None:
        """One scalar; the first time a series appears its legend name and service colour are set."""
        if path not in self._series_styled:
            colour = self._service_colour.setdefault(
                service, SERVICE_PALETTE[len(self._service_colour) % len(SERVICE_PALETTE)])
            self.rec.log(path, rr.SeriesLines(names=label, colors=[colour]), static=True)
            self._series_styled.add(path)
        self.rec.log(path, rr.Scalars(value))

    def heartbeat(self, msg: m.Heartbeat) -> None:
        """A service's progress rate, other rates and problem counters as time series."""
        svc = P.service_part(msg.service)
        self._at(self.sensor_ns)
        for name, value in msg.rates.items():
            if not isinstance(value, (int, float)):
                continue
            if name == "progress_per_s":
                self._series(f"{P.PROGRESS}/{svc}", msg.service, msg.service, float(value))
            else:
                self._series(f"{P.RATES}/{svc}/{P.service_part(name)}", msg.service, f"{msg.service} {name}",
                             float(value))
        for name, value in msg.counters.items():
            if isinstance(value, (int, float)) and PROBLEM_COUNTER.search(name):
                self._series(f"{P.PROBLEMS}/{svc}/{P.service_part(name)}", msg.service, f"{msg.service} {name}",
                             float(value))
        if msg.state != self._last_state.get(msg.service):
            self._event(f"{msg.service}: {msg.state}", "INFO" if msg.state in ("running", "starting") else "WARN")
            self._last_state[msg.service] = msg.state

    def liveliness(self, service: str, alive: bool) -> None:
        """1 while the service's liveliness token exists, 0 after it vanished (exit or crash)."""
        if alive and service == "planner":
            self._planner_seen()
        self._at(self.sensor_ns)
        self._series(f"{P.ALIVE}/{P.service_part(service)}", service, service, 1.0 if alive else 0.0)
        self._event(f"{service}: {'alive' if alive else 'gone'}", "INFO" if alive else "WARN")
