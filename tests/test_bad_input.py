"""Bad files and flags give one line naming the field and what it expects, exit 2, and a traceback only
with ``flyslam --debug``. The cases are bench/faults.py's, so the bench and the tests cannot drift."""
from __future__ import annotations

import os
import subprocess
import sys

import pytest

from bench.faults import file_and_flag_cases
from common.camera import CalibrationError
from common.stereo_rectify import RawStereoRig, rectify_rig
from deploy import cli
from deploy.supervisor import LaunchError, load_launch
from tests.helpers import ROOT


def test_every_file_and_flag_case_is_one_line_naming_the_problem(tmp_path, capsys):
    failures = []
    for name, argv, expected in file_and_flag_cases(tmp_path):
        rc = cli.main(argv)
        err = capsys.readouterr().err
        lines = [ln for ln in err.splitlines() if ln.strip()]
        if rc != 2 or len(lines) != 1 or expected not in lines[0] or not lines[0].startswith("flyslam "):
            failures.append(f"{name}: exit {rc}, stderr {err!r}")
    assert not failures, "\n".join(failures)


def test_the_traceback_is_shown_only_with_debug(tmp_path):
    argv = ["record", "--out", str(tmp_path / "x.mcap"), "--cfg", "nocolon"]
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    plain = subprocess.run([sys.executable, "-m", "deploy.cli", *argv], cwd=ROOT, env=env, capture_output=True,
                           text=True, timeout=60)
    debug = subprocess.run([sys.executable, "-m", "deploy.cli", "--debug", *argv], cwd=ROOT, env=env,
                           capture_output=True, text=True, timeout=60)
    assert plain.returncode == 2 and "Traceback" not in plain.stderr
    assert plain.stderr.strip() == "flyslam record: --cfg expects KEY:JSON5 (e.g. 'scouting/multicast/enabled:true'), got 'nocolon'"
    assert debug.returncode != 0 and "Traceback (most recent call last)" in debug.stderr
    assert "BusConfigError" in debug.stderr


def test_a_bad_zenoh_runtime_in_the_environment_is_one_line_naming_it(tmp_path, zenoh_port):
    env = dict(os.environ, PYTHONPATH=str(ROOT), ZENOH_RUNTIME="(nonsense")
    run = subprocess.run([sys.executable, "-m", "deploy.cli", "record", "--out", str(tmp_path / "x.mcap"),
                          "--hub", f"tcp/127.0.0.1:{zenoh_port}"], cwd=ROOT, env=env, capture_output=True, text=True,
                         timeout=60)
    assert run.returncode == 2 and "Traceback" not in run.stderr
    assert run.stderr.strip().splitlines()[-1].startswith(
        "flyslam record: cannot open the Zenoh session: ZENOH_RUNTIME='(nonsense' is not a valid")
    assert not (tmp_path / "x.mcap").exists()


def test_an_internal_error_is_one_line_with_exit_1(monkeypatch, capsys):
    from deploy.commands import info

    def broken(argv):
        raise RuntimeError("something the code did not expect")
    monkeypatch.setattr(info, "main", broken)
    assert cli.main(["info", "x.mcap"]) == 1
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "internal error, RuntimeError: something the code did not expect" in err
    assert "flyslam --debug info" in err
    with pytest.raises(RuntimeError):
        cli.main(["--debug", "info", "x.mcap"])


def test_shipped_launch_files_pass_the_type_checks_and_wrong_types_name_the_field(tmp_path):
    for path in (ROOT / "deploy" / "launch").glob("*.toml"):
        assert load_launch(path).services
    base = '[[service]]\nname = "a"\nmodule = "m"\n'
    cases = {"required = 1": "required must be true or false", "nice = 20": "nice must be an integer in 0..19",
             "backoff_s = -1": "backoff_s must be a number of seconds", "args = [1]": "args must be a list of strings",
             "max_restarts = true": "max_restarts must be an integer", "colour = 'red'": "unknown field 'colour'"}
    for line, expected in cases.items():
        (tmp_path / "l.toml").write_text(base + line + "\n")
        with pytest.raises(LaunchError, match=expected):
            load_launch(tmp_path / "l.toml")
    (tmp_path / "l.toml").write_text(base + '[vars]\nx = ["a"]\n')
    with pytest.raises(LaunchError, match=r"\[vars\] x must be a string or a number"):
        load_launch(tmp_path / "l.toml")


def test_a_rig_with_zero_baseline_or_focal_length_is_a_calibration_error():
    K = [[500, 0, 320], [0, 500, 240], [0, 0, 1]]
    with pytest.raises(CalibrationError, match="baseline must be non-zero"):
        RawStereoRig(640, 480, K, [0] * 5, K, [0] * 5, [[1, 0, 0], [0, 1, 0], [0, 0, 1]], [0, 0, 0])
    with pytest.raises(CalibrationError, match="K2: focal lengths"):
        RawStereoRig(640, 480, K, [0] * 5, [[0, 0, 320], [0, 500, 240], [0, 0, 1]], [0] * 5,
                     [[1, 0, 0], [0, 1, 0], [0, 0, 1]], [-0.1, 0, 0])
    rig = RawStereoRig(640, 480, K, [0] * 5, K, [0] * 5, [[1, 0, 0], [0, 1, 0], [0, 0, 1]], [-0.12, 0, 0])
    assert rectify_rig(rig).baseline == pytest.approx(0.12)


def test_a_config_that_leaves_listen_to_zenohs_defaults_is_checked_not_crashed_on(tmp_path):
    """Without listen endpoints Zenoh's default is a map per mode; the secured-config check once failed on
    it with an internal error instead of accepting the file (or naming its placeholder)."""
    from common.bus import BusConfigError, BusOptions, make_config

    good, placeholder = tmp_path / "connect_only.json5", tmp_path / "placeholder.json5"
    good.write_text('{mode: "peer", connect: {endpoints: ["tcp/127.0.0.1:7447"]}}')
    placeholder.write_text('{mode: "peer", connect: {endpoints: ["tls/ROBOT_HOST:7447"]}}')
    make_config(BusOptions(config=str(good)))
    with pytest.raises(BusConfigError, match="ROBOT_HOST placeholder"):
        make_config(BusOptions(config=str(placeholder)))
