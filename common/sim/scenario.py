"""Scenario files: a TOML description of a world, a robot and its sensors, checked on load.

A scenario is plain data (dataclasses); `common.sim.world.World` turns it into render/collision geometry.
Every error is a `ScenarioError` naming the file and the field, e.g.
``corridor.toml: walls[2].from: expected 2 numbers, got 3``; unknown keys are errors too (typos must not
silently fall back to defaults).

Top-level layout (all lengths in metres, angles in degrees, map frame: z up, floor at z = 0)::

    name = "corridor"                 description = "..."
    [robot]    start = [x, y, yaw_deg]   radius = 0.22
    target = [x, y]                   # planner goal (optional)
    [camera] / [odometry] / [sonar] / [lighting]   # overrides of CameraConfig, OdometryConfig, ...
    [textures.NAME]  kind = "brick" ...  # named textures (see common.sim.textures for kinds)
    [floor]   x = [x0, x1]  y = [y0, y1]  z = 0.0  texture = ...
    [ceiling] x = [...]  y = [...]  z = 2.5  texture = ...
    [[walls]]   from = [x, y]  to = [x, y]  z = [z0, z1]  texture = ...        (solid)
    [[doors]] / [[posters]]  from, to, z, texture   # flat decals on a wall, visible from the LEFT of
                                                    # from→to (set flip = true for the other side)
    [[panels]]  origin = [x,y,z]  u = [..3]  v = [..3]  texture  solid = false  decal = false
                # a decal panel is one-sided: visible from the side u × v points to
    [[boxes]]   center = [x, y]  size = [sx, sy, sz]  yaw = 0  z0 = 0  texture = ...
    [[lights]]  position = [x, y, z]  intensity = 0.4  radius = 3.0     # point lights (no shadows)
    [path]  mode = "waypoints" | "poses" | "velocity"  ...             # scripted motion (optional)

A ``texture`` is the name of a ``[textures.NAME]`` table, a bare kind ("brick"), or an inline table
``{kind = "poster", seed = 3}``.  Bare kinds and inline tables without a seed get a seed derived from
the element, so every poster differs.
"""
from __future__ import annotations

import dataclasses
import tomllib
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from common.sim.textures import KINDS, TextureError, TextureSpec


class ScenarioError(ValueError):
    """A scenario file that cannot be used; the message names the file and the field."""


# ------------------------------------------------------------------------------------ configurations
@dataclass
class CameraConfig:
    """Stereo rig and its photometry. The left camera sits baseline/2 left of the robot centre line."""
    width: int = 640
    height: int = 480
    hfov_deg: float = 70.0
    baseline: float = 0.12
    height_m: float = 0.45          # optical centre above the floor
    forward_m: float = 0.10         # optical centre ahead of base_link
    pitch_deg: float = 0.0          # positive looks down
    rate_hz: float = 10.0
    exposure: float = 1.0           # scene-to-sensor scale of the left camera
    gain_right: float = 1.07        # right/left gain ratio (photometric difference between the cameras)
    offset_right: float = 4.0       # right/left black-level difference, grey levels
    read_noise: float = 1.2         # grey levels (σ)
    shot_noise: float = 0.08        # σ² grows by shot_noise × signal (grey levels)
    vignetting: float = 0.25        # brightness loss at the image corners
    motion_blur_samples: int = 1    # >1 averages that many poses over exposure_time_s
    exposure_time_s: float = 0.012
    # a hand-held rig: the camera sways (roll, pitch and half as much yaw, degrees) and bobs (metres)
    # about the planar path, periodically (sway_period_s; the bob at twice the rate, one per step)
    sway_deg: float = 0.0
    bob_m: float = 0.0
    sway_period_s: float = 1.2


