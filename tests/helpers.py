"""Utilities for tests that start real processes on a real Zenoh session (unique loopback ports)."""
from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from common import messages as m
from common.camera import StereoCalibration
from common.images import make_frame
from common.recording import RecordingWriter

ROOT = Path(__file__).resolve().parent.parent


def hub(port: int) -> str:
    return f"tcp/127.0.0.1:{port}"


def start_module(module: str, *args: str, port: int, log_path: Path | None = None,
                 restarts: int = 0) -> subprocess.Popen:
    """Start ``python -m module args --hub ...`` as its own process (``restarts``: as the supervisor
    starts a service it has restarted that many times)."""
    out = open(log_path, "wb") if log_path else subprocess.DEVNULL
    env = dict(os.environ, PYTHONUNBUFFERED="1", PYTHONPATH=str(ROOT), FLYSLAM_RESTARTS=str(restarts))
    return subprocess.Popen([sys.executable, "-m", module, *args, "--hub", hub(port)], stdout=out,
                            stderr=subprocess.STDOUT, cwd=ROOT, env=env)


def stop(proc: subprocess.Popen, timeout: float = 10) -> int:
    if proc.poll() is None:
        proc.send_signal(signal.SIGTERM)
    try:
        return proc.wait(timeout)
    except subprocess.TimeoutExpired:
        proc.kill()
        return proc.wait()


def wait_until(predicate, timeout: float, poll: float = 0.05) -> bool:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if predicate():
            return True
        time.sleep(poll)
    return predicate()


def resend_until(send, predicate, timeout: float = 30, every: float = 1.0) -> bool:
    """Call ``send()`` every ``every`` seconds until ``predicate()`` holds, for at most ``timeout``
    seconds.  A service drops what reaches it before it is ready (a frame before its calibration, a
    population while it loads its kernels), as it would a camera's: a test sends again, as a camera does."""
    deadline = time.monotonic() + timeout
    while True:
        send()
        if wait_until(predicate, min(every, max(0.0, deadline - time.monotonic()))):
            return True
        if time.monotonic() >= deadline:
            return False


def write_source_recording(path: Path, frames: int = 30, size=(64, 48), seed: int = 0) -> list[tuple[str, bytes]]:
    """A small recording of what a live source publishes; returns the (key, payload) list in order."""
    rng = np.random.default_rng(seed)
    w, h = size
    written = []
    with RecordingWriter(path, chunk_size=64_000) as rec:
        cal = m.encode(m.calibration_to_msg(StereoCalibration.ideal(w, h), 1, 10**9))
        rec.write("rig/stereo/calibration", cal, 10**9)
        rec.add_calibration(cal)
        written.append(("rig/stereo/calibration", cal))
        for i in range(frames):
            t = 10**9 + (i + 1) * 33_000_000
            img = rng.integers(0, 255, (h, w, 3), dtype=np.uint8)
            frame = m.encode(make_frame(img, img, i + 1, t))
            odom = m.encode(m.WheelOdometry(wheel_speeds=np.array([1.0, 1.0 + i]), header=m.header(i + 1, t + 1, "base_link")))
            rec.write("rig/stereo/frame", frame, t)
            rec.write("rig/odom/wheels", odom, t + 1000)
            written += [("rig/stereo/frame", frame), ("rig/odom/wheels", odom)]
    return written
