"""Render the reference cloud a D405 would see at a pruning pose, by each backend.

Renders the bundled sample's first pose with Open3D ray casting (and pyrender and MuJoCo when EGL
is available), applies the D405 sensor model, runs the shared perception chain, and prints how
the backends agree and what the reference holds. Writes a preview PNG.

    .venv/bin/python samples/02_reference_cloud.py [--out preview.png] [--quick]
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from vinetwin.errors import BackendUnavailable
from vinetwin.render.backends import BACKENDS, get_backend
from vinetwin.render.preview import save_preview
from vinetwin.render.reference import reference_for
from vinetwin.twin import Twin

SAMPLE = Path(__file__).resolve().parent / "vine_bilateral.twin"


def main() -> None:
    ap = argparse.ArgumentParser(description=(__doc__ or "").split("\n")[0])
    ap.add_argument("--out", type=Path, default=Path("preview.png"))
    ap.add_argument("--quick", action="store_true", help="open3d only")
    args = ap.parse_args()
    twin = Twin.load(SAMPLE)
    mesh = twin.load_mesh()
    pose = twin.poses[0]
    depths = {}
    for name in BACKENDS[:1] if args.quick else BACKENDS:
        try:
            backend = get_backend(name, mesh.vertices, mesh.faces, twin.camera)
        except BackendUnavailable as exc:
            print(f"{name}: skipped ({exc.reason})")
            continue
        depths[name] = backend.render(pose.T_vine_camera)
        if name == "open3d":
            # the pose's reference, as every part of vinetwin gets it (here rendered now, with
            # this backend, rather than read from the twin's exported files)
            ref = reference_for(twin, pose.id, use_exported=False, renderer=backend)
            print(
                f"reference of {pose.id}: {len(ref.cloud)} points, depth {ref.cloud.points[:, 2].min():.3f}-{ref.cloud.points[:, 2].max():.3f} m"
            )
            save_preview(ref, args.out, f"{twin.name} / {pose.id}")
            print(f"preview -> {args.out}")
        backend.close()
    base = depths["open3d"]
    for name, d in depths.items():
        both = (d > 0) & (base > 0)
        print(
            f"{name:9}: {int((d > 0).sum())} valid pixels, max |depth - open3d| = {1000 * np.abs(d[both] - base[both]).max():.3f} mm"
        )


if __name__ == "__main__":
    main()
