"""A small synthetic run for the bridge tests and the screenshot: a robot driving towards a textured wall,
flies on the wall (and some stray ones), four pose streams, a keyframe map, a harmonic field, commands and
heartbeats — every message the bridge views, as the services would publish them."""
from __future__ import annotations

import cv2
import numpy as np

from common import messages as m
from common.camera import StereoCalibration
from common.geometry import invert, make_transform, planar_pose, pose_from_transform, transform_points
from common.images import make_frame

T0 = 1_700_000_000_000_000_000
DT_NS = 100_000_000
# Left optical frame in base_link (REP-103 body x forward, z up → optical z forward, x right, y down).
R_BASE_OPTICAL = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
T_BASE_CAMERA = make_transform(R_BASE_OPTICAL, [0.1, 0.0, 0.4])
WALL_X = 4.0


def calibration(width=320, height=240) -> StereoCalibration:
    return StereoCalibration.ideal(width, height, baseline=0.12, T_base_camera=T_BASE_CAMERA)


def robot_pose(i: int) -> np.ndarray:
    """T_map_base at step i: forward along x with a gentle weave."""
    return planar_pose(0.04 * i, 0.4 * np.sin(i / 8.0), 0.2 * np.cos(i / 8.0))


def wall_points(n: int, rng) -> np.ndarray:
    """Points (map frame) on the wall x = WALL_X, y ∈ [-2, 2], z ∈ [0, 1.6]."""
    return np.column_stack([np.full(n, WALL_X), rng.uniform(-2, 2, n), rng.uniform(0, 1.6, n)])


