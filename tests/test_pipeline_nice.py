"""Launch files can lower a service's priority (``nice``) so it yields the CPU to the pose pipeline."""
from __future__ import annotations

import sys
import time
from pathlib import Path

import pytest

from deploy.supervisor import Child, LaunchError, ServiceSpec, load_launch


def niceness(pid: int) -> int:
    return int((Path("/proc") / str(pid) / "stat").read_text().rsplit(")", 1)[1].split()[16])


def test_a_niced_service_runs_at_lower_priority(tmp_path):
    child = Child(ServiceSpec(name="sleeper", module="-", nice=7),
                  [sys.executable, "-c", "import time; time.sleep(30)"], tmp_path / "sleeper.log")
    child.start({})
    try:
        time.sleep(0.2)
        assert niceness(child.proc.pid) == 7
    finally:
        child.terminate(5)


def test_launch_file_nice_is_read_and_checked(tmp_path):
    launch = tmp_path / "launch.toml"
    launch.write_text('[[service]]\nname = "bridge"\nmodule = "services.bridge"\nnice = 15\n')
    assert load_launch(launch).services[0].nice == 15
    launch.write_text('[[service]]\nname = "bridge"\nmodule = "services.bridge"\nnice = -5\n')
    with pytest.raises(LaunchError, match="nice must be an integer in 0..19"):
        load_launch(launch)


def test_demo_launch_nices_only_services_off_the_pose_path():
    demo = load_launch(Path(__file__).resolve().parent.parent / "deploy" / "launch" / "demo.toml")
    nice = {s.name: s.nice for s in demo.services}
    assert nice["bridge"] > 0 and nice["recorder"] > 0
    assert nice["evolver"] == nice["localiser"] == nice["fusion"] == nice["sim"] == 0
