"""The planner service and its core: a wall of fit flies ahead blocks the straight way, young flies do not,
and the live service steers towards its target from the bus's inputs."""
from __future__ import annotations

import ast
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from common import messages as m
from common.bus import BusOptions, Node
from common.camera import StereoCalibration
from common.fly.selection import fittest
from common.geometry import planar_pose
from common.planning import PlannerConfig
from common.planning.core import PlannerCore, PlannerServiceConfig
from tests.helpers import hub, start_module, stop, wait_until

# Camera looking along base_link x (optical z forward, x right, y down), 0.3 m up.
T_BASE_CAMERA = np.array([[0, 0, 1, 0.0], [-1, 0, 0, 0.0], [0, -1, 0, 0.3], [0, 0, 0, 1.0]])


def test_fittest_keeps_the_top_fraction_above_the_floor_and_never_non_finite_flies():
    f = np.array([0.9, 0.01, 0.5, -np.inf, np.nan, 0.3, 0.02, 0.7], np.float32)
    assert list(fittest(f, 0.25)) == [0, 7]                  # fittest first
    assert list(fittest(f, 0.5, 0.05)) == [0, 7, 2, 5]
    assert list(fittest(f, 0.5, 0.4)) == [0, 7, 2]           # min_fitness is a floor under the top fraction
    assert list(fittest(f, 1.0, 0.0)) == [0, 7, 2, 5, 6, 1]  # −inf and NaN never
    assert list(fittest(np.ones(10, np.float32), 0.5)) == list(np.argsort(-np.ones(10))[:5])   # ties: still half
    assert len(fittest(np.zeros(0, np.float32), 0.5)) == 0


def _wall_population(fitness: float, seq: int = 1, camera_x: float = 0.0) -> m.FlyPopulation:
    """Flies on a wall across the corridor 1.5 m ahead of the odom origin, seen by a camera ``camera_x``
    ahead of it."""
    rng = np.random.default_rng(seq)
    n = 3000
    pts = np.stack([rng.uniform(-1.5, 1.5, n), rng.uniform(-0.2, 0.25, n), np.full(n, 1.5 - camera_x)], 1)
    T_odom_camera = T_BASE_CAMERA.copy()
    T_odom_camera[0, 3] = camera_x
    return m.FlyPopulation(positions=pts.astype(np.float32), fitness=np.full(n, fitness, np.float32), generation=500,
                           source_seq=seq, T_odom_camera=T_odom_camera,
                           header=m.header(0, seq * 10**8, m.CAMERA_LEFT_OPTICAL))


def _core() -> PlannerCore:
    core = PlannerCore(PlannerConfig(), PlannerServiceConfig(extent=(-1.0, -2.0, 6.0, 2.0), solve_ms=200.0))
    core.on_calibration(m.calibration_to_msg(StereoCalibration.ideal(320, 240, T_base_camera=T_BASE_CAMERA), 1, 1))
    core.on_pose(m.pose_msg(planar_pose(0.0, 0.0, 0.0), stamp_ns=10**8, status="ok"))
    core.on_map_to_odom(_identity_map_to_odom())
    core.on_target(m.Target(x=4.0, y=0.0, radius_m=0.3))
    return core


def _identity_map_to_odom() -> m.TransformMsg:
    return m.TransformMsg(child_frame_id=m.ODOM, translation=np.zeros(3), rotation=np.array([0.0, 0.0, 0.0, 1.0]),
                          header=m.header(0, 10**8, m.MAP))


def test_the_robot_stays_still_until_the_localiser_has_a_map():
    core = _core()
    core.map_to_odom = None                      # a pose from odometry, but no map yet
    assert not core.on_population(_wall_population(0.5))   # the young flies are no evidence yet
    assert not core.planner.grid.occupied().any()
    for _ in range(20):
        cmd = core.cycle(10**8)
    assert cmd.stop and cmd.reason == "waiting for the localiser's map", cmd
    core.on_map_to_odom(_identity_map_to_odom())
    cmd, _ = _heading_after(core)
    assert not cmd.stop and cmd.linear_mps > 0, cmd
    alone = PlannerCore(PlannerConfig(), PlannerServiceConfig(extent=(-1.0, -2.0, 6.0, 2.0), solve_ms=200.0,
                                                              wait_for_map=False))
    alone.on_calibration(core.calibration)
    alone.on_pose(core.pose)
    alone.on_target(core.target)
    cmd, _ = _heading_after(alone)
    assert not cmd.stop and cmd.linear_mps > 0, cmd


def _heading_after(core: PlannerCore) -> tuple[m.VelocityCommand, np.ndarray]:
    for _ in range(20):
        cmd = core.cycle(10**8)
        if core.report.converged:
            break
    return cmd, core.field_message(10**8).values


