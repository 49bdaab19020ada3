"""Debian's Chromium, headless, as the tests and `benchmarks/web.py` drive the app: through
Playwright with `executable_path` (no browser is ever downloaded; `scripts/setup.sh` installs
Debian's `chromium`)."""

from __future__ import annotations

import os
import signal
import threading
from pathlib import Path
from typing import Any, Literal

#: Where Debian installs Chromium.
CHROMIUM = Path("/usr/bin/chromium")
#: Flags for a headless run as root in a container, with nothing phoning home.
CHROMIUM_ARGS = [
    "--headless", "--no-sandbox", "--disable-quic", "--no-first-run",
    "--disable-background-networking", "--disable-component-update", "--disable-sync",
]  # fmt: skip
#: How the page's WebGL is drawn without a GPU: "swiftshader", Chromium's own software
#: renderer (needs nothing but Chromium; what the tests use), or "llvmpipe", the machine's Mesa
#: through EGL (ANGLE's OpenGL ES back end; the EGL libraries MuJoCo's rendering installs), which
#: drew the app's frames about twice as fast on the 2-core machine (`docs/web.md`).
#: SwiftShader runs as the GPU process's device (ANGLE on SwiftShader's Vulkan), so the page is
#: composited there too. With `--disable-gpu` instead, the compositor is software and reads each
#: WebGL frame back on the page's main thread, which then waits for every frame to be drawn before
#: it handles anything else: a click's preview took about 1.5x as long (`docs/web.md`).
#: `--enable-unsafe-swiftshader` is Chromium's opt-in for WebGL on SwiftShader; the page is the
#: app's own, on this machine.
GL_ARGS: dict[str, list[str]] = {
    "swiftshader": ["--use-angle=swiftshader", "--enable-unsafe-swiftshader"],
    "llvmpipe": ["--use-angle=gl-egl", "--ignore-gpu-blocklist"],
}
Gl = Literal["swiftshader", "llvmpipe"]
#: The page's WebGL renderer, as the page reports it.
RENDERER_JS = """() => { const g = document.createElement('canvas').getContext('webgl2');
    if (!g) return 'no WebGL2'; const e = g.getExtension('WEBGL_debug_renderer_info');
    return String(e ? g.getParameter(e.UNMASKED_RENDERER_WEBGL) : g.getParameter(g.RENDERER)); }"""


#: A browser still open this long (s) after its launch is killed (`launch`).
DEADLINE_S = 300.0


def _chromium_descendants() -> list[int]:
    """PIDs of the Chromium processes below this one (Linux `/proc`; none elsewhere)."""
    children: dict[int, list[int]] = {}
    for d in Path("/proc").glob("[0-9]*"):
        try:
            ppid = int((d / "stat").read_text().rsplit(")", 1)[1].split()[1])
        except (OSError, ValueError, IndexError):
            continue
        children.setdefault(ppid, []).append(int(d.name))
    out, todo = [], [os.getpid()]
    while todo:
        for c in children.get(todo.pop(), []):
            todo.append(c)
            try:
                if "chromium" in os.readlink(f"/proc/{c}/exe"):
                    out.append(c)
            except OSError:
                continue
    return out


#: How many times `kill_chromium` has killed a browser in this process.
kills = 0


def kill_chromium() -> int:
    """SIGKILL every Chromium process started below this one; how many were killed."""
    global kills
    n = 0
    for pid in _chromium_descendants():
        try:
            os.kill(pid, signal.SIGKILL)
            n += 1
        except OSError:
            continue
    kills += n > 0
    return n


def launch(
    playwright: Any, profile_dir: str | Path, gl: Gl = "swiftshader",
    deadline_s: float | None = DEADLINE_S,
) -> Any:  # fmt: skip
    """A headless Chromium context (a 1200x800 page) with its profile in `profile_dir`, its
    WebGL drawn by `gl` (`GL_ARGS`).

    A browser still open `deadline_s` after its launch is killed (`kill_chromium`), so that
    whatever waits on it fails with Playwright's "target closed" error instead of waiting for
    ever: a software-rendered Chromium has been seen to spin for 20 minutes, holding its test
    past pytest-timeout's alarm (which cannot end a wait inside the browser's teardown). None:
    no deadline."""
    if gl not in GL_ARGS:
        raise ValueError(f"gl must be one of {sorted(GL_ARGS)}, not {gl!r}")
    ctx = playwright.chromium.launch_persistent_context(
        str(profile_dir), executable_path=str(CHROMIUM), headless=True,
        args=CHROMIUM_ARGS + GL_ARGS[gl], viewport={"width": 1200, "height": 800},
    )  # fmt: skip
    if deadline_s is not None:
        timer = threading.Timer(deadline_s, kill_chromium)
        timer.daemon = True
        timer.start()
        ctx.on("close", lambda *_: timer.cancel())
    return ctx
