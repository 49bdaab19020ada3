"""Fault injection for tests: `VINETWIN_FAULT=kill:KEY[@STAGE]` makes the process that reaches
`fault_point(KEY, STAGE)` SIGKILL itself there; with `VINETWIN_FAULT_ONCE=FILE` only the first
time (the file marks it done). Keys are job keys (a reference's `TWIN/POSE`, a validation group,
a campaign run) or, for `atomic_write_bytes`, the path being written. Kept apart from the
executor so that the twin format's writes can carry a fault point without importing process
pools."""

from __future__ import annotations

import os

FAULT_VAR = "VINETWIN_FAULT"


def fault_point(key: str, stage: str = "") -> None:
    """Kills this process when `VINETWIN_FAULT` names this key (and stage). Does nothing
    otherwise."""
    spec = os.environ.get(FAULT_VAR, "")
    if not spec.startswith("kill:"):
        return
    want_key, _, want_stage = spec[5:].partition("@")
    if want_key == key and want_stage == stage:
        marker = os.environ.get(FAULT_VAR + "_ONCE", "")
        if marker:  # kill only the first attempt
            try:
                fd = os.open(marker, os.O_CREAT | os.O_EXCL | os.O_WRONLY)
                os.close(fd)
            except FileExistsError:
                return
        os.kill(os.getpid(), 9)
