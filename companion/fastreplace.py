"""``dataclasses.replace`` for the per-frame paths: the same result (the class's own ``__init__`` and
``__post_init__`` run, so validation is unchanged), without re-reading the class's fields on every call.

The hover-thrust estimate updates the controller's and the engagement's parameters every frame; the stdlib
``replace`` inspects the fields each time, which cost more than the guidance solve.
"""

from __future__ import annotations

import dataclasses
from typing import Any, TypeVar

T = TypeVar("T")

_INIT_FIELDS: dict[type, tuple[str, ...]] = {}


def replace(obj: T, **changes: Any) -> T:
    """A copy of the dataclass instance ``obj`` with ``changes`` (keyword per field), like ``dataclasses.replace``."""
    cls = type(obj)
    names = _INIT_FIELDS.get(cls)
    if names is None:
        fs = dataclasses.fields(obj)  # type: ignore[arg-type]
        if any(f._field_type is dataclasses._FIELD_INITVAR for f in fs):  # type: ignore[attr-defined]
            return dataclasses.replace(obj, **changes)  # InitVars need the stdlib's handling
        for f in fs:
            if not f.init and f.name in changes:
                raise ValueError(f"field {f.name} is declared with init=False, it cannot be specified with replace()")
        names = _INIT_FIELDS.setdefault(cls, tuple(f.name for f in fs if f.init))
    kw = {n: getattr(obj, n) for n in names}
    kw.update(changes)
    return cls(**kw)
