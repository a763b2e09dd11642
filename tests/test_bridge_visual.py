"""The message → Rerun mapping, without the bus: synthetic messages into an .rrd, read back with the SDK."""
from __future__ import annotations

import subprocess

import numpy as np
import pytest
import rerun as rr

from common import messages as m
from common.images import make_frame
from common.viz import RerunLogger, blueprint
from common.viz import paths as P
from common.viz.colours import field_image, field_pixels, fitness_colours
from tests import bridge_scene
from tests.bridge_scene import rrd_rows, trajectory_points
from tests.helpers import ROOT

RERUN = ROOT / ".venv" / "bin" / "rerun"


def _record(path, feed, **kwargs):
    """Run ``feed(logger)`` on a fresh file-backed recording and close it."""
    rec = rr.RecordingStream("flyslam-test")
    rec.save(str(path), default_blueprint=blueprint())
    logger = RerunLogger(rec, **kwargs)
    feed(logger)
    logger.finish()
    rec.flush()
    rec.disconnect()
    return logger


def _play(logger, **scene):
    for stream, msg in bridge_scene.messages(**scene):
        logger.handle(stream, msg)
    logger.liveliness("evolver", True)
    logger.liveliness("evolver", False)


def _by_stamp(cols, name):
    """Values of one column ordered by the sensor timeline."""
    order = np.argsort(np.array(cols[P.STAMP], dtype=np.int64), kind="stable")
    values = cols[name]
    return [values[i] for i in order]


@pytest.fixture(scope="module")
def synthetic_rrd(tmp_path_factory):
    path = tmp_path_factory.mktemp("bridge") / "synthetic.rrd"
    frames, flies = 30, 2000
    _record(path, lambda lg: _play(lg, frames=frames, flies=flies), max_flies=500)
    return path, rrd_rows(path), frames


def test_synthetic_run_fills_every_view_and_the_file_verifies(synthetic_rrd):
    path, rows, frames = synthetic_rrd
    expected = {
        P.LEFT: "EncodedImage:blob", P.RIGHT: "EncodedImage:blob", P.FLIES: "Points3D:positions",
        P.LEFT_FLIES: "Points2D:positions", P.RIGHT_FLIES: "Points2D:positions", P.ROBOT: "Transform3D:translation",
        P.MAP_POINTS: "Points3D:positions", P.MAP_KEYFRAMES: "Points3D:positions", P.FIELD: "EncodedImage:blob",
        P.FIELD_PATH: "LineStrips2D:strips", P.PLANNED_PATH_3D: "LineStrips3D:strips",
        P.TARGET_3D: "Points3D:positions", P.SONAR_POINTS: "Points3D:positions",
        f"{P.CMD}/linear_mps": "Scalars:scalars",
        f"{P.CMD}/angular_radps": "Scalars:scalars", f"{P.PROGRESS}/evolver": "Scalars:scalars",
        f"{P.RATES}/localiser/frames_per_s": "Scalars:scalars", f"{P.PROBLEMS}/planner/rejected": "Scalars:scalars",
        f"{P.ALIVE}/evolver": "Scalars:scalars", P.EVENTS: "TextLog:text",
    }
    expected.update({P.trajectory_segment_path(s, 0): "LineStrips3D:strips" for s in P.TRAJECTORY_STYLE})
    for entity, column in expected.items():
        assert f"/{entity}" in rows, f"{entity} was not logged"
        assert rows[f"/{entity}"].get(column), f"{entity} has no {column}"
    assert len(rows[f"/{P.LEFT}"]["EncodedImage:blob"]) == frames
    assert rows[f"/{P.LEFT}"]["EncodedImage:media_type"][0] == ["image/jpeg"]
    # Static calibration: the Pinhole under the camera and the base_link → camera transform.
    pinhole = rows[f"/{P.LEFT}"]["static:Pinhole:image_from_camera"][0][0]
    calib = bridge_scene.calibration()
    assert np.allclose(np.array(pinhole).reshape(3, 3, order="F")[0, 0], calib.fx)
    assert rows[f"/{P.LEFT}"]["static:Pinhole:resolution"][0] == [[calib.width, calib.height]]
    assert np.allclose(rows[f"/{P.CAMERA}"]["static:Transform3D:translation"][0][0], [0.1, 0.0, 0.4])
    assert rows[f"/{P.WORLD}"]["static:ViewCoordinates:xyz"]
    # Both timelines on images; heartbeats on the sensor timeline, never on frame_seq.
    assert sorted(rows[f"/{P.LEFT}"][P.FRAME_SEQ]) == list(range(1, frames + 1))
    assert P.FRAME_SEQ not in rows[f"/{P.PROGRESS}/evolver"]
    assert all(s is not None for s in rows[f"/{P.PROGRESS}/evolver"][P.STAMP])
    assert [v[0] for v in _by_stamp(rows[f"/{P.ALIVE}/evolver"], "Scalars:scalars")][-1] == 0.0
    result = subprocess.run([str(RERUN), "rrd", "verify", str(path)], capture_output=True, text=True, timeout=60)
    assert result.returncode == 0, result.stderr


