"""Plain-JSON round trip shared by vinetwin's frozen config dataclasses (camera, perception,
sensor): `to_dict` gives their fields; `from_dict` ignores keys it does not know, so a file
written by a newer vinetwin still loads."""

from __future__ import annotations

import dataclasses
import functools
import math
import typing
from typing import Any, Self

from vinetwin.errors import InputError


def json_default(x: Any) -> Any:
    """`json.dumps(default=...)` for numpy scalars and arrays in result records."""
    import numpy as np

    if isinstance(x, np.generic | np.ndarray):
        return x.tolist()
    raise TypeError(f"not JSON serialisable: {type(x).__name__}")


class JsonFields:
    """Mixin for dataclasses stored in twin.json and reference sidecars."""

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)  # type: ignore[arg-type]

    def _nested_from_dicts(self) -> None:
        """Rebuilds nested config fields given as dicts (as `Config(**other.to_dict())` passes
        them); call from `__post_init__`."""
        hints = _hints(type(self))
        for f in dataclasses.fields(self):  # type: ignore[arg-type]
            v, t = getattr(self, f.name), hints.get(f.name)
            if isinstance(v, dict) and isinstance(t, type) and issubclass(t, JsonFields):
                object.__setattr__(self, f.name, t.from_dict(v))

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> Self:
        """The dataclass from `to_dict`'s output; nested config dataclasses are rebuilt from
        their dicts, tuples from lists, and unknown keys are ignored."""
        hints = _hints(cls)
        out: dict[str, Any] = {}
        for f in dataclasses.fields(cls):  # type: ignore[arg-type]
            if f.name not in data:
                continue
            v, t = data[f.name], hints.get(f.name)
            if isinstance(v, dict) and isinstance(t, type) and issubclass(t, JsonFields):
                v = t.from_dict(v)
            elif isinstance(v, list) and typing.get_origin(t) is tuple:
                v = _tuple(v)
            _check_scalar(cls, f.name, v, t)
            out[f.name] = v
        return cls(**out)


#: What a scalar field of each type accepts from JSON (a bool is no number here).
_SCALARS: dict[type, tuple[type, ...]] = {
    float: (int, float),
    int: (int,),
    bool: (bool,),
    str: (str,),
}


def _check_scalar(cls: type, name: str, v: Any, t: Any) -> None:
    """Raises InputError when a JSON value cannot be a scalar field's type (a profile file's
    "0.5" or null for a number): named here rather than a TypeError deep in a check."""
    if typing.get_origin(t) is tuple:
        from vinetwin.errors import InputError

        if not isinstance(v, tuple):
            raise InputError(f"{cls.__name__}.{name} must be a list, got {v!r}")
        args = typing.get_args(t)
        for i, x in enumerate(v):
            _check_scalar(
                cls,
                f"{name}[{i}]",
                x,
                args[0] if args[-1] is Ellipsis else args[min(i, len(args) - 1)],
            )
        return
    accepted = _SCALARS.get(t) if isinstance(t, type) else None
    if accepted is None:
        return
    if not isinstance(v, accepted) or (t is not bool and isinstance(v, bool)):
        from vinetwin.errors import InputError

        raise InputError(f"{cls.__name__}.{name} must be a {t.__name__}, got {v!r}")


def _tuple(v: list[Any]) -> tuple[Any, ...]:
    return tuple(_tuple(x) if isinstance(x, list) else x for x in v)


@functools.cache
def _hints(cls: type) -> dict[str, Any]:
    try:
        return typing.get_type_hints(cls)
    except (NameError, TypeError):  # an annotation only known to type checkers
        return {}


def check_finite(config: object, names: tuple[str, ...], positive: bool = False) -> None:
    """Raises InputError naming the first of `names` that is not a finite number > 0
    (`positive`) or >= 0: a limit that NaN, infinity, a negative number or a string (a profile
    file's "0.5") would switch off."""
    for name in names:
        v = getattr(config, name)
        if isinstance(v, bool) or not isinstance(v, int | float):
            raise InputError(f"{name} must be a number, got {v!r}")
        if not (math.isfinite(v) and (v > 0 if positive else v >= 0)):
            raise InputError(
                f"{name} must be {'positive' if positive else '>= 0'} and finite, got {v}"
            )


def check_counts(config: object, names: tuple[str, ...], ceiling: int = 2**32) -> None:
    """Raises InputError naming the first of `names` (seeds, counts of workers) that is not an
    integer in [0, ceiling)."""
    for name in names:
        v = getattr(config, name)
        if isinstance(v, bool) or not isinstance(v, int) or not 0 <= v < ceiling:
            raise InputError(f"{name} must be an integer in [0, {ceiling}), got {v!r}")


def check_at_most(config: object, ceilings: dict[str, float], why: str) -> None:
    """Raises InputError naming the first field of `ceilings` above its ceiling, and `why`."""
    for name, ceiling in ceilings.items():
        v = getattr(config, name)
        if v > ceiling:
            raise InputError(f"{name} {v:g} is above {ceiling:g} {why}")
