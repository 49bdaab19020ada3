"""OpenGL and EGL housekeeping shared by the OpenGL backends (`pyrender`, `mujoco`): the
platform a headless process needs, and EGL displays and contexts that outlive one renderer."""

from __future__ import annotations

import os
from typing import Any

from vinetwin.errors import BackendUnavailable


def _require_gl(backend: str) -> None:
    plat = os.environ.get("PYOPENGL_PLATFORM")
    if plat is None and not os.environ.get("DISPLAY"):
        os.environ["PYOPENGL_PLATFORM"] = "egl"
    elif plat not in (None, "egl", "osmesa") and not os.environ.get("DISPLAY"):
        raise BackendUnavailable(
            backend, f"PYOPENGL_PLATFORM={plat} needs a display; use egl or osmesa"
        )


def _keep_egl_display_alive(renderer: Any) -> None:
    """pyrender's EGL teardown calls eglTerminate on the display, which EGL shares across the
    whole process: a MuJoCo renderer in the same process then fails with EGL_BAD_DISPLAY. Make
    this renderer destroy only its own context."""
    platform = getattr(renderer, "_platform", None)
    if platform is None or type(platform).__name__ != "EGLPlatform":
        return

    def delete_context() -> None:
        from OpenGL.EGL import eglDestroyContext

        if platform._egl_display is not None and platform._egl_context is not None:
            eglDestroyContext(platform._egl_display, platform._egl_context)
        platform._egl_context = None
        platform._egl_display = None

    platform.delete_context = delete_context


def _mujoco_gl() -> str:
    """The OpenGL platform a MuJoCo renderer made now would use: MUJOCO_GL, else EGL without a
    display (what `MujocoBackend` sets) and GLFW with one (MuJoCo's own default)."""
    gl = os.environ.get("MUJOCO_GL")
    if gl:
        return gl.lower()
    return "glfw" if os.environ.get("DISPLAY") else "egl"


def _mujoco_egl() -> Any:
    """`mujoco.egl` where MuJoCo renders through EGL (`_mujoco_gl`), else None."""
    if _mujoco_gl() != "egl":
        return None
    try:
        from mujoco import egl
    except Exception:
        return None
    return egl


def _egl_reinitialize() -> None:
    """With EGL: initialises again the EGL display MuJoCo keeps for the process, in case a
    library sharing it (pyrender's `OffscreenRenderer.delete`, used directly) terminated it;
    MuJoCo would otherwise fail with EGL_NOT_INITIALIZED until the process ends. A no-op on an
    initialised display."""
    egl = _mujoco_egl()
    if egl is not None and egl.EGL_DISPLAY is not None:
        egl.EGL.eglInitialize(egl.EGL_DISPLAY, None, None)


def _egl_release() -> Any:
    """With EGL: a function releasing this thread's current EGL context (a context is current in
    one thread at a time; released, another thread can take it); else None."""
    egl = _mujoco_egl()
    if egl is None:
        return None

    def release() -> None:
        E = egl.EGL
        if egl.EGL_DISPLAY is not None:
            E.eglMakeCurrent(egl.EGL_DISPLAY, E.EGL_NO_SURFACE, E.EGL_NO_SURFACE, E.EGL_NO_CONTEXT)

    return release
