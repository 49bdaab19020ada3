"""Lazy imports of heavy libraries, typed as Any: their bundled stubs are incomplete or wrong
(open3d's Tensor constructors, mujoco's module attributes), and importing them only where used
keeps `import vinetwin` light."""

from __future__ import annotations

import importlib
from typing import Any


def open3d() -> Any:
    """The open3d module (needs Debian's libusb-1.0-0 on a bare machine)."""
    return importlib.import_module("open3d")


def mujoco() -> Any:
    """The mujoco module."""
    return importlib.import_module("mujoco")


def module(name: str, needed_for: str) -> Any:
    """An optional library, or an InputError that says what needs it and how to install it."""
    try:
        return importlib.import_module(name)
    except ImportError as exc:
        from vinetwin.errors import InputError

        raise InputError(f"{needed_for} needs the `{name}` package: {exc}") from exc
