"""Run the simulator offline, as fast as the machine allows, straight into a recording.

Deterministic for (scenario, seed, options): the same call writes the same messages, so large
recordings need not be committed — :func:`cached_recording` regenerates them on first use.
Stamps start at ``t0_ns`` (default 1.7e18 ns, a fixed wall-clock-like epoch) + simulated time.
"""
from __future__ import annotations

import hashlib
import json
import os
import threading
from pathlib import Path
from typing import Callable

from common import messages as m
from common.recording import RecordingWriter
from common.sim.bus_messages import camera_messages, odometry_message, sonar_message, target_message
from common.sim.scenario import load_scenario, scenario_path
from common.sim.sensors import OdometryReading, SonarReading
from common.sim.simulator import CameraDue, Simulator
from common.trajectory import write_tum

T0_NS = 1_700_000_000_000_000_000
ROOT = Path(__file__).resolve().parent.parent.parent
CACHE_DIR = ROOT / ".cache" / "recordings"


def simulate_to_recording(scenario: str, out: str | Path, seed: int = 0, seconds: float | None = None,
                          fps: float | None = None, width: int | None = None, height: int | None = None,
                          encoding: str = "jpeg", quality: int = 90, depth: bool = False, robot: str = "rig",
                          progress: Callable[[float, int], None] | None = None, truth_tum: str | Path | None = None) -> dict:
    """Write a simulated run (scripted path) to ``out``; returns a summary dict."""
    path = Path(scenario) if str(scenario).endswith(".toml") else scenario_path(scenario)
    scn = load_scenario(path)
    sim = Simulator(scn, seed=seed, width=width, height=height, camera_rate_hz=fps)
    options = dict(scenario=str(path.name), seed=seed, seconds=seconds, fps=fps, width=sim.calibration.width,
                   height=sim.calibration.height, encoding=encoding, quality=quality, depth=depth)
    key = lambda stream: f"{robot}/{stream}"  # noqa: E731
    frames = 0
    truth = ([], [])
    # a partial file of this writer's own: two benches that make the same recording at once each write
    # theirs, and the last atomic replace leaves one whole recording (the same bytes either way)
    tmp = Path(out).with_suffix(f".{os.getpid()}-{threading.get_ident()}.partial")
    try:
        with RecordingWriter(tmp) as rec:
            rec.add_config({"generator": "common.sim.offline", **options})
            calib = m.encode(m.calibration_to_msg(sim.calibration, 1, T0_NS))
            rec.write(key("stereo/calibration"), calib, T0_NS)
            rec.add_calibration(calib)
            target = target_message(scn, T0_NS)
            if target is not None:
                rec.write(key("planner/target"), m.encode(target), T0_NS)
            while not sim.finished and (seconds is None or sim.time_ns * 1e-9 < seconds):
                for ev in sim.advance(0.02):
                    stamp = T0_NS + ev.stamp_ns
                    if isinstance(ev, OdometryReading):
                        rec.write(key("odom/wheels"), m.encode(odometry_message(ev, stamp)), stamp)
                    elif isinstance(ev, SonarReading):
                        rec.write(key("sonar/scan"), m.encode(sonar_message(ev, stamp)), stamp)
                    elif isinstance(ev, CameraDue):
                        images = sim.render(ev.stamp_ns)
                        frames += 1
                        for stream, msg in camera_messages(images, frames, stamp, encoding, depth, quality).items():
                            rec.write(key(stream), m.encode(msg), stamp)
                        truth[0].append(stamp)
                        truth[1].append(images.T_map_base)
                        if progress:
                            progress(sim.time_ns * 1e-9, frames)
        tmp.replace(out)
    except BaseException:
        tmp.unlink(missing_ok=True)      # (an interrupted simulation leaves no partial file behind)
        raise
    if truth_tum:
        import numpy as np
        write_tum(truth_tum, np.array(truth[0], np.int64), np.array(truth[1]))
    return {**options, "out": str(out), "frames": frames, "seconds": sim.time_ns * 1e-9}


# What a simulated recording is made by: a change to any of these makes cached recordings stale.  Every
# module of common the simulator imports (tests/test_sim_cache.py checks), less common/__init__.py,
# numba_cache.py (where compiled kernels go) and trajectory.py (the TUM file beside a recording).
SIMULATOR_SOURCES = (*sorted((ROOT / "common" / "sim").glob("*.py")),
                     *(ROOT / "common" / f for f in ("camera.py", "codec.py", "geometry.py", "images.py",
                                                     "messages.py", "recording.py")))


def simulator_digest() -> str:
    """Digest of the simulator's source files (``SIMULATOR_SOURCES``) and of the libraries that draw,
    blur and encode its images."""
    import cv2
    import numba
    import numpy
    h = hashlib.sha1(f"{cv2.__version__} {numpy.__version__} {numba.__version__}".encode())
    for f in SIMULATOR_SOURCES:
        h.update(f.name.encode())
        h.update(f.read_bytes())
    return h.hexdigest()


def cached_recording(scenario: str = "corridor", seed: int = 0, progress=None, **options) -> Path:
    """Path of a deterministic simulated recording, generated on first use into .cache/recordings/.

    The name carries a digest of the scenario, seed and options, then one of the simulator's code
    (``simulator_digest``): a recording made by an older simulator is never taken for a new one's, and
    making the new one deletes the older ones of the same scenario, seed and options."""
    scn_file = Path(scenario) if str(scenario).endswith(".toml") else scenario_path(scenario)
    what = hashlib.sha1(json.dumps([scn_file.read_text(), seed, sorted(options.items())], default=str)
                        .encode()).hexdigest()[:10]
    stem = f"{scn_file.stem}-seed{seed}-{what}"
    out = CACHE_DIR / f"{stem}-{simulator_digest()[:10]}.mcap"
    if not out.exists():
        CACHE_DIR.mkdir(parents=True, exist_ok=True)
        simulate_to_recording(str(scn_file), out, seed=seed, progress=progress, **options)
        for stale in [*CACHE_DIR.glob(f"{stem}-*.mcap"), CACHE_DIR / f"{stem}.mcap"]:   # older simulators'
            if stale != out:
                stale.unlink(missing_ok=True)
    return out
