"""The entity tree the bridge logs into, and the blueprint that lays it out on first open.

World entities live under ``world/`` in the map frame (REP-103, z up). The robot's pose moves
``world/robot``; the left camera's optical frame is ``world/robot/camera`` (T_base_camera), so flies,
which travel in that optical frame, are logged there and Rerun's transform hierarchy places them.
The left image sits under a Pinhole at ``world/robot/camera/left`` (the image plane of that frame), so
it appears both in the 3-D view (as the camera frustum) and in its own 2-D view with the projected flies.
"""
from __future__ import annotations

import rerun as rr
import rerun.blueprint as rrb

WORLD = "world"
ROBOT = "world/robot"
CAMERA = "world/robot/camera"            # left optical frame (RDF)
FLIES = "world/robot/camera/flies"       # Points3D in the optical frame
LEFT = "world/robot/camera/left"         # Pinhole + left image
LEFT_FLIES = "world/robot/camera/left/flies"   # Points2D on the left image
RIGHT = "images/right"                   # right image (2-D only)
RIGHT_FLIES = "images/right/flies"       # the same flies at their right-image projection
SONAR_POINTS = "world/robot/sonar_points"  # fusion's sonar echoes, in base_link
MAP_POINTS = "world/map/points"
MAP_KEYFRAMES = "world/map/keyframes"
TRAJECTORIES = "world/trajectories"
PLANNED_PATH_3D = "world/planner/path"
TARGET_3D = "world/planner/target"
FIELD = "planner/field"
FIELD_PATH = "planner/field/path"
CMD = "plots/cmd"
PROGRESS = "plots/progress"              # progress_per_s per service
RATES = "plots/rates"                    # other rates per service
PROBLEMS = "plots/problems"              # rejected / skipped / dropped / error counters
ALIVE = "plots/alive"                    # liveliness: 1 while the service's token exists
EVENTS = "events"                        # TextLog of state changes, stop reasons, pose rejections

# Timelines
STAMP = "stamp"          # sensor time (envelope stamp_ns), a timestamp timeline
FRAME_SEQ = "frame_seq"  # stereo frame sequence number

# Trajectory sources: bus stream → (entity name, colour)
TRAJECTORY_STYLE = {
    "slam/pose": ("slam", (255, 150, 30)),
    "fusion/pose": ("fusion", (60, 220, 90)),
    "fusion/odom": ("odom", (120, 150, 255)),
    "truth/pose": ("truth", (240, 240, 240)),
}


def trajectory_path(stream: str) -> str:
    return f"{TRAJECTORIES}/{TRAJECTORY_STYLE[stream][0]}"


def trajectory_segment_path(stream: str, segment: int) -> str:
    """Trajectories are logged in segments (see common.viz.logger.Trail), one entity each."""
    return f"{trajectory_path(stream)}/{segment:05d}"


def service_part(name: str) -> str:
    """A service or counter name made safe as one entity-path part."""
    return rr.escape_entity_path_part(name or "unnamed")


def blueprint(planner: bool = True) -> rrb.Blueprint:
    """Layout: the 3-D world and health plots on the left; the left image with flies, the right image
    and, with ``planner``, the harmonic field and the commands on the right (a run without a planner, a
    replayed recording or a camera, gives the images that space). Sensor time is the default timeline."""
    world = rrb.Spatial3DView(
        name="World (map frame)", origin=WORLD,
        eye_controls=rrb.EyeControls3D(position=(-2.0, -3.0, 2.5), look_target=(1.5, 0.0, 0.3), eye_up=(0, 0, 1)),
    )
    left = rrb.Spatial2DView(name="Left image + flies", origin=LEFT)
    right = rrb.Spatial2DView(name="Right image", origin=RIGHT)
    field = rrb.Spatial2DView(name="Harmonic field + path", origin=FIELD)
    cmd = rrb.TimeSeriesView(name="Commands", origin=CMD)
    health = rrb.Tabs(
        rrb.TimeSeriesView(name="Progress /s", origin=PROGRESS),
        rrb.TimeSeriesView(name="Rates", origin=RATES),
        rrb.TimeSeriesView(name="Problems", origin=PROBLEMS),
        rrb.TimeSeriesView(name="Alive", origin=ALIVE),
        rrb.TextLogView(name="Events", origin=EVENTS),
    )
    return rrb.Blueprint(
        rrb.Horizontal(
            rrb.Vertical(world, health, row_shares=[3, 1.3]),
            rrb.Vertical(left, right, rrb.Horizontal(field, cmd), row_shares=[1, 1, 1]) if planner
            else rrb.Vertical(left, right, row_shares=[1, 1]),
            column_shares=[3, 2],
        ),
        rrb.BlueprintPanel(state="collapsed"),
        rrb.SelectionPanel(state="collapsed"),
        rrb.TimePanel(timeline=STAMP, state="collapsed", play_state="following"),
    )
