"""The exception hierarchy of vinetwin: every error the package raises on purpose is a
`VinetwinError`, so a caller (the CLI, the web app, a servo loop) can catch one type and show
its message, which says what was wrong and what would be valid."""

from __future__ import annotations

import logging


class VinetwinError(Exception):
    """Root of every error raised on purpose by vinetwin."""


class InputError(VinetwinError, ValueError):
    """An argument to a public function has the wrong shape, type or value."""


class PoseError(InputError):
    """A 4x4 pose is not a finite rigid transform."""


class ArrivalError(VinetwinError):
    """Arrival registration refused: where the vine stands could not be established from the
    first frame (too little agreement with the twin, an ambiguous view); nothing moved."""


class CameraError(InputError):
    """A camera model is inconsistent (non-positive focal length, depth range, size)."""


class TwinError(VinetwinError):
    """A twin folder or its twin.json cannot be read, validated or written."""


class TwinFieldError(TwinError):
    """A field of twin.json is missing or holds a bad value; `field` is its path."""

    def __init__(self, path: str, field: str, message: str) -> None:
        self.path = path
        self.field = field
        super().__init__(f"{path}: field '{field}': {message}")


class TwinConflictError(TwinError):
    """A save would overwrite a change another writer saved to the same field of twin.json."""


class TwinVersionError(TwinError):
    """twin.json was written by a newer format version than this vinetwin can read."""


class OutputError(VinetwinError):
    """A file vinetwin writes cannot be written (a full disk, no permission); names the file."""


class MeshError(VinetwinError):
    """A mesh is missing, unreadable, empty or holds non-finite vertices."""


class ImportFormatError(VinetwinError):
    """A skeleton file (hydroshoot digit.input, cylinder list) cannot be parsed."""


class ScanError(VinetwinError):
    """A scan (point cloud or mesh file) cannot be read, or what it holds is not a plant that
    `import-scan` can make a twin of (empty, all NaN, a plane, a ball, a scale no plant has)."""


class SeveralPlants(ScanError):
    """A scan of a row holds `count` plants and none was named (`--plant-number`)."""

    def __init__(self, message: str, count: int) -> None:
        self.count = count
        super().__init__(message)


class BackendUnavailable(VinetwinError):
    """A rendering backend cannot start here (no EGL, library missing); `reason` says why."""

    def __init__(self, backend: str, reason: str) -> None:
        self.backend = backend
        self.reason = reason
        super().__init__(f"render backend '{backend}' is unavailable: {reason}")


def raise_if_interrupt(exc: BaseException) -> None:
    """Raises KeyboardInterrupt when `exc` is one, or was caused by one. Ctrl-C landing while a
    compiled (numba) kernel runs comes out of the kernel's call as `SystemError: CPUDispatcher
    (...) returned a result with an exception set`, the interrupt as its cause: every handler
    that turns an exception into a failed job, a refused frame or a named failure calls this
    first, so an interrupt always stops the run."""
    seen: set[int] = set()
    e: BaseException | None = exc
    while e is not None and id(e) not in seen:
        if isinstance(e, KeyboardInterrupt):
            raise KeyboardInterrupt from exc
        seen.add(id(e))
        e = e.__cause__ or e.__context__


def exit_status(exc: BaseException, log: logging.Logger) -> int:
    """The exit status of a command that raised `exc`, its error named on `log`: 2 for a
    refused input or a file that cannot be read or written, 130 for Ctrl-C (also when it
    landed inside a compiled kernel); anything else is a bug, raised with its traceback."""
    if isinstance(exc, SystemExit):  # --help, or tyro's named error for a refused value
        return exc.code if isinstance(exc.code, int) else 2
    if isinstance(exc, VinetwinError):
        log.error("%s", exc)
        return 2
    if isinstance(exc, OSError):  # not a traceback
        log.error("%s%s", f"{exc.filename}: " if exc.filename else "", exc.strerror or exc)
        return 2
    try:
        raise_if_interrupt(exc)
    except KeyboardInterrupt:
        log.error("interrupted")
        return 130
    raise exc
