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

    display_faces: int = 60_000
    """The most triangles of the vine the page draws (0: all). A larger mesh is shown decimated
    by quadric error (`vinetwin.web.display`): before the app starts up to 300k triangles
    (about 1 s); a larger one at once with its vertices clustered, then decimated in the
    background (8.8 s for the dense generated vine's 897k). Clicks still hit the full mesh on
    the server. In software WebGL (SwiftShader) the dense vine's click to the page's next frame
    took 441 ms with 60k against 953 ms with every triangle (`docs/web.md`)."""

    def __post_init__(self) -> None:
        from vinetwin.errors import InputError

        if not (self.display_faces == 0 or self.display_faces >= 1000):
            raise InputError(
                f"WebConfig.display_faces must be 0 (every triangle) or at least 1000, not "
                f"{self.display_faces}"
            )

        if self.shading not in ("fast", "full"):
            raise InputError(f"WebConfig.shading must be 'fast' or 'full', not {self.shading!r}")
