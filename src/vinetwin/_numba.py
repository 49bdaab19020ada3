"""numba, configured once for every module of compiled kernels: the threading layers in the
order `import vinetwin` set in the environment, also where numba was imported before it (its
environment variable read then). Each kernel module imports `nb` from here, so the setting is made
on the import of the first of them, not on each pass."""

from __future__ import annotations

import numba as nb
from numba.core import config as _nb_config

from vinetwin import NUMBA_THREADING_LAYERS

_nb_config.THREADING_LAYER_PRIORITY = list(NUMBA_THREADING_LAYERS)  # type: ignore[attr-defined]

__all__ = ["nb"]
