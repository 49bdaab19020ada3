"""Debian's Chromium, headless, as the tests and `benchmarks/web.py` drive the app: through
Playwright with `executable_path` (no browser is ever downloaded; `scripts/setup.sh` installs
Debian's `chromium`)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

#: Where Debian installs Chromium.
CHROMIUM = Path("/usr/bin/chromium")
#: Flags for a headless run as root in a container, with nothing phoning home.
CHROMIUM_ARGS = [
    "--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
    "--disable-background-networking", "--disable-component-update", "--disable-sync",
]  # fmt: skip


def launch(playwright: Any, profile_dir: str | Path) -> Any:
    """A headless Chromium context (a 1200x800 page) with its profile in `profile_dir`."""
    return playwright.chromium.launch_persistent_context(
        str(profile_dir), executable_path=str(CHROMIUM), headless=True, args=CHROMIUM_ARGS,
        viewport={"width": 1200, "height": 800},
    )  # fmt: skip