@dataclass
class OdometryConfig:
    """Differential-drive wheel odometry. Errors are relative: the *nominal* (assumed) wheel radius is
    true × (1 + radius_error_*), so a +2 % radius error makes odometry distances 2 % too long."""
    rate_hz: float = 50.0
    wheel_radius: float = 0.05      # nominal, metres
    track_width: float = 0.30       # nominal, metres
    ticks_per_rev: int = 4096
    radius_error_left: float = 0.0
    radius_error_right: float = 0.0
    track_error: float = 0.0        # nominal = true × (1 + track_error)
    slip_sigma: float = 0.01        # per-sample relative wheel slip (σ)
    burst_rate_hz: float = 0.02     # occasional slip bursts (wheel spinning on a slippery patch)
    burst_duration_s: float = 0.4
    burst_slip: float = 0.3         # extra relative wheel rotation during a burst
    speed_noise: float = 0.02       # σ of reported wheel speeds, rad/s


@dataclass
class SonarConfig:
    count: int = 12
    rate_hz: float = 10.0
    ring_radius: float = 0.20
    height_m: float = 0.25
    beam_width_deg: float = 25.0
    min_range: float = 0.15
    max_range: float = 5.0
    noise_sigma: float = 0.01       # metres
    noise_rel: float = 0.005        # relative to range
    critical_angle_deg: float = 60.0  # incidence beyond which a smooth surface returns no echo
    dropout: float = 0.02           # probability of a missed echo
    rays: int = 9                   # rays cast across the beam


@dataclass
class PointLight:
    position: tuple[float, float, float]
    intensity: float = 0.4
    radius: float = 3.0


@dataclass
class LightingConfig:
    ambient: float = 0.55
    sun: tuple[float, float, float] = (0.3, 0.5, 1.0)  # direction towards the light
    sun_intensity: float = 0.45
    sky_color: tuple[int, int, int] = (170, 195, 225)
    lights: list[PointLight] = field(default_factory=list)


@dataclass
class PathConfig:
    """Scripted motion. ``waypoints``: diff-drive turn-then-drive through [x, y] points; ``poses``:
    trolley moves between [x, y, yaw_deg] poses (translation and rotation together, holonomic, with a
    pause at each); ``velocity``: a list of [duration_s, v, omega] segments."""
    mode: str
    waypoints: list = field(default_factory=list)
    poses: list = field(default_factory=list)
    segments: list = field(default_factory=list)
    speed: float = 0.4
    turn_rate_deg: float = 30.0
    pause_s: float = 0.0


# ------------------------------------------------------------------------------------------ geometry
@dataclass
class Surface:
    """A textured rectangle: corners origin, origin+u, origin+v, origin+u+v (u ⟂ v)."""
    origin: np.ndarray
    u: np.ndarray
    v: np.ndarray
    texture: TextureSpec
    solid: bool = False
    decal: bool = False
    name: str = ""


@dataclass
class Box:
    center: tuple[float, float]
    size: tuple[float, float, float]
    yaw: float = 0.0  # radians
    z0: float = 0.0
    texture: TextureSpec = field(default_factory=lambda: TextureSpec("wood"))
    name: str = ""


@dataclass
class Scenario:
    name: str
    description: str
    source: str
    surfaces: list[Surface]
    boxes: list[Box]
    start: tuple[float, float, float]  # x, y, yaw (radians)
    robot_radius: float = 0.22
    target: tuple[float, float] | None = None
    path: PathConfig | None = None
    camera: CameraConfig = field(default_factory=CameraConfig)
    odometry: OdometryConfig = field(default_factory=OdometryConfig)
    sonar: SonarConfig = field(default_factory=SonarConfig)
    lighting: LightingConfig = field(default_factory=LightingConfig)


