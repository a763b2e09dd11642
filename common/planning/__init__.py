"""Harmonic-function planner: occupancy from the fly population and sonar, a log-space harmonic field kept
up to date by warm-started relaxation, and a differential-drive command down its gradient.

See ``planner.HarmonicPlanner`` for the API used by the planner service, ``closed_loop`` for the kinematic
test harness and ``scenarios`` for the seeded obstacle worlds.
"""
from .config import Command, PlannerConfig, PlannerInputError, SolveReport
from .planner import HarmonicPlanner

__all__ = ["Command", "HarmonicPlanner", "PlannerConfig", "PlannerInputError", "SolveReport"]
