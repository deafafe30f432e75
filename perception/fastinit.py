"""A cheaper ``__init__`` for the frozen, slotted dataclasses built every frame.

A frozen dataclass's generated ``__init__`` sets each field with ``object.__setattr__(self, name, value)`` (a
frozen class overrides ``__setattr__`` to raise). That generic path looks the attribute up by name for every
field: ~0.25 us a field, and a frame builds some 70 fields of boxes, setpoints, controller outputs and decisions
(about a tenth of the controller's step, issue 21). :func:`fast_init` gives such a class an ``__init__`` that calls
each slot's descriptor directly: the same object, the same fields, defaults and signature, the class stays frozen
(assignment after construction still raises ``FrozenInstanceError``), about 2.5x faster.
"""

from __future__ import annotations

import dataclasses
from typing import TypeVar

T = TypeVar("T", bound=type)


def fast_init(cls: T) -> T:
    """Class decorator (above ``@dataclass(frozen=True, slots=True)``): replace the generated ``__init__``.

    Only for the plain case: every field an ordinary positional init field, no ``default_factory``, no
    ``InitVar``. A ``__post_init__`` (validation) is called last, as the dataclass ``__init__`` calls it."""
    name = cls.__qualname__
    params = getattr(cls, "__dataclass_params__", None)
    if params is None or not params.frozen or "__slots__" not in cls.__dict__:
        raise TypeError(f"fast_init({name}): needs a @dataclass(frozen=True, slots=True) class")
    if len(cls.__dataclass_fields__) != len(dataclasses.fields(cls)):  # type: ignore[attr-defined]
        raise TypeError(f"fast_init({name}): has an InitVar or ClassVar pseudo-field (keep the dataclass __init__)")
    args: list[str] = []
    body: list[str] = []
    env: dict[str, object] = {}
    for f in dataclasses.fields(cls):
        if not f.init or f.kw_only or f.default_factory is not dataclasses.MISSING:
            raise TypeError(f"fast_init({name}): field {f.name!r} is not a plain positional init field")
        slot = cls.__dict__.get(f.name)
        if type(slot).__name__ != "member_descriptor":
            raise TypeError(f"fast_init({name}): field {f.name!r} is not a slot")
        env[f"_set_{f.name}"] = slot.__set__
        if f.default is dataclasses.MISSING:
            args.append(f.name)
        else:
            env[f"_default_{f.name}"] = f.default
            args.append(f"{f.name}=_default_{f.name}")
        body.append(f"    _set_{f.name}(self, {f.name})")
    if hasattr(cls, "__post_init__"):
        body.append("    self.__post_init__()")
    src = f"def __init__(self, {', '.join(args)}):\n" + ("\n".join(body) or "    pass") + "\n"
    local: dict[str, object] = {}
    exec(src, env, local)
    init = local["__init__"]
    init.__qualname__ = f"{name}.__init__"  # type: ignore[attr-defined]
    init.__module__ = cls.__module__  # type: ignore[attr-defined]
    init.__doc__ = cls.__init__.__doc__  # type: ignore[misc]
    cls.__init__ = init  # type: ignore[misc]
    return cls