# ------------------------------------------------------------------------------------------- parsing
class _Ctx:
    def __init__(self, source: str):
        self.source = source

    def err(self, where: str, msg: str) -> ScenarioError:
        return ScenarioError(f"{self.source}: {where}: {msg}")

    def table(self, data, where) -> dict:
        if not isinstance(data, dict):
            raise self.err(where, f"expected a table, got {type(data).__name__}")
        return data

    def check_keys(self, data: dict, allowed, where: str):
        extra = sorted(set(data) - set(allowed))
        if extra:
            raise self.err(where, f"unknown key(s) {', '.join(extra)}; allowed: {', '.join(sorted(allowed))}")

    def number(self, data: dict, key: str, where: str, default=None, positive=False, nonneg=False):
        if key not in data:
            if default is None:
                raise self.err(f"{where}.{key}", "missing")
            return default
        val = data[key]
        if isinstance(val, bool) or not isinstance(val, (int, float)) or not np.isfinite(val):
            raise self.err(f"{where}.{key}", f"expected a number, got {val!r}")
        if positive and val <= 0:
            raise self.err(f"{where}.{key}", f"must be positive, got {val}")
        if nonneg and val < 0:
            raise self.err(f"{where}.{key}", f"must be ≥ 0, got {val}")
        return float(val)

    def vec(self, data: dict, key: str, n: int, where: str, default=None) -> tuple:
        if key not in data:
            if default is None:
                raise self.err(f"{where}.{key}", "missing")
            return default
        val = data[key]
        if (not isinstance(val, list) or len(val) != n
                or not all(isinstance(x, (int, float)) and not isinstance(x, bool) and np.isfinite(x) for x in val)):
            got = f"{len(val)} values" if isinstance(val, list) else repr(val)
            raise self.err(f"{where}.{key}", f"expected {n} numbers, got {got}")
        return tuple(float(x) for x in val)

    def array_of_tables(self, data: dict, key: str) -> list[dict]:
        items = data.get(key, [])
        if not isinstance(items, list) or not all(isinstance(i, dict) for i in items):
            raise self.err(key, "expected an array of tables ([[" + key + "]])")
        return items


def _config(ctx: _Ctx, cls, data, where: str):
    """Dataclass ``cls`` with defaults overridden by the TOML table ``data`` (types checked)."""
    data = ctx.table(data, where)
    fields = {f.name: f for f in dataclasses.fields(cls) if f.name != "lights"}
    ctx.check_keys(data, fields, where)
    obj = cls()
    for key, val in data.items():
        default = getattr(obj, key)
        w = f"{where}.{key}"
        if isinstance(default, bool):
            if not isinstance(val, bool):
                raise ctx.err(w, f"expected true/false, got {val!r}")
        elif isinstance(default, int):
            if isinstance(val, bool) or not isinstance(val, int):
                raise ctx.err(w, f"expected an integer, got {val!r}")
        elif isinstance(default, float):
            val = ctx.number(data, key, where)
        elif isinstance(default, tuple):
            val = ctx.vec(data, key, len(default), where)
        setattr(obj, key, val)
    return obj


def _validate_configs(ctx: _Ctx, cam: CameraConfig, odo: OdometryConfig, son: SonarConfig):
    positive = [("camera", cam, ("width", "height", "hfov_deg", "baseline", "height_m", "rate_hz", "exposure",
                                 "gain_right", "exposure_time_s", "motion_blur_samples", "sway_period_s")),
                ("odometry", odo, ("rate_hz", "wheel_radius", "track_width", "ticks_per_rev", "burst_duration_s")),
                ("sonar", son, ("count", "rate_hz", "beam_width_deg", "max_range", "rays", "critical_angle_deg"))]
    for name, obj, keys in positive:
        for k in keys:
            if getattr(obj, k) <= 0:
                raise ctx.err(f"{name}.{k}", f"must be positive, got {getattr(obj, k)}")
    if not (0 <= cam.sway_deg < 45 and 0 <= cam.bob_m < cam.height_m):
        raise ctx.err("camera.sway_deg", f"sway must be in [0, 45)° and bob_m in [0, height_m), got "
                                         f"{cam.sway_deg}° and {cam.bob_m} m")
    if not cam.hfov_deg < 170:
        raise ctx.err("camera.hfov_deg", f"must be below 170, got {cam.hfov_deg}")
    for k in ("radius_error_left", "radius_error_right", "track_error"):
        if abs(getattr(odo, k)) >= 0.5:
            raise ctx.err(f"odometry.{k}", f"must be a relative error with |e| < 0.5, got {getattr(odo, k)}")
    if not 0 <= son.dropout <= 1:
        raise ctx.err("sonar.dropout", f"must be a probability, got {son.dropout}")
    if not 0 <= son.min_range < son.max_range:
        raise ctx.err("sonar.min_range", f"must be in [0, max_range), got {son.min_range}")


