"""Render and collision geometry of a scenario: textured rectangles ("quads") plus obstacle footprints.

Boxes become five quads (no bottom).  The quad arrays are what the numba renderer consumes; the 2-D
obstacle segments are what the planner harness, the sonar model and collision checks consume.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from common.geometry import rot_z
from common.sim.scenario import Box, Scenario, Surface
from common.sim.textures import TextureAtlas

DECAL_BIAS_M = 0.004  # a decal wins the depth test against the wall it lies on


@dataclass
class QuadArrays:
    """Struct-of-arrays view of all quads, float64 unless noted.

    origin/u/v (Q,3) corners; normal (Q,3) unit u×v; u_dual/v_dual (Q,3) = u/|u|², v/|v|² (so
    a = (p−origin)·u_dual ∈ [0,1] inside); size (Q,2) = |u|, |v| metres; tex (Q,) int64 atlas index;
    decal (Q,) bool (one-sided, depth-biased); solid (Q,) bool (obstacle); tex_scale (Q,2) maps the
    quad coordinates (a, b) to texture coordinates (tiling textures repeat, stretched ones span [0,1]);
    tiles (Q,) bool wrap vs clamp; texel_density (Q,) level-0 texels per metre on the surface.
    """
    origin: np.ndarray
    u: np.ndarray
    v: np.ndarray
    normal: np.ndarray
    u_dual: np.ndarray
    v_dual: np.ndarray
    size: np.ndarray
    tex: np.ndarray
    decal: np.ndarray
    solid: np.ndarray
    tex_scale: np.ndarray
    tiles: np.ndarray
    texel_density: np.ndarray

    def __len__(self):
        return len(self.tex)


def box_surfaces(box: Box) -> list[Surface]:
    """The four sides and the top of a box as quads; side quads have v pointing up (texture upright)."""
    sx, sy, sz = box.size
    R = rot_z(box.yaw)
    c = np.array([box.center[0], box.center[1], box.z0])
    ex, ey = R[:, 0] * sx, R[:, 1] * sy
    up = np.array([0.0, 0.0, sz])
    p00 = c - ex / 2 - ey / 2
    corners = [p00, p00 + ex, p00 + ex + ey, p00 + ey]
    out = []
    for k in range(4):  # counter-clockwise corners: u = next − this, outward normal u × up
        a, b = corners[k], corners[(k + 1) % 4]
        out.append(Surface(a.copy(), b - a, up.copy(), box.texture, solid=True, name=f"{box.name}.side{k}"))
    out.append(Surface(p00 + up, ex.copy(), ey.copy(), box.texture, solid=True, name=f"{box.name}.top"))
    return out


class World:
    """Geometry of a scenario. ``quads`` feed the renderer, ``atlas`` holds their textures."""

    def __init__(self, scenario: Scenario):
        self.scenario = scenario
        surfaces = list(scenario.surfaces)
        for b in scenario.boxes:
            surfaces.extend(box_surfaces(b))
        self.surfaces = surfaces
        specs, index = [], {}
        tex_ids = []
        for s in surfaces:
            if s.texture not in index:
                index[s.texture] = len(specs)
                specs.append(s.texture)
            tex_ids.append(index[s.texture])
        self.atlas = TextureAtlas.build(specs)
        O = np.array([s.origin for s in surfaces], float).reshape(-1, 3)
        U = np.array([s.u for s in surfaces], float).reshape(-1, 3)
        V = np.array([s.v for s in surfaces], float).reshape(-1, 3)
        N = np.cross(U, V)
        N /= np.maximum(np.linalg.norm(N, axis=1, keepdims=True), 1e-12)
        lu, lv = np.linalg.norm(U, axis=1), np.linalg.norm(V, axis=1)
        tex = np.array(tex_ids, np.int64).reshape(-1)
        a = self.atlas
        tiles = a.period_m[tex, 0] > 0 if len(tex) else np.zeros(0, bool)
        span = np.where(tiles[:, None], a.period_m[tex], np.stack([lu, lv], 1)) if len(tex) else np.zeros((0, 2))
        tex_scale = np.where(tiles[:, None], np.stack([lu, lv], 1) / np.where(tiles[:, None], span, 1.0), 1.0)
        density = np.maximum(a.width[tex, 0] / span[:, 0], a.height[tex, 0] / span[:, 1]) if len(tex) else np.zeros(0)
        self.quads = QuadArrays(
            origin=O, u=U, v=V, normal=N, u_dual=U / lu[:, None] ** 2, v_dual=V / lv[:, None] ** 2,
            size=np.stack([lu, lv], 1), tex=tex,
            decal=np.array([s.decal for s in surfaces], bool), solid=np.array([s.solid for s in surfaces], bool),
            tex_scale=np.ascontiguousarray(tex_scale, float), tiles=np.ascontiguousarray(tiles, bool),
            texel_density=np.ascontiguousarray(density, float))
        # Box footprints (for "inside an obstacle" tests): (B, 4, 2) corner polygons, with z ranges.
        fp, zr = [], []
        for b in scenario.boxes:
            side = box_surfaces(b)[:4]
            fp.append(np.array([s.origin[:2] for s in side]))
            zr.append((b.z0, b.z0 + b.size[2]))
        self._footprints = np.array(fp, float).reshape(-1, 4, 2)
        self._footprint_z = np.array(zr, float).reshape(-1, 2)
        self._segment_cache: dict[tuple[float, float], np.ndarray] = {}

    # ------------------------------------------------------------------------------- 2-D obstacles
    def obstacle_segments(self, z_min: float = 0.05, z_max: float = 2.0) -> np.ndarray:
        """(M, 2, 2) map-frame x-y segments of every solid vertical surface meeting the band [z_min, z_max]
        (walls and box sides). Floors, ceilings, box tops and decals are not obstacles.  The array is
        cached per band and read-only."""
        if not z_max >= z_min:
            raise ValueError(f"obstacle_segments needs z_min ≤ z_max, got {z_min}, {z_max}")
        key = (float(z_min), float(z_max))
        if key not in self._segment_cache:  # the world is static: compute once per band
            self._segment_cache[key] = self._segments(*key)
            self._segment_cache[key].flags.writeable = False
        return self._segment_cache[key]

    def _segments(self, z_min: float, z_max: float) -> np.ndarray:
        q = self.quads
        vertical = np.abs(q.normal[:, 2]) < 1e-6
        corners_z = np.stack([q.origin[:, 2], (q.origin + q.u)[:, 2], (q.origin + q.v)[:, 2],
                              (q.origin + q.u + q.v)[:, 2]], 1)
        zlo, zhi = corners_z.min(1), corners_z.max(1)
        keep = q.solid & vertical & (zhi >= z_min) & (zlo <= z_max)
        segs = []
        for i in np.flatnonzero(keep):
            o, u, v = q.origin[i], q.u[i], q.v[i]
            h = u if np.hypot(u[0], u[1]) >= np.hypot(v[0], v[1]) else v  # the horizontal edge
            segs.append([o[:2], o[:2] + h[:2]])
        return np.array(segs, float).reshape(-1, 2, 2)

    def clearance(self, xy, z_min: float = 0.05, z_max: float = 2.0) -> np.ndarray:
        """Distance (m) from each map point (N, 2) — or one (2,) point — to the nearest obstacle in the
        height band; negative (minus the distance to the nearest edge) inside a box footprint."""
        P = np.atleast_2d(np.asarray(xy, float))
        if P.shape[1] != 2:
            raise ValueError(f"clearance expects (N, 2) points, got shape {np.shape(xy)}")
        d = point_segment_distance(P, self.obstacle_segments(z_min, z_max))
        band = (self._footprint_z[:, 1] >= z_min) & (self._footprint_z[:, 0] <= z_max)
        for poly in self._footprints[band]:
            inside = _inside_convex(P, poly)
            d = np.where(inside, -np.abs(d), d)
        return d if np.ndim(xy) > 1 else d[:1]

    def min_clearance(self, x: float, y: float, robot_radius: float | None = None) -> float:
        """Clearance of the robot body at (x, y): distance to the nearest obstacle minus the robot radius
        (defaults to the scenario's); ≤ 0 means a collision."""
        r = self.scenario.robot_radius if robot_radius is None else robot_radius
        return float(self.clearance(np.array([[x, y]]))[0] - r)


def point_segment_distance(P: np.ndarray, segs: np.ndarray) -> np.ndarray:
    """(N,) distance from points (N, 2) to the nearest of segments (M, 2, 2); inf when M = 0."""
    if len(segs) == 0:
        return np.full(len(P), np.inf)
    a, b = segs[:, 0], segs[:, 1]
    ab = b - a
    L2 = np.maximum((ab ** 2).sum(1), 1e-18)
    ap = P[:, None, :] - a[None]
    t = np.clip((ap * ab[None]).sum(2) / L2[None], 0, 1)
    closest = a[None] + t[..., None] * ab[None]
    return np.sqrt(((P[:, None, :] - closest) ** 2).sum(2)).min(1)


def _inside_convex(P: np.ndarray, poly: np.ndarray) -> np.ndarray:
    """Points strictly inside a convex polygon given counter-clockwise."""
    e = np.roll(poly, -1, 0) - poly
    rel = P[:, None, :] - poly[None]
    cross = e[None, :, 0] * rel[..., 1] - e[None, :, 1] * rel[..., 0]
    return np.all(cross > 0, axis=1)