def test_flies_are_subsampled_coloured_by_fitness_and_projected_inside_the_images(synthetic_rrd):
    _, rows, _ = synthetic_rrd
    calib = bridge_scene.calibration()
    flies = rows[f"/{P.FLIES}"]
    assert all(len(p) == 500 for p in flies["Points3D:positions"]), "populations of 2000 are cut to max_flies"
    assert all(len(c) == 500 for c in flies["Points3D:colors"])
    for pts in rows[f"/{P.LEFT_FLIES}"]["Points2D:positions"] + rows[f"/{P.RIGHT_FLIES}"]["Points2D:positions"]:
        uv = np.array(pts)
        assert len(uv) > 100
        assert (uv[:, 0] >= 0).all() and (uv[:, 0] < calib.width).all()
        assert (uv[:, 1] >= 0).all() and (uv[:, 1] < calib.height).all()
    # Flies of the last population project where the calibration says.
    last_pos = np.array(_by_stamp(flies, "Points3D:positions")[-1])
    ul, _, v = calib.project(last_pos)
    inside = np.isfinite(ul) & (ul >= 0) & (ul < calib.width) & (v >= 0) & (v < calib.height)
    uv = np.array(_by_stamp(rows[f"/{P.LEFT_FLIES}"], "Points2D:positions")[-1])
    assert np.allclose(uv, np.column_stack([ul[inside], v[inside]]), atol=1e-3)


def test_fitness_colours_run_from_cold_to_hot_and_grey_out_invalid_flies():
    fit = np.array([0.0, 0.5, 1.0, -np.inf], np.float32)
    rgb = fitness_colours(fit)
    assert rgb.shape == (4, 3) and rgb.dtype == np.uint8
    assert rgb[2, 0] > rgb[0, 0] and rgb[0, 2] > rgb[2, 2], "high fitness is red, low is blue"
    assert tuple(rgb[3]) == (90, 90, 90)
    assert (fitness_colours(np.full(3, -np.inf, np.float32)) == 90).all()


def test_trajectories_grow_and_the_fused_pose_moves_the_robot(synthetic_rrd):
    _, rows, frames = synthetic_rrd
    truth = _by_stamp(rows[f"/{P.trajectory_segment_path('truth/pose', 0)}"], "LineStrips3D:strips")
    lengths = [len(strips[0]) for strips in truth]
    assert lengths == sorted(lengths) and lengths[-1] == frames, "the last strip holds every (distinct) pose"
    whole = trajectory_points(rows, "truth/pose")
    assert np.allclose(whole, [bridge_scene.robot_pose(i)[:3, 3] for i in range(frames)])
    robot = np.array(_by_stamp(rows[f"/{P.ROBOT}"], "Transform3D:translation")[-1][0])
    assert np.allclose(robot, trajectory_points(rows, "fusion/pose")[-1]), "world/robot follows fusion/pose"


def test_long_trajectories_are_logged_in_bounded_segments(tmp_path):
    frames = 30
    _record(tmp_path / "seg.rrd", lambda lg: _play(lg, frames=frames, flies=50), trail_segment_points=8)
    rows = rrd_rows(tmp_path / "seg.rrd")
    prefix = f"/{P.trajectory_path('truth/pose')}/"
    segments = [e for e in rows if e.startswith(prefix)]
    assert len(segments) == 5, "30 points in segments of 8 that share their end points: 5 segments"
    for entity in segments:
        assert all(len(s[0]) <= 8 for s in rows[entity]["LineStrips3D:strips"])
    whole = trajectory_points(rows, "truth/pose")
    assert np.allclose(whole, [bridge_scene.robot_pose(i)[:3, 3] for i in range(frames)])


def test_map_keyframes_are_transformed_into_the_map_frame(synthetic_rrd):
    _, rows, _ = synthetic_rrd
    cloud = np.array(rows[f"/{P.MAP_POINTS}"]["Points3D:positions"][-1])
    assert len(cloud) == 1500
    assert np.allclose(cloud[:, 0], bridge_scene.WALL_X, atol=1e-4), "keyframe points land back on the wall"
    assert len(rows[f"/{P.MAP_KEYFRAMES}"]["Points3D:positions"][-1]) == 3