class _Textures:
    def __init__(self, ctx: _Ctx, named: dict):
        self.ctx = ctx
        self.named: dict[str, TextureSpec] = {}
        for name, tdata in ctx.table(named, "textures").items():
            self.named[name] = self._inline(tdata, f"textures.{name}", default_seed=0)

    def _inline(self, data, where, default_seed: int) -> TextureSpec:
        ctx = self.ctx
        data = ctx.table(data, where)
        ctx.check_keys(data, ("kind", "seed", "color", "size_m", "contrast", "resolution"), where)
        if "kind" not in data:
            raise ctx.err(f"{where}.kind", "missing")
        seed = data.get("seed", default_seed)
        if isinstance(seed, bool) or not isinstance(seed, int):
            raise ctx.err(f"{where}.seed", f"expected an integer, got {seed!r}")
        res = data.get("resolution", 256)
        if isinstance(res, bool) or not isinstance(res, int):
            raise ctx.err(f"{where}.resolution", f"expected an integer, got {res!r}")
        color = ctx.vec(data, "color", 3, where, default=None) if "color" in data else None
        size = ctx.vec(data, "size_m", 2, where, default=None) if "size_m" in data else None
        try:
            return TextureSpec(kind=data["kind"], seed=seed, resolution=res,
                               color=None if color is None else tuple(int(round(c)) for c in color),
                               size_m=size, contrast=ctx.number(data, "contrast", where, default=1.0))
        except TextureError as e:
            raise ctx.err(where, str(e)) from None

    def get(self, data: dict, where: str, default_kind: str, element_seed: int) -> TextureSpec:
        val = data.get("texture", default_kind)
        if isinstance(val, dict):
            return self._inline(val, f"{where}.texture", default_seed=element_seed)
        if isinstance(val, str):
            if val in self.named:
                return self.named[val]
            if val in KINDS:
                return TextureSpec(kind=val, seed=element_seed)
            raise self.ctx.err(f"{where}.texture",
                               f"{val!r} is neither a [textures] entry ({', '.join(self.named) or 'none'}) "
                               f"nor a texture kind ({', '.join(KINDS)})")
        raise self.ctx.err(f"{where}.texture", f"expected a name or an inline table, got {val!r}")


def _vertical_rect(ctx, item, where, tex, solid, decal, name, flip=False) -> Surface:
    a = np.array(ctx.vec(item, "from", 2, where))
    b = np.array(ctx.vec(item, "to", 2, where))
    z0, z1 = ctx.vec(item, "z", 2, where)
    if np.linalg.norm(b - a) < 1e-6:
        raise ctx.err(f"{where}.to", "must differ from 'from'")
    if not z1 > z0:
        raise ctx.err(f"{where}.z", f"needs z0 < z1, got [{z0}, {z1}]")
    if flip:
        a, b = b, a
    # Wound so the surface normal u × v points to the LEFT of from→to (decals face that side).
    origin = np.array([b[0], b[1], z0])
    u = np.array([a[0] - b[0], a[1] - b[1], 0.0])
    v = np.array([0.0, 0.0, z1 - z0])
    return Surface(origin, u, v, tex, solid=solid, decal=decal, name=name)


