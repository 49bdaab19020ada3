"""Plain-JSON round trip shared by vinetwin's frozen config dataclasses (camera, perception,
sensor): `to_dict` gives their fields; `from_dict` ignores keys it does not know, so a file
written by a newer vinetwin still loads."""

from __future__ import annotations

import dataclasses
import functools
import typing
from typing import Any, Self


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
            out[f.name] = v
        return cls(**out)


def _tuple(v: list[Any]) -> tuple[Any, ...]:
    return tuple(_tuple(x) if isinstance(x, list) else x for x in v)


@functools.cache
def _hints(cls: type) -> dict[str, Any]:
    try:
        return typing.get_type_hints(cls)
    except (NameError, TypeError):  # an annotation only known to type checkers
        return {}
