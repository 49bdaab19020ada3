"""Plain-JSON round trip shared by vinetwin's frozen config dataclasses (camera, perception,
sensor): `to_dict` gives their fields; `from_dict` ignores keys it does not know, so a file
written by a newer vinetwin still loads."""

from __future__ import annotations

import dataclasses
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

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> Self:
        names = {f.name for f in dataclasses.fields(cls)}  # type: ignore[arg-type]
        return cls(**{k: v for k, v in data.items() if k in names})