def parse_scenario(data: dict, source: str = "<scenario>") -> Scenario:
    """Scenario from an already-parsed TOML document (see module docstring for the layout)."""
    ctx = _Ctx(source)
    top = {"name", "description", "robot", "target", "camera", "odometry", "sonar", "lighting", "textures",
           "floor", "ceiling", "walls", "doors", "posters", "panels", "boxes", "lights", "path"}
    ctx.check_keys(data, top, "top level")
    name = data.get("name", Path(source).stem)
    if not isinstance(name, str):
        raise ctx.err("name", "expected a string")
    tex = _Textures(ctx, data.get("textures", {}))

    robot = ctx.table(data.get("robot", {}), "robot")
    ctx.check_keys(robot, ("start", "radius"), "robot")
    sx, sy, syaw = ctx.vec(robot, "start", 3, "robot", default=(0.0, 0.0, 0.0))
    radius = ctx.number(robot, "radius", "robot", default=0.22, positive=True)
    target = ctx.vec(data, "target", 2, "top level", default=None) if "target" in data else None

    camera = _config(ctx, CameraConfig, data.get("camera", {}), "camera")
    odometry = _config(ctx, OdometryConfig, data.get("odometry", {}), "odometry")
    sonar = _config(ctx, SonarConfig, data.get("sonar", {}), "sonar")
    _validate_configs(ctx, camera, odometry, sonar)
    lighting = _config(ctx, LightingConfig, data.get("lighting", {}), "lighting")
    lights = []
    for i, item in enumerate(ctx.array_of_tables(data, "lights")):
        w = f"lights[{i}]"
        ctx.check_keys(item, ("position", "intensity", "radius"), w)
        lights.append(PointLight(ctx.vec(item, "position", 3, w),
                                 ctx.number(item, "intensity", w, default=0.4, nonneg=True),
                                 ctx.number(item, "radius", w, default=3.0, positive=True)))
    lighting.lights = lights

    surfaces: list[Surface] = []
    seed_base = 1000
    for key, z_default, kind in (("floor", 0.0, "tiles"), ("ceiling", 2.5, "tiles")):
        if key not in data:
            continue
        item = ctx.table(data[key], key)
        ctx.check_keys(item, ("x", "y", "z", "texture"), key)
        x0, x1 = ctx.vec(item, "x", 2, key)
        y0, y1 = ctx.vec(item, "y", 2, key)
        if not (x1 > x0 and y1 > y0):
            raise ctx.err(key, f"needs x0 < x1 and y0 < y1, got x=[{x0}, {x1}] y=[{y0}, {y1}]")
        z = ctx.number(item, "z", key, default=z_default)
        surfaces.append(Surface(np.array([x0, y0, z]), np.array([x1 - x0, 0, 0.0]), np.array([0, y1 - y0, 0.0]),
                                tex.get(item, key, kind, seed_base + len(surfaces)), name=key))

    for key, kind, solid, decal in (("walls", "paint", True, False), ("doors", "door", False, True),
                                    ("posters", "poster", False, True)):
        for i, item in enumerate(ctx.array_of_tables(data, key)):
            w = f"{key}[{i}]"
            ctx.check_keys(item, ("from", "to", "z", "texture", "flip"), w)
            flip = item.get("flip", False)
            if not isinstance(flip, bool):
                raise ctx.err(f"{w}.flip", f"expected true/false, got {flip!r}")
            surfaces.append(_vertical_rect(ctx, item, w, tex.get(item, w, kind, seed_base + 37 * len(surfaces) + i),
                                           solid, decal, w, flip))

    for i, item in enumerate(ctx.array_of_tables(data, "panels")):
        w = f"panels[{i}]"
        ctx.check_keys(item, ("origin", "u", "v", "texture", "solid", "decal"), w)
        o, u, v = (np.array(ctx.vec(item, k, 3, w)) for k in ("origin", "u", "v"))
        nu, nv = np.linalg.norm(u), np.linalg.norm(v)
        if nu < 1e-6 or nv < 1e-6:
            raise ctx.err(w, "u and v must be non-zero edge vectors")
        if abs(u @ v) > 1e-6 * nu * nv:
            raise ctx.err(w, "u and v must be perpendicular (panels are rectangles)")
        flags = {}
        for k in ("solid", "decal"):
            flags[k] = item.get(k, False)
            if not isinstance(flags[k], bool):
                raise ctx.err(f"{w}.{k}", f"expected true/false, got {flags[k]!r}")
        surfaces.append(Surface(o, u, v, tex.get(item, w, "noise", seed_base + 53 * len(surfaces) + i), name=w, **flags))

    boxes = []
    for i, item in enumerate(ctx.array_of_tables(data, "boxes")):
        w = f"boxes[{i}]"
        ctx.check_keys(item, ("center", "size", "yaw", "z0", "texture"), w)
        size = ctx.vec(item, "size", 3, w)
        if min(size) <= 0:
            raise ctx.err(f"{w}.size", f"all three sizes must be positive, got {list(size)}")
        boxes.append(Box(ctx.vec(item, "center", 2, w), size, np.deg2rad(ctx.number(item, "yaw", w, default=0.0)),
                         ctx.number(item, "z0", w, default=0.0),
                         tex.get(item, w, "wood", seed_base + 71 * i + 5), name=w))

    path = _path(ctx, data["path"]) if "path" in data else None
    desc = data.get("description", "")
    if not isinstance(desc, str):
        raise ctx.err("description", "expected a string")
    return Scenario(name=name, description=desc, source=source, surfaces=surfaces, boxes=boxes,
                    start=(sx, sy, float(np.deg2rad(syaw))), robot_radius=radius, target=target, path=path,
                    camera=camera, odometry=odometry, sonar=sonar, lighting=lighting)


