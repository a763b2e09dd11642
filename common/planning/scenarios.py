"""Seeded 2-D obstacle worlds for the closed-loop planner test: walls as (M, 2, 2) map-frame segments.

Three kinds, chosen by ``seed % 3``: a corridor with randomly placed boxes, a room split by a wall with a
doorway, and a dead end (a U-shaped trap opening towards the robot, with the target behind it, so the
robot must back out and detour).  Stand-in until ``common.sim.World.obstacle_segments`` is available.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Scenario:
    name: str
    segments: np.ndarray                 # (M, 2, 2) float64, map x, y
    start: tuple[float, float, float]    # x, y, yaw
    target: tuple[float, float, float]   # x, y, radius
    bounds: tuple[float, float, float, float]   # xmin, ymin, xmax, ymax


def _box(cx: float, cy: float, hx: float, hy: float) -> list:
    c = [(cx - hx, cy - hy), (cx + hx, cy - hy), (cx + hx, cy + hy), (cx - hx, cy + hy)]
    return [(c[i], c[(i + 1) % 4]) for i in range(4)]


def _rect(x0: float, y0: float, x1: float, y1: float) -> list:
    return _box((x0 + x1) / 2, (y0 + y1) / 2, (x1 - x0) / 2, (y1 - y0) / 2)


def corridor_with_boxes(rng: np.random.Generator) -> Scenario:
    length, width = 12.0, 2.4
    segs = _rect(0.0, 0.0, length, width)
    # boxes at least 0.8 m apart along the corridor, so the robot can always weave between them
    xs = 3.0 + 2.6 * np.arange(3) + rng.uniform(0.0, 1.2, size=3)
    for x in xs:
        h = rng.uniform(0.15, 0.3)
        # leave >= 0.9 m free on one side of the box
        if rng.random() < 0.5:
            cy = rng.uniform(h, width - 0.95 - h)
        else:
            cy = rng.uniform(0.95 + h, width - h)
        segs += _box(float(x), float(cy), h, h)
    return Scenario("corridor", np.asarray(segs, dtype=float), (0.7, width / 2, 0.0),
                    (length - 0.8, width / 2, 0.3), (0.0, 0.0, length, width))


def doorway(rng: np.random.Generator) -> Scenario:
    w, h = 10.0, 6.0
    segs = _rect(0.0, 0.0, w, h)
    door_w = rng.uniform(0.95, 1.2)
    door_y = rng.uniform(1.0, h - 1.0 - door_w)
    segs += [((5.0, 0.0), (5.0, door_y)), ((5.0, door_y + door_w), (5.0, h))]
    start_y = rng.uniform(1.0, h - 1.0)
    target_y = rng.uniform(1.0, h - 1.0)
    return Scenario("doorway", np.asarray(segs, dtype=float), (1.0, start_y, rng.uniform(-0.5, 0.5)),
                    (9.0, target_y, 0.3), (0.0, 0.0, w, h))


def dead_end(rng: np.random.Generator) -> Scenario:
    w, h = 11.0, 7.0
    segs = _rect(0.0, 0.0, w, h)
    yc = h / 2 + rng.uniform(-0.5, 0.5)
    half = rng.uniform(0.8, 1.1)              # half-width of the U
    x_open, x_back = rng.uniform(4.0, 4.8), 6.2
    segs += [((x_open, yc - half), (x_back, yc - half)), ((x_back, yc - half), (x_back, yc + half)),
             ((x_back, yc + half), (x_open, yc + half))]
    return Scenario("dead end", np.asarray(segs, dtype=float), (1.0, yc, 0.0), (8.5, yc, 0.3),
                    (0.0, 0.0, w, h))


def make_scenario(seed: int) -> Scenario:
    """Scenario ``seed``: kind by seed % 3 (corridor, doorway, dead end), layout from the seed."""
    rng = np.random.default_rng(seed)
    return (corridor_with_boxes, doorway, dead_end)[seed % 3](rng)
