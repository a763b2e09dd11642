"""Every service runs OpenCV on its calling thread: the services share the cores as processes, and
OpenCV's own pool only burns CPU on wake-ups."""
import os
import subprocess
import sys

PROBE = r"""
import sys
if sys.argv[1] == "early":
    import cv2
from services.base import one_opencv_thread
one_opencv_thread()
import cv2
print(cv2.getNumThreads())
"""


def opencv_threads(when: str, env: dict) -> int:
    out = subprocess.run([sys.executable, "-c", PROBE, when], capture_output=True, text=True, check=True, env=env)
    return int(out.stdout.strip())


def test_a_service_process_runs_opencv_on_one_thread_unless_told_otherwise():
    env = {k: v for k, v in os.environ.items() if k != "OPENCV_FOR_THREADS_NUM"}
    assert opencv_threads("early", env) == 1          # OpenCV imported before the service started
    assert opencv_threads("late", env) == 1           # ... or after
    assert opencv_threads("late", {**env, "OPENCV_FOR_THREADS_NUM": "2"}) == 2