def _path(ctx: _Ctx, data) -> PathConfig:
    data = ctx.table(data, "path")
    ctx.check_keys(data, ("mode", "waypoints", "poses", "segments", "speed", "turn_rate_deg", "pause_s"), "path")
    mode = data.get("mode")
    need = {"waypoints": ("waypoints", 2), "poses": ("poses", 3), "velocity": ("segments", 3)}
    if mode not in need:
        raise ctx.err("path.mode", f"expected one of {', '.join(need)}, got {mode!r}")
    key, n = need[mode]
    rows = data.get(key)
    if not isinstance(rows, list) or not rows:
        raise ctx.err(f"path.{key}", f"mode {mode!r} needs a non-empty list of [{n} numbers] rows")
    parsed = [ctx.vec({"row": r}, "row", n, f"path.{key}[{i}]") for i, r in enumerate(rows)]
    pc = PathConfig(mode=mode, speed=ctx.number(data, "speed", "path", default=0.4, positive=True),
                    turn_rate_deg=ctx.number(data, "turn_rate_deg", "path", default=30.0, positive=True),
                    pause_s=ctx.number(data, "pause_s", "path", default=0.0, nonneg=True))
    setattr(pc, key, parsed)
    if mode == "velocity":
        for i, (dur, _, _) in enumerate(parsed):
            if dur <= 0:
                raise ctx.err(f"path.segments[{i}]", f"duration must be positive, got {dur}")
    return pc


def load_scenario(path) -> Scenario:
    """Read and check a scenario TOML file. Raises ScenarioError naming the file and field."""
    p = Path(path)
    try:
        text = p.read_bytes().decode("utf-8")
    except OSError as e:
        raise ScenarioError(f"{p}: cannot read scenario file ({e.strerror or e})") from None
    except UnicodeDecodeError as e:
        raise ScenarioError(f"{p}: not UTF-8 text (byte {e.start}); a scenario is TOML") from None
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as e:
        raise ScenarioError(f"{p}: not valid TOML ({e})") from None
    if not data:
        raise ScenarioError(f"{p}: empty scenario (no keys or tables); see {SCENARIO_DIR / 'corridor.toml'}")
    return parse_scenario(data, source=str(p))


SCENARIO_DIR = Path(__file__).resolve().parents[2] / "recordings" / "scenarios"


def scenario_path(name: str) -> Path:
    """Path of a shipped scenario by name (``"corridor"`` → recordings/scenarios/corridor.toml)."""
    p = SCENARIO_DIR / (name if name.endswith(".toml") else f"{name}.toml")
    if not p.is_file():
        have = sorted(q.stem for q in SCENARIO_DIR.glob("*.toml"))
        raise ScenarioError(f"no scenario {name!r} in {SCENARIO_DIR}; available: {', '.join(have)}")
    return p
