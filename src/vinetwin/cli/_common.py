"""What the command modules share: tyro's markers, the backend choice, the log."""

from __future__ import annotations

import logging
from typing import Literal

import tyro

from vinetwin.render.backends import BackendName

log = logging.getLogger("vinetwin")

Positional, Nested = tyro.conf.Positional, tyro.conf.OmitArgPrefixes
#: "auto" or a render backend (`render.backends.BACKENDS`, where the names are declared).
BackendChoice = Literal["auto"] | BackendName


def _summary(twin: object) -> None:
    """Prints what a twin holds (`vinetwin info`)."""
    from vinetwin.twin.summary import print_summary

    print_summary(twin)  # type: ignore[arg-type]
