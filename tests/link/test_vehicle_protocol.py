"""The declared vehicle interface (companion/vehicle.py) matches what implements it, without a vehicle.

VehicleLink must satisfy VehicleControl structurally (each member there, of the same kind: property,
coroutine function or plain method, with compatible parameters); VehicleTelemetry must hold nothing that
commands the vehicle (shadow mode runs on it); the truth sources must satisfy TruthSource.
"""

from __future__ import annotations

import ast
import inspect
import typing
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest

from companion import vehicle
from companion.app.link import VehicleLink
from companion.app.shadow import _COMMANDING
from companion.app.telemetry import LinkPositionTruth, TruthForLog
from companion.px4sitl.truth import SihTruth
from companion.vehicle import TruthSource, VehicleControl, VehicleTelemetry

_MISSING = object()
COMMANDING = {"arm", "takeoff", "hold", "land", "start_offboard", "set_setpoint", "stop_offboard",
              "wait_landed_and_disarm"}


def _members(proto: type) -> dict[str, Any]:
    """A Protocol's own and inherited members: name -> the declared object (property, function)."""
    out: dict[str, Any] = {}
    for cls in reversed(proto.__mro__):
        if cls in (object, typing.Protocol, typing.Generic) or not getattr(cls, "_is_protocol", False):
            continue
        for name, obj in vars(cls).items():
            if name.startswith("_") and name != "__len__":
                continue
            if isinstance(obj, property) or inspect.isfunction(obj):
                out[name] = obj
        for name in getattr(cls, "__annotations__", {}):
            if not name.startswith("_"):
                out.setdefault(name, property())
    return out


def _kind(obj: Any) -> str:
    if isinstance(obj, property):
        return "property"
    return "coroutine" if inspect.iscoroutinefunction(obj) else "method"


def _params_compatible(declared: Any, impl: Any) -> str | None:
    """None when ``impl`` accepts every call ``declared`` allows (same names, kinds and optional ones)."""
    d = list(inspect.signature(declared).parameters.values())[1:]  # without self
    i = {p.name: p for p in list(inspect.signature(impl).parameters.values())[1:]}
    for p in d:
        q = i.pop(p.name, None)
        if q is None:
            return f"no parameter {p.name}"
        if q.kind != p.kind:
            return f"{p.name} is {q.kind.description}, declared {p.kind.description}"
        if p.default is not inspect.Parameter.empty and q.default is inspect.Parameter.empty:
            return f"{p.name} is required, declared optional"
    extra = [q.name for q in i.values() if q.default is inspect.Parameter.empty
             and q.kind not in (inspect.Parameter.VAR_POSITIONAL, inspect.Parameter.VAR_KEYWORD)]
    return f"undeclared required parameter(s) {extra}" if extra else None


def _check(impl_cls: type, proto: type, instance: Any = None) -> list[str]:
    problems = []
    for name, declared in _members(proto).items():
        impl = inspect.getattr_static(impl_cls, name, _MISSING)
        want = _kind(declared)
        if impl is _MISSING:  # a plain attribute set in __init__ satisfies a read-only property
            if want == "property" and instance is not None and hasattr(instance, name) \
                    and not callable(getattr(instance, name)):
                continue
            problems.append(f"{name}: missing")
            continue
        got = _kind(impl)
        if got != want:
            problems.append(f"{name}: {got}, declared {want}")
        elif want != "property":
            why = _params_compatible(declared, impl)
            if why is not None:
                problems.append(f"{name}: {why}")
    return problems


def test_vehicle_link_satisfies_vehicle_control() -> None:
    assert _check(VehicleLink, VehicleControl, VehicleLink()) == []


def test_telemetry_commands_nothing_and_control_adds_exactly_the_commands() -> None:
    telemetry, control = set(_members(VehicleTelemetry)), set(_members(VehicleControl))
    assert not telemetry & _COMMANDING  # shadow mode's read-only link blocks these
    assert control - telemetry == COMMANDING
    assert COMMANDING <= _COMMANDING  # and every command is one the read-only link refuses


def test_the_checker_sees_a_wrong_kind() -> None:
    class Broken:
        def arm(self) -> None:  # a sync arm is not the declared coroutine
            pass

        async def hold(self, timeout: float) -> None:  # declared optional
            pass

    problems = _check(Broken, VehicleControl)
    assert "arm: method, declared coroutine" in problems and "takeoff: missing" in problems
    assert "hold: timeout is required, declared optional" in problems


@pytest.mark.parametrize("impl", [SihTruth, LinkPositionTruth])
def test_truth_sources_satisfy_truth_source(impl: type) -> None:
    assert _check(impl, TruthSource) == []


def test_link_position_truth_is_the_links_own_position() -> None:
    link = SimpleNamespace(position_for_log=None, attitude=None)
    truth = LinkPositionTruth(link)
    assert truth.latest() is None and truth.at(1.0) is None
    link.position_for_log = TruthForLog(np.array([1.0, 2.0, -3.0]), np.array([0.5, 0.0, 0.0]), 7.0)
    assert truth.latest() is link.position_for_log and truth.at(7.0) is None  # no attitude yet
    link.attitude = SimpleNamespace(q_wxyz=np.array([1.0, 0.0, 0.0, 0.0]), t_rx=7.01)
    pose = truth.at(7.01)
    assert pose is not None and pose.t_rx == 7.01
    assert np.array_equal(pose.position_ned, [1.0, 2.0, -3.0]) and np.array_equal(pose.q_wxyz, [1, 0, 0, 0])
    truth.close()  # nothing to release; the link is not closed by it


def test_vehicle_module_imports_nothing_from_the_app() -> None:
    tree = ast.parse(Path(vehicle.__file__).read_text())
    names = [a.name for n in ast.walk(tree) if isinstance(n, ast.Import) for a in n.names]
    names += [n.module or "" for n in ast.walk(tree) if isinstance(n, ast.ImportFrom)]
    assert not [m for m in names if m.startswith("companion")], names
