"""A picture of what the camera sees at a pruning pose: the D405 depth image and the reference
cloud (as a top and a side view), for people to look at."""

from __future__ import annotations

import logging
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from vinetwin.errors import InputError
from vinetwin.files import refuse_existing, save_figure
from vinetwin.render.reference import Reference

if TYPE_CHECKING:
    from vinetwin.twin.model import Twin

log = logging.getLogger(__name__)


def preview_pose(
    twin: Twin,
    pose_id: str,
    out: str | Path,
    backend: str | None = None,
    seed: int = 0,
    overwrite: bool = False,
) -> Reference:
    """Renders one pose's reference (the export's settings and noise seed) and writes its
    preview PNG to `out`; returns the reference. `backend` None or "auto": the one
    `render.backends.resolve_backend` picks for a single view."""
    from vinetwin.render.backends import get_backend, resolve_backend
    from vinetwin.render.reference import reference_for

    out = Path(out)
    if out.suffix.lower() != ".png":
        raise InputError(f"--out must name a .png file, got {out}")
    if out.exists() and out.is_dir():
        raise InputError(f"--out {out} is a folder; name a .png file")
    refuse_existing(out, "--out", overwrite)
    out.parent.mkdir(parents=True, exist_ok=True)
    pose = twin.pose(pose_id)
    mesh = twin.load_mesh()
    backend = resolve_backend(backend)
    renderer = get_backend(backend, mesh.vertices, mesh.faces, twin.camera)
    try:
        ref = reference_for(twin, pose.id, use_exported=False, renderer=renderer, seed=seed)
    finally:
        renderer.close()
    save_preview(ref, out, f"{twin.name} / {pose.id} ({backend})")
    if ref.cloud.empty:
        log.warning(
            "pose %s sees nothing within %.2f m: empty reference cloud",
            pose.id,
            twin.perception.max_depth,
        )
    log.info("wrote %s (%d points)", out, len(ref.cloud))
    return ref


def save_preview(ref: Reference, path: str | Path, title: str = "") -> None:
    """Writes a PNG with the depth image (turbo colours, metres) and two views of the cloud."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    if ref.depth is None:
        raise InputError("a preview needs the rendered depth, not an exported cloud")
    d = np.where(ref.depth > 0, ref.depth, np.nan)
    fig, axes = plt.subplots(1, 3, figsize=(15, 4.2), gridspec_kw={"width_ratios": [1.8, 1, 1]})
    im = axes[0].imshow(d, cmap="turbo")
    axes[0].set_title("D405 depth (m)")
    axes[0].set_xlabel("u (px)")
    axes[0].set_ylabel("v (px)")
    fig.colorbar(im, ax=axes[0], fraction=0.03)
    p = ref.cloud.points
    sc = None
    for ax, (i, j, name) in zip(
        axes[1:],
        [(0, 1, "front (x right, y down)"), (0, 2, "top (x right, z forward)")],
        strict=True,
    ):
        if len(p):
            sc = ax.scatter(p[:, i], p[:, j], c=p[:, 2], s=2, cmap="turbo")
            ax.set_aspect("equal")
            if j == 1:
                ax.invert_yaxis()
        ax.set_title(f"reference cloud, {name}")
        ax.set_xlabel("m")
    if sc is not None:
        fig.colorbar(sc, ax=axes[2], fraction=0.04, label="depth (m)")
    fig.suptitle(f"{title}  ({len(p)} points)")
    fig.tight_layout()
    save_figure(fig, path, 80)
    plt.close(fig)
