"""One source of defaults: every flag a launch file passes exists in that service's parser, every flag
derived from a config dataclass has the dataclass's default, and no service re-declares a config field
as a hand-written flag (whose default could drift from the dataclass's)."""
from __future__ import annotations

import dataclasses
import importlib
import re
from pathlib import Path

import pytest

from common.config_args import flag_fields
from deploy.supervisor import load_launch

ROOT = Path(__file__).resolve().parent.parent
LAUNCH_FILES = sorted((ROOT / "deploy" / "launch").glob("*.toml"))
SERVICES = ["evolver", "localiser", "planner", "fusion", "bridge", "sim", "camera", "recorder", "replay"]


def _parser(module: str):
    return importlib.import_module(module).build_parser()


def _substitute(arg: str, variables: dict[str, str]) -> str:
    """A launch argument with its {placeholders} filled: the file's [vars], a path for the rest."""
    return re.sub(r"\{(\w+)\}", lambda mt: str(variables.get(mt.group(1), f"/tmp/{mt.group(1)}")), arg)


def _launch_services():
    for path in LAUNCH_FILES:
        launch = load_launch(path)
        for spec in launch.services:
            yield pytest.param(path, launch.vars, spec, id=f"{path.name}:{spec.name}")


def test_there_are_launch_files_to_check():
    assert any(p.name == "demo.toml" for p in LAUNCH_FILES)


@pytest.mark.parametrize("path,variables,spec", list(_launch_services()))
def test_every_launch_file_argument_is_a_flag_of_its_service(path, variables, spec):
    parser = _parser(spec.module)
    argv = [_substitute(a, variables) for a in spec.args]
    try:
        parser.parse_args(argv)
    except SystemExit:
        pytest.fail(f"{path.name}: service {spec.name} ({spec.module}) does not accept {argv}")


@pytest.mark.parametrize("service", SERVICES)
def test_derived_flags_default_to_the_dataclass_defaults(service):
    parser = _parser(f"services.{service}")
    for cls, name, dest in flag_fields(parser):
        default = {f.name: f.default for f in dataclasses.fields(cls)}[name]
        got = parser.get_default(dest)
        assert (tuple(got) if isinstance(got, list) else got) == default, \
            f"{service}: --{dest} defaults to {got!r} but {cls.__name__}.{name} is {default!r}"


@pytest.mark.parametrize("service", SERVICES)
def test_no_config_field_is_also_a_hand_written_flag(service):
    parser = _parser(f"services.{service}")
    derived = flag_fields(parser)
    derived_dests = {dest for _, _, dest in derived}
    fields = {f.name for cls in {c for c, _, _ in derived} for f in dataclasses.fields(cls)}
    for action in parser._actions:
        if action.dest in fields and action.dest not in derived_dests:
            pytest.fail(f"{service}: --{action.dest} is hand-written but is a config field: derive it")


def test_service_help_is_one_line_per_flag():
    for service in [s for s in SERVICES if s not in ("recorder", "replay")]:
        for action in _parser(f"services.{service}")._actions:
            text = action.help or ""
            assert len(text) <= 120 and "\n" not in text, f"{service} --{action.dest}: help is {len(text)} chars"


def test_the_live_planner_and_the_library_agree_on_the_robot():
    from common.planning import PlannerConfig
    args = _parser("services.planner").parse_args([])
    assert (args.robot_radius, args.slow_clearance, args.v_max) == \
        (PlannerConfig.robot_radius, PlannerConfig.slow_clearance_m, PlannerConfig.v_max)


def test_eval_localiser_overrides_read_as_a_user_types_them():
    from deploy.commands.evaluate import parse_overrides
    cfg = parse_overrides(["loop_closure=true", "photometric=False", "odometry=visual", "window=(1.0, 1.0, 0.2)",
                           "eps=0.1"])
    assert cfg.loop_closure is True and cfg.photometric is False and cfg.odometry == "visual"
    assert cfg.window == (1.0, 1.0, 0.2) and cfg.eps == 0.1
    with pytest.raises(ValueError, match="eps"):
        parse_overrides(["eps=abc"])
    with pytest.raises(ValueError, match="FIELD one of"):
        parse_overrides(["no_such_field=1"])