def test_field_image_puts_map_north_up_and_the_path_on_its_cells():
    values = np.tile(np.arange(10, dtype=np.float32)[:, None], (1, 4))  # grows with row index = map +y
    values[0, 0] = -np.inf
    img = field_image(values)
    assert img.shape == (10, 4, 3)
    assert img[0].astype(int).sum() > img[-2].astype(int).sum(), "high values (large y) at the top"
    assert tuple(img[-1, 0]) == (90, 90, 90), "the blocked cell (row 0, col 0) is bottom-left, grey"
    px = field_pixels(np.array([[1.0, 2.0], [1.2, 2.5]]), np.array([1.0, 2.0]), 0.1, 10)
    assert np.allclose(px, [[0, 10], [2, 5]])
    with pytest.raises(ValueError, match="2-D grid"):
        field_image(np.zeros(5))


def test_raw_frames_are_compressed_and_bad_messages_raise_clear_errors(tmp_path):
    calib = bridge_scene.calibration()
    img = bridge_scene.wall_texture(calib.height, calib.width)
    bad_pop = m.FlyPopulation(positions=np.zeros((4, 3), np.float32), fitness=np.zeros(3, np.float32),
                              header=m.header(1, 5))
    errors = []

    def feed(lg):
        lg.handle("stereo/calibration", m.calibration_to_msg(calib))
        lg.handle("stereo/frame", make_frame(img, img, 1, bridge_scene.T0, encoding="rgb8"))
        for stream, msg in (("flies/population", bad_pop), ("odom/pose", m.pose_msg(np.eye(4))),
                            ("truth/pose", m.pose_msg(np.eye(4))), ("odom/wheels", m.WheelOdometry())):
            if stream == "truth/pose":
                msg.position[0] = np.nan
            with pytest.raises(ValueError) as e:
                lg.handle(stream, msg)
            errors.append(str(e.value))

    _record(tmp_path / "raw.rrd", feed)
    rows = rrd_rows(tmp_path / "raw.rrd")
    blob = rows[f"/{P.LEFT}"]["EncodedImage:blob"][0][0]
    assert rows[f"/{P.LEFT}"]["EncodedImage:media_type"][0] == ["image/jpeg"]
    assert bytes(blob[:2]) == b"\xff\xd8" and len(blob) < img.nbytes / 3
    assert "4 positions but 3 fitness" in errors[0]
    assert "odom/pose" in errors[1] and "non-finite" in errors[2] and "WheelOdometry" in errors[3]


def test_a_flood_of_poses_is_logged_at_the_pose_rate_not_the_publishers(tmp_path):
    """1,000 fused poses in one second of sensor time (a 1 kHz publisher, or a flood): the robot moves
    at most 30 times and the trajectory still reaches the last pose to within one period's travel."""
    def feed(lg):
        for i in range(1000):
            T = np.eye(4)
            T[0, 3] = i * 1e-3          # 1 m/s
            lg.handle("fusion/pose", m.pose_msg(T, seq=i + 1, stamp_ns=10**9 + i * 10**6))
    _record(tmp_path / "flood.rrd", feed)
    rows = rrd_rows(tmp_path / "flood.rrd")
    moves = rows[f"/{P.ROBOT}"]["Transform3D:translation"]
    assert 25 <= len(moves) <= 31
    assert trajectory_points(rows, "fusion/pose")[-1][0] > 1.0 - 1 / 30 - 1e-6


def _view_origins(container) -> set[str]:
    """The origins of every view under a blueprint container."""
    origins = set()
    for item in getattr(container, "contents", []):
        if hasattr(item, "origin"):
            origins.add(str(item.origin))
        else:
            origins |= _view_origins(item)
    return origins


def test_the_planners_views_join_the_layout_when_the_planner_shows_up(tmp_path):
    """A replayed recording or a camera has no planner: its run's layout gives the images the space of
    the empty harmonic-field and command views, which come back once the planner is alive."""
    assert P.FIELD in _view_origins(blueprint().root_container)
    assert P.FIELD not in _view_origins(blueprint(planner=False).root_container)
    assert P.LEFT in _view_origins(blueprint(planner=False).root_container)
    rec = rr.RecordingStream("flyslam-test")
    rec.save(str(tmp_path / "run.rrd"), default_blueprint=blueprint(planner=False))
    sent = []
    rec.send_blueprint = lambda bp, **kw: sent.append(bp)
    logger = RerunLogger(rec, planner_layout=False)
    logger.liveliness("evolver", True)
    assert sent == []
    logger.liveliness("planner", True)
    logger.command(m.VelocityCommand(linear_mps=0.1))
    assert len(sent) == 1 and P.FIELD in _view_origins(sent[0].root_container)
    rec.disconnect()
