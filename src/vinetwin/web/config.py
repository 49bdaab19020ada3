"""The authoring app's settings (`vinetwin web --config.*`)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

from vinetwin._config import JsonFields

Shading = Literal["fast", "full"]


@dataclass(frozen=True, kw_only=True)
class WebConfig(JsonFields):
    """How the page draws the scene."""

    shading: Shading = "fast"
    """How the browser shades the vine: "fast", toon shading without shadows, or "full",
    physically based shading lit by an environment map, with shadows. A browser that draws
    WebGL in software (headless Chromium, a machine without a GPU or with its acceleration off)
    redraws the whole view after each click; there, "fast" showed the preview 2-3x sooner on
    the bundled sample (`docs/web.md`). With a GPU either is quick."""

    def __post_init__(self) -> None:
        from vinetwin.errors import InputError

        if self.shading not in ("fast", "full"):
            raise InputError(f"WebConfig.shading must be 'fast' or 'full', not {self.shading!r}")
