"""Turn a desired heading into a differential-drive command (v, omega) within speed and turn limits."""
from __future__ import annotations

import math

from .config import PlannerConfig


def heading_command(desired_heading: float, yaw: float, cfg: PlannerConfig,
                    speed_limit: float) -> tuple[float, float]:
    """Proportional turn towards ``desired_heading``; forward speed scaled by cos(heading error) and 0 when
    the error exceeds ``turn_in_place_rad`` (turn on the spot rather than sweep a wide arc into a wall).

    Returns (v, omega) with |omega| <= omega_max and 0 <= v <= min(speed_limit, v_max)."""
    err = (desired_heading - yaw + math.pi) % (2 * math.pi) - math.pi
    omega = max(-cfg.omega_max, min(cfg.omega_max, cfg.heading_gain * err))
    if abs(err) >= cfg.turn_in_place_rad:
        return 0.0, omega
    v = min(speed_limit, cfg.v_max) * max(0.0, math.cos(err))
    return v, omega
