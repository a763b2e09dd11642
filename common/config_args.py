"""argparse flags derived from config dataclasses, so a flag's default is the dataclass's default.

    add_config_arguments(parser, PlannerConfig, only=["robot_radius", "v_max"],
                         rename={"slow_clearance_m": "slow-clearance"})
    config = config_from_args(PlannerConfig, args, only=[...], size_m=(...))

A field ``name_of_field`` becomes ``--name-of-field`` (or the ``rename`` given), with the field's default,
its type (bool → ``--x/--no-x``; a tuple → that many values; ``float | None`` → float) and a one-line
help from the field's ``metadata["help"]`` (or ``helps``). Only fields with a plain default can be
flags. ``flag_fields(parser)`` lists what was derived, for tests/test_defaults.py.
"""
from __future__ import annotations

import argparse
import dataclasses
import math
import types
import typing
from typing import Iterable

_DERIVED = "_flyslam_config_flags"     # parser attribute: [(cls, field name, dest)]


def _flag(name: str, rename: dict[str, str]) -> str:
    return "--" + rename.get(name, name.replace("_", "-"))


def _dest(name: str, rename: dict[str, str]) -> str:
    return rename.get(name, name).replace("-", "_")


def _base_type(hint):
    """(element type, is_tuple) of a field's annotation."""
    origin = typing.get_origin(hint)
    args = [a for a in typing.get_args(hint) if a is not type(None)]
    if origin in (typing.Union, types.UnionType) and len(args) == 1:
        return _base_type(args[0])
    if origin is tuple or hint is tuple:
        return (args[0] if args else float), True
    return hint, False


def _float(text: str) -> float:
    value = float(text)           # 'inf' is allowed: depth_max may be infinite
    if math.isnan(value):
        raise argparse.ArgumentTypeError("NaN is not a value")
    return value


def add_config_arguments(parser: argparse.ArgumentParser | argparse._ArgumentGroup, cls,
                         only: Iterable[str] | None = None, rename: dict[str, str] | None = None,
                         helps: dict[str, str] | None = None, root: argparse.ArgumentParser | None = None) -> None:
    """Add one flag per field of ``cls`` (or per field in ``only``, in that order)."""
    rename, helps = rename or {}, helps or {}
    hints = typing.get_type_hints(cls)
    fields = {f.name: f for f in dataclasses.fields(cls)}
    names = list(only) if only is not None else list(fields)
    root = root or parser
    derived = getattr(root, _DERIVED, None)
    if derived is None:
        derived = []
        setattr(root, _DERIVED, derived)
    for name in names:
        f = fields[name]
        if f.default is dataclasses.MISSING:
            raise TypeError(f"{cls.__name__}.{name} has no plain default: it cannot be a flag")
        default = f.default
        text = f.metadata.get("help", helps.get(name, name.replace("_", " ")))
        kind, is_tuple = _base_type(hints[name])
        dest = _dest(name, rename)
        if kind is bool:
            parser.add_argument(_flag(name, rename), dest=dest, action=argparse.BooleanOptionalAction,
                                default=default, help=text)
        elif is_tuple:
            nargs = f.metadata.get("nargs", len(default) if default is not None else None)
            parser.add_argument(_flag(name, rename), dest=dest, type=_float if kind is float else kind,
                                nargs=nargs, default=None if default is None else tuple(default),
                                metavar=f.metadata.get("metavar", "V"), help=text)
        else:
            conv = _float if kind is float else kind if kind in (int, str) else str
            parser.add_argument(_flag(name, rename), dest=dest, type=conv, default=default, help=text)
        derived.append((cls, name, dest))


def config_values(cls, args: argparse.Namespace, only: Iterable[str] | None = None,
                  rename: dict[str, str] | None = None) -> dict:
    """{field: value} of the flags :func:`add_config_arguments` added for ``cls``."""
    rename = rename or {}
    names = list(only) if only is not None else [f.name for f in dataclasses.fields(cls)]
    values = {}
    for name in names:
        v = getattr(args, _dest(name, rename))
        values[name] = tuple(v) if isinstance(v, list) else v
    return values


def config_from_args(cls, args: argparse.Namespace, only: Iterable[str] | None = None,
                     rename: dict[str, str] | None = None, **extra):
    """``cls(**flags, **extra)``: the dataclass the command line describes."""
    return cls(**config_values(cls, args, only, rename), **extra)


def flag_fields(parser: argparse.ArgumentParser) -> list[tuple[type, str, str]]:
    """(dataclass, field, argparse dest) of every flag derived on ``parser``."""
    return list(getattr(parser, _DERIVED, []))