def wall_texture(h: int, w: int, seed: int = 1) -> np.ndarray:
    """Soft grey texture (blurred noise) so that the coloured flies stand out on it."""
    rng = np.random.default_rng(seed)
    tex = rng.normal(0, 1, (h // 3, w // 3)).astype(np.float32)
    tex = cv2.GaussianBlur(cv2.resize(tex, (w, h), interpolation=cv2.INTER_CUBIC), (0, 0), 2.0)
    tex = np.clip(110 + 35 * tex / tex.std(), 0, 255).astype(np.uint8)
    return np.repeat(tex[:, :, None], 3, axis=2)


def population(i: int, calib: StereoCalibration, n: int, rng) -> m.FlyPopulation:
    T_cam_map = invert(robot_pose(i) @ T_BASE_CAMERA)
    on_wall = transform_points(T_cam_map, wall_points(n * 3 // 4, rng))
    stray = rng.uniform([-2, -1.5, 0.5], [2, 1.5, 6], (n - len(on_wall), 3))
    pos = np.concatenate([on_wall, stray]).astype(np.float32)
    fit = np.concatenate([rng.uniform(0.5, 0.95, len(on_wall)), rng.uniform(0.0, 0.3, len(stray))]).astype(np.float32)
    fit[-5:] = -np.inf  # outside the images
    T_odom_cam = robot_pose(i) @ T_BASE_CAMERA
    return m.FlyPopulation(positions=pos, fitness=fit, generation=10 * i, source_seq=i + 1, T_odom_camera=T_odom_cam,
                           header=m.header(i + 1, T0 + i * DT_NS, m.CAMERA_LEFT_OPTICAL))


def fly_map(calib: StereoCalibration, n_per_kf: int, rng) -> m.FlyMap:
    kfs = []
    for k, i in enumerate((0, 10, 20)):
        T_map_cam = robot_pose(i) @ T_BASE_CAMERA
        pts = transform_points(invert(T_map_cam), wall_points(n_per_kf, rng)).astype(np.float32)
        p, q = pose_from_transform(T_map_cam)
        kfs.append(m.Keyframe(id=k, stamp_ns=T0 + i * DT_NS, position=p, orientation=q, points=pts,
                              fitness=rng.uniform(0.5, 0.9, n_per_kf).astype(np.float32)))
    return m.FlyMap(keyframes=kfs, header=m.header(1, T0 + 20 * DT_NS, m.MAP))


def harmonic_field(i: int, target=(3.5, 0.0)) -> m.HarmonicField:
    """A log-potential falling with distance to the target, −inf inside a box obstacle."""
    res, origin = 0.05, np.array([-0.5, -2.0])
    ys, xs = np.mgrid[0:80, 0:100]
    x, y = origin[0] + (xs + 0.5) * res, origin[1] + (ys + 0.5) * res
    values = -np.hypot(x - target[0], y - target[1])
    values[(np.abs(x - 2.0) < 0.3) & (np.abs(y - 0.8) < 0.3)] = -np.inf
    start = robot_pose(i)[:2, 3]
    path = np.linspace(start, target, 20)
    return m.HarmonicField(values=values.astype(np.float32), origin_xy=origin, resolution_m=res, path_xy=path,
                           header=m.header(i + 1, T0 + i * DT_NS, m.MAP))


def messages(frames: int = 30, flies: int = 2000, seed: int = 0, calib: StereoCalibration | None = None,
             encoding: str = "jpeg"):
    """Yield (stream, message) in publication order."""
    rng = np.random.default_rng(seed)
    calib = calib or calibration()
    yield "stereo/calibration", m.calibration_to_msg(calib, 1, T0)
    yield "planner/target", m.Target(x=3.5, y=0.0, radius_m=0.3, header=m.header(1, T0, m.MAP))
    tex = wall_texture(calib.height, calib.width + 16)
    for i in range(frames):
        t = T0 + i * DT_NS
        shift = i % 8
        left = np.ascontiguousarray(tex[:, shift:shift + calib.width])
        right = np.ascontiguousarray(tex[:, shift + 6:shift + 6 + calib.width])
        yield "stereo/frame", make_frame(left, right, i + 1, t, encoding=encoding)
        yield "flies/population", population(i, calib, flies, rng)
        T = robot_pose(i)
        drift = planar_pose(0.0, 0.01 * i, 0.004 * i)
        yield "truth/pose", m.pose_msg(T, seq=i + 1, stamp_ns=t)
        yield "fusion/odom", m.pose_msg(drift @ T, seq=i + 1, stamp_ns=t, frame_id=m.ODOM)
        yield "slam/pose", m.pose_msg(planar_pose(*rng.normal(0, 0.02, 3)) @ T, seq=i + 1, stamp_ns=t)
        yield "fusion/pose", m.pose_msg(planar_pose(*rng.normal(0, 0.01, 3)) @ T, seq=i + 1, stamp_ns=t)
        echoes = np.array([[WALL_X - T[0, 3], a, 0.2] for a in (-0.3, 0.0, 0.3)], np.float32)
        yield "fusion/sonar_points", m.FlyPopulation(positions=echoes, fitness=np.ones(3, np.float32), source_seq=i + 1,
                                                     header=m.header(i + 1, t, m.BASE_LINK))
        last = i == frames - 1
        yield "planner/cmd_vel", m.VelocityCommand(linear_mps=0.4, angular_radps=0.2 * np.sin(i / 5), stop=last,
                                                   reason="target reached" if last else "",
                                                   header=m.header(i + 1, t, m.BASE_LINK))
        if i % 5 == 0:
            yield "planner/field", harmonic_field(i)
            for svc, rate in (("evolver", 9.5), ("localiser", 4.0), ("planner", 2.0)):
                yield f"status/{svc}", m.Heartbeat(service=svc, pid=100, progress=i, state="running",
                                                   rates={"progress_per_s": rate + 0.1 * i, "frames_per_s": rate},
                                                   counters={"stereo_frame_received": i, "rejected": i // 10,
                                                             "stereo_frame_skipped": i // 3},
                                                   header=m.header(i + 1, 5 + i, ""))
        if i == min(20, frames - 1):
            yield "slam/map", fly_map(calib, 500, rng)


def rrd_rows(path) -> dict[str, dict[str, list]]:
    """{entity path: {column: [row values...]}} of a .rrd file, read back with the Rerun SDK; static rows
    are listed under the column name prefixed with 'static:'; timestamp timelines come as int64 ns."""
    import pyarrow as pa
    import rerun as rr

    out: dict[str, dict[str, list]] = {}
    for chunk in rr.chunk.RrdReader(str(path)).store().stream():
        cols = out.setdefault(chunk.entity_path, {})
        batch = chunk.to_record_batch()
        for name in batch.schema.names:
            key = f"static:{name}" if chunk.is_static else name
            col = batch.column(name)
            if pa.types.is_timestamp(col.type):  # timestamp timelines as int64 ns
                col = col.cast(pa.int64())
            cols.setdefault(key, []).extend(col.to_pylist())
    return out


def trajectory_points(rows: dict, stream: str) -> np.ndarray:
    """The whole logged trajectory of a pose stream: the last strip of each segment entity, joined
    (segments share their boundary point)."""
    from common.viz import paths as P

    prefix = f"/{P.trajectory_path(stream)}/"
    parts = []
    for entity in sorted(e for e in rows if e.startswith(prefix)):
        cols = rows[entity]
        last = int(np.argmax(np.array(cols["stamp"], dtype=np.int64)))
        strip = np.array(cols["LineStrips3D:strips"][last][0])
        parts.append(strip if not parts else strip[1:])
    return np.concatenate(parts) if parts else np.zeros((0, 3))