def test_a_wall_of_fit_flies_blocks_the_way_and_young_flies_do_not():
    free = _core()
    free.on_population(_wall_population(0.01))          # random-looking flies: below min_fitness
    cmd_free, field_free = _heading_after(free)
    assert not cmd_free.stop and cmd_free.linear_mps > 0 and abs(cmd_free.angular_radps) < 0.2, cmd_free

    walled = _core()
    for seq in range(1, 4):                              # seen from three places 0.1 m apart
        walled.on_population(_wall_population(0.5, seq, camera_x=0.1 * seq))
    cmd_wall, field_wall = _heading_after(walled)
    assert np.isinf(field_wall).sum() > np.isinf(field_free).sum() + 20
    assert cmd_wall.reason != "following field" or cmd_wall.linear_mps < cmd_free.linear_mps, cmd_wall


def test_a_converged_field_takes_in_new_evidence_at_solve_hz_not_every_cycle():
    core = _core()
    _heading_after(core)                                 # converged on the empty corridor at t = 0.1 s
    blocked_before = np.isinf(core.field_message(10**8).values).sum()
    for seq in range(1, 4):
        core.on_population(_wall_population(0.5, seq, camera_x=0.1 * seq))
    period_ns = int(1e9 / core.settings.solve_hz)
    core.cycle(10**8 + period_ns // 2)                   # the next command cycle: the last field still
    assert np.isinf(core.field_message(10**8).values).sum() == blocked_before
    core.cycle(10**8 + period_ns)                        # one solve period on: the wall is in the field
    assert np.isinf(core.field_message(10**8).values).sum() > blocked_before + 20


def test_planner_service_steers_towards_the_target_and_publishes_its_field(tmp_path, zenoh_port):
    proc = start_module("services.planner", "--extent", "-1", "-2", "6", "2", "--target", "4", "0",
                        port=zenoh_port, log_path=tmp_path / "planner.log")
    cmds, fields = [], []
    try:
        with Node("feeder", BusOptions(hub=hub(zenoh_port)), handle_signals=False) as node:
            node.subscribe("planner/cmd_vel", m.VelocityCommand, cmds.append)
            node.subscribe("planner/field", m.HarmonicField, fields.append)
            assert wait_until(lambda: cmds, 30), (tmp_path / "planner.log").read_text()[-2000:]
            assert cmds[-1].stop and cmds[-1].reason == "no pose"
            calib = StereoCalibration.ideal(320, 240, T_base_camera=T_BASE_CAMERA)
            node.publisher("stereo/calibration", latched=True).publish(m.calibration_to_msg(calib, 1, 1))
            poses, transforms = node.publisher("fusion/pose"), node.publisher("slam/map_to_odom")
            deadline = time.monotonic() + 30
            while time.monotonic() < deadline and not (cmds and cmds[-1].reason == "following field"):
                poses.publish(m.pose_msg(planar_pose(0.0, 0.0, 0.0), stamp_ns=time.time_ns(), status="ok"))
                transforms.publish(_identity_map_to_odom())
                time.sleep(0.1)
            assert cmds[-1].reason == "following field", [c.reason for c in cmds[-5:]]
            assert cmds[-1].linear_mps > 0
            assert wait_until(lambda: fields and fields[-1].path_xy is not None, 10)
            assert stop(proc) == 0, (tmp_path / "planner.log").read_text()[-2000:]
            assert wait_until(lambda: cmds[-1].reason == "planner stopped", 5)
            assert cmds[-1].stop
    finally:
        if proc.poll() is None:
            stop(proc)


def test_a_restarted_planner_takes_the_latched_map_to_odom(tmp_path, zenoh_port):
    """The supervisor latches slam/map_to_odom: a planner started after it was published drives on
    without waiting for the localiser's next one."""
    with Node("latch-holder", BusOptions(hub=hub(zenoh_port)), handle_signals=False) as node:
        node.publisher("slam/map_to_odom", latched=True).publish(_identity_map_to_odom())
        proc = start_module("services.planner", "--extent", "-1", "-2", "6", "2", "--target", "4", "0",
                            port=zenoh_port, log_path=tmp_path / "planner.log")
        cmds = []
        try:
            node.subscribe("planner/cmd_vel", m.VelocityCommand, cmds.append)
            calib = StereoCalibration.ideal(320, 240, T_base_camera=T_BASE_CAMERA)
            node.publisher("stereo/calibration", latched=True).publish(m.calibration_to_msg(calib, 1, 1))
            poses = node.publisher("fusion/pose")
            deadline = time.monotonic() + 20
            while time.monotonic() < deadline and not (cmds and cmds[-1].reason == "following field"):
                poses.publish(m.pose_msg(planar_pose(0.0, 0.0, 0.0), stamp_ns=time.time_ns(), status="ok"))
                time.sleep(0.1)
            assert cmds and cmds[-1].reason == "following field", [c.reason for c in cmds[-5:]]
        finally:
            stop(proc)


def _lone_fly(seq: int, x_cam: float = 0.0) -> m.FlyPopulation:
    """A population whose only fly in the height band sits 0.8 m ahead of the camera (at 0.3 m above the
    floor), the rest far overhead."""
    pts = np.array([[x_cam, 0.15, 0.8]] + [[0.0, -3.0, 3.0]] * 50, np.float32)
    return m.FlyPopulation(positions=pts, fitness=np.full(len(pts), 0.5, np.float32), generation=500,
                           source_seq=seq, T_odom_camera=T_BASE_CAMERA.copy(),
                           header=m.header(0, seq * 10**8, m.CAMERA_LEFT_OPTICAL))


def test_a_standing_robot_re_reporting_one_fly_does_not_make_it_an_obstacle():
    """A population republished 10 times a second from the same place is the same view: one fly stuck at
    a wrong depth stays weak evidence; a surface of flies is still an obstacle."""
    core = _core()
    for seq in range(1, 51):                     # 5 s standing, the same lone fly every 0.1 s
        core.on_population(_lone_fly(seq))
    assert not core.planner.grid.occupied().any()
    wall = _core()
    for seq in range(1, 101):                    # 10 s standing before a wall: persistent evidence counts
        wall.on_population(_wall_population(0.5, seq))
    assert wall.planner.grid.occupied().sum() > 20


def _cluster_of_copies(seq: int, camera_x: float = 0.0) -> m.FlyPopulation:
    """Near-copies of one fit fly (the Parisian population breeds them) 0.5 m ahead at 0.3 m up, plus an
    average population far overhead, seen by a camera ``camera_x`` ahead of the odom origin."""
    rng = np.random.default_rng(seq)
    copies = np.array([0.0, 0.15, 0.5 - camera_x]) + rng.normal(0.0, 0.003, (16, 3))
    pts = np.vstack([copies, np.tile([0.0, -3.0, 3.0], (200, 1))])
    fit = np.r_[np.full(16, 0.6), np.full(200, 0.5)]
    T_odom_camera = T_BASE_CAMERA.copy()
    T_odom_camera[0, 3] = camera_x
    return m.FlyPopulation(positions=pts.astype(np.float32), fitness=fit.astype(np.float32), generation=500,
                           source_seq=seq, T_odom_camera=T_odom_camera,
                           header=m.header(0, seq * 10**8, m.CAMERA_LEFT_OPTICAL))


def test_one_view_of_a_cluster_of_fly_copies_is_no_obstacle_but_two_views_are():
    """16 near-copies of one fly, seen once, made a phantom obstacle 0.5 m ahead of the standing robot at
    the start of the demo; a point confirmed from a second viewpoint is an obstacle."""
    once = _core()
    for seq in range(1, 6):                      # lives half a second in front of the standing robot
        once.on_population(_cluster_of_copies(seq))
    assert not once.planner.grid.occupied().any()
    cmd, _ = _heading_after(once)
    assert not cmd.stop and cmd.linear_mps > 0 and abs(cmd.angular_radps) < 0.2, cmd
    twice = _core()
    twice.on_population(_cluster_of_copies(1))
    twice.on_population(_cluster_of_copies(2, camera_x=0.1))
    assert twice.planner.grid.occupied().any()


def test_new_view_settings_must_be_positive():
    with pytest.raises(ValueError, match="new_view"):
        PlannerServiceConfig(new_view_s=0.0)
    with pytest.raises(ValueError, match="view_cell_cap"):
        PlannerServiceConfig(view_cell_cap=float("nan"))


KERNELS_LOADED_BY_CYCLES = """
import sys
from common.planning import PlannerConfig
from common.planning.core import warm_up
from common.warmup import kernel_modules, kernels
from tests.test_planner_service import _core, _heading_after, _wall_population
found = kernels([name for name in kernel_modules() if name.startswith("common.planning")])
if sys.argv[1] == "warm":
    warm_up(PlannerConfig())
before = {k: len(d.signatures) for k, d in found.items()}
core = _core()
_heading_after(core)                                  # a solved field, then a wall cuts cells out of it
for seq in range(1, 4):
    core.on_population(_wall_population(0.5, seq, camera_x=0.1 * seq))
_heading_after(core)
core.cycle(10**9)
print(sorted(k for k, d in found.items() if len(d.signatures) > before[k]))
"""


@pytest.mark.parametrize("warm", ["warm", "cold"])
def test_the_warm_up_leaves_no_kernel_for_the_planners_cycles_to_load(warm):
    # A fresh process, as the service is: numba loads each kernel from its cache on first use, and in a
    # run that first use was the first cycles with a population (half a second of CPU while frames flow).
    out = subprocess.run([sys.executable, "-c", KERNELS_LOADED_BY_CYCLES, warm], capture_output=True, text=True,
                         cwd=Path(__file__).resolve().parent.parent, timeout=300)
    assert out.returncode == 0, out.stderr
    loaded = ast.literal_eval(out.stdout.strip().splitlines()[-1])
    assert (loaded == []) == (warm == "warm"), loaded
