"""perception/fastinit.py: the fast __init__ builds the same frozen objects as the dataclass one."""

from __future__ import annotations

import dataclasses
import inspect
import math

import numpy as np
import pytest

from companion.controller import ControlOutput
from companion.core import CoreStep, FrameInput
from companion.engagement import Decision, Phase
from companion.guidance import Setpoint, ThrustAttitude
from perception.fastinit import fast_init
from perception.types import BoundingBox


@dataclasses.dataclass(frozen=True, slots=True)
class _Plain:
    a: float
    b: object
    c: float = math.nan
    d: str = "x"


_Fast = fast_init(dataclasses.make_dataclass("_Fast", [("a", float), ("b", object), ("c", float, math.nan),
                                                      ("d", str, "x")], frozen=True, slots=True))


def test_same_fields_defaults_and_equality_as_the_dataclass_init() -> None:
    v = np.arange(3.0)
    for args, kw in [((1.0, v), {}), ((1.0, v, 2.0), {}), ((1.0,), {"b": v, "d": "y"}), ((), {"a": 3.0, "b": None})]:
        plain, fast = _Plain(*args, **kw), _Fast(*args, **kw)
        assert (fast.a, fast.d) == (plain.a, plain.d)
        assert fast.b is plain.b
        assert fast.c == plain.c or (math.isnan(fast.c) and math.isnan(plain.c))
    assert list(inspect.signature(_Fast).parameters) == ["a", "b", "c", "d"]
    assert inspect.signature(_Fast).parameters["d"].default == "x"


def test_still_frozen_and_missing_arguments_still_raise() -> None:
    x = _Fast(1.0, 2)
    with pytest.raises(dataclasses.FrozenInstanceError):
        x.a = 2.0  # type: ignore[misc]
    with pytest.raises(TypeError):
        _Fast(1.0)  # type: ignore[call-arg]
    with pytest.raises(TypeError):
        _Fast(1.0, 2, 3.0, "y", 5)  # type: ignore[call-arg]
    assert dataclasses.replace(x, a=5.0) == _Fast(5.0, 2)


def test_refuses_classes_it_cannot_copy_exactly() -> None:
    @dataclasses.dataclass(frozen=True, slots=True)
    class WithInitVar:
        a: float
        b: dataclasses.InitVar[float] = 0.0

        def __post_init__(self, b: float) -> None:
            pass

    @dataclasses.dataclass(frozen=True)
    class NoSlots:
        a: float

    @dataclasses.dataclass(frozen=True, slots=True)
    class Factory:
        a: list = dataclasses.field(default_factory=list)

    for cls in (WithInitVar, NoSlots, Factory):
        with pytest.raises(TypeError, match="fast_init"):
            fast_init(cls)


def test_the_project_classes_keep_their_values_and_stay_frozen() -> None:
    """Every decorated class: each field reads back what was passed (or its default), and stays frozen."""
    R, q, a = np.eye(3), np.array([1.0, 0.0, 0.0, 0.0]), np.array([0.0, 1.0, 0.0])
    sp = Setpoint(1.0, 2.0, 3.0, 0.5, R)
    box = BoundingBox(320.0, 240.0, 40.0, 30.0)
    objs = [
        (sp, dict(roll_deg=1.0, pitch_deg=2.0, yaw_deg=3.0, thrust=0.5, R_ned_frd=R)),
        (box, dict(cx=320.0, cy=240.0, w=40.0, h=30.0, confidence=1.0, t=0.0, appearance=None)),
        (ThrustAttitude(9.0, 0.1, 0.2, R, 1.0, False),
         dict(f_th=9.0, phi=0.1, theta=0.2, R_W_B=R, demand_scale=1.0, fallback=False)),
        (Decision(1.5, Phase.ENGAGE, sp), dict(t=1.5, phase=Phase.ENGAGE, setpoint=sp, control=None, why="",
                                               previous=None, reason=None, events=())),
        (FrameInput(2.0, box, q), dict(t=2.0, box=box, q_wxyz_ned_frd=q, baro_rel_alt=None, events=())),
        (ControlOutput(0.1, sp, "pn", None, 0.3, a, 1.0, 9.8, None),
         dict(t=0.1, setpoint=sp, mode="pn", los_ned=None, lambda_dot=0.3, a_n=a, demand_scale=1.0, f_th=9.8,
              rejected=None)),
    ]
    for obj, expect in objs:
        for name, value in expect.items():
            got = getattr(obj, name)
            assert got is value if isinstance(value, np.ndarray) else got == value, (type(obj).__name__, name)
        with pytest.raises(dataclasses.FrozenInstanceError):
            setattr(obj, next(iter(expect)), 0.0)
    assert math.isnan(objs[-1][0].v_rel)
    assert CoreStep(objs[3][0]).passes_confirmed == 0
    assert BoundingBox.from_xyxy(10.0, 20.0, 30.0, 60.0) == BoundingBox(20.0, 40.0, 20.0, 40.0)


def test_post_init_runs_last() -> None:
    """A class that validates in __post_init__ keeps validating: it runs after every field is set."""

    @fast_init
    @dataclasses.dataclass(frozen=True, slots=True)
    class Validated:
        a: float
        b: float = 1.0

        def __post_init__(self) -> None:
            if not self.a < self.b:
                raise ValueError("need a < b")

    assert (Validated(0.5).a, Validated(0.5).b, Validated(1.0, b=2.0).b) == (0.5, 1.0, 2.0)
    with pytest.raises(ValueError, match="a < b"):
        Validated(3.0)
    with pytest.raises(dataclasses.FrozenInstanceError):
        Validated(0.5).a = 0.0  # type: ignore[misc]
