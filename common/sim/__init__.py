"""World simulator: a scenario (TOML) of textured planes and boxes, a differential-drive robot with a
calibrated stereo rig, wheel odometry and a sonar ring, all deterministic for a seed.

Public API (see `common.sim.simulator` for the stepping contract)::

    from common.sim import load_scenario, Simulator
    scn = load_scenario("recordings/scenarios/corridor.toml")
    sim = Simulator(scn, seed=0, width=640, height=480)
    events = sim.advance(0.02)     # [OdometryReading | SonarReading | CameraDue], stamp order
    frame = sim.render(stamp_ns)   # StereoImages(stamp_ns, left, right, depth, T_map_base)
    sim.set_command(v, omega); sim.truth_pose(); sim.time_ns; sim.finished; sim.calibration
    sim.world.obstacle_segments(z_min, z_max); sim.world.min_clearance(x, y)
"""
from common.sim.scenario import Scenario, ScenarioError, load_scenario, parse_scenario, scenario_path
from common.sim.sensors import OdometryReading, SonarReading
from common.sim.simulator import CameraDue, SimulationError, Simulator, StereoImages
from common.sim.world import World

__all__ = ["Scenario", "ScenarioError", "load_scenario", "parse_scenario", "scenario_path", "OdometryReading",
           "SonarReading", "CameraDue", "SimulationError", "Simulator", "StereoImages", "World"]
