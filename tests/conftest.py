"""Shared pytest fixtures.

`shared_data` locates ../shared/data; when it is missing (the project cloned alone) tests that need it
skip with a reason, except under CI (CI=true) where a missing folder is a failure.
"""
from __future__ import annotations

import os
import socket
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
SHARED_DATA = ROOT.parent / "shared" / "data"


@pytest.fixture(scope="session")
def shared_data() -> Path:
    if not SHARED_DATA.is_dir():
        if os.environ.get("CI", "").lower() == "true":
            pytest.fail(f"{SHARED_DATA} is missing under CI")
        pytest.skip(f"{SHARED_DATA} not found (clone the project beside its shared/ folder)")
    return SHARED_DATA


def free_port() -> int:
    """A TCP port on loopback that is free right now (tests use unique ports to run side by side)."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture
def zenoh_port() -> int:
    return free_port()


@pytest.fixture(scope="session")
def deep_street_views():
    """(rig, true planar motion (x, z, θ), A, B): 3,000 flies each seen from two poses of the deep
    synthetic street (independent populations), for the registration tests."""
    import numpy as np

    from common.geometry import make_transform, rot_y
    from common.registration import scenes

    rng = np.random.default_rng(21)
    rig = scenes.deep_rig()
    scene = scenes.street_scene(rng)
    truth = np.array([-0.2, 0.9, np.deg2rad(-3.0)])
    T2 = make_transform(rot_y(truth[2]), [truth[0], 0, truth[1]])
    A, _, _ = scenes.observe(scene, np.eye(4), rig, 3000, rng)
    B, _, _ = scenes.observe(scene, T2, rig, 3000, rng)
    return rig, truth, A, B
