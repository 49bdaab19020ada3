"""`vinetwin check-reference`: on the day, is a twin still valid at a pruning pose?

With the camera at the pruning pose (the robot sent there), a few live frames are aligned to the
pose's reference by the pose's own ICP variant (the one its servo uses) from the identity, the guess a twin that is still right
makes exact. The answer, per frame and as medians:

- the *correction*: where ICP moved the live view to fit the reference (mm, rad). A vine (or a
  robot registration) that moved since the twin was made shows here;
- the *residual* (inlier RMSE), the *overlap* (pairs over the smaller cloud) and the *coverage*
  (share of the reference the live view covers): a vine that changed (grown, pruned, leaves,
  a broken cane) shows here;

and a verdict: "twin still valid", "vine moved" (correction beyond `max_translation` /
`max_rotation`) or "vine changed here" (coverage under `min_coverage`, residual over
`max_rmse`, or no alignment at all), with a picture: the reference and the aligned live points
projected into the image, the live points coloured by their distance to the reference.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, cast

import numpy as np

from vinetwin.cloud import Cloud, perceive
from vinetwin.files import save_figure
from vinetwin.frames import Array, pose_error, transform_points
from vinetwin.registration.icp import ICP, ICPConfig
from vinetwin.servo.config import CheckConfig, Variant
from vinetwin.twin.model import Twin


@dataclass
class ReferenceCheck:
    """The outcome of `check_reference`."""

    pose: str
    verdict: str
    """"twin still valid", "vine moved" or "vine changed here"."""
    reason: str
    variant: str = ""
    """The ICP variant that aligned the frames."""
    correction_mm: float = float("nan")
    correction_rad: float = float("nan")
    residual_mm: float = float("nan")
    overlap: float = 0.0
    coverage: float = 0.0
    frames: list[dict[str, Any]] = field(default_factory=list)

    @property
    def valid(self) -> bool:
        return self.verdict == "twin still valid"

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)

    def describe(self) -> str:
        return (
            f"{self.pose}: {self.verdict.upper()}: {self.reason}\n"
            f"correction {self.correction_mm:.2f} mm, {self.correction_rad:.4f} rad; residual "
            f"{self.residual_mm:.2f} mm; overlap {self.overlap:.2f}; the live view covers "
            f"{100 * self.coverage:.0f}% of the reference ({len(self.frames)} frames, "
            f"{self.variant or 'ICP'})"
        )


def check_reference(
    twin: Twin, pose_id: str, depths: list[Any], reference: Cloud, config: CheckConfig
) -> tuple[ReferenceCheck, list[tuple[Cloud, Array]]]:
    """Aligns each live depth image (metres, taken at the pose) to the pose's reference; returns
    the check and, per frame, the live cloud with its alignment (for the picture)."""
    cfg = config
    variant = cfg.variant or twin.pose(pose_id).icp_variant
    icp = ICP(
        reference, ICPConfig(variant=cast(Variant, variant)), camera=twin.camera,
        max_depth=twin.perception.max_depth,
    )  # fmt: skip
    rows, aligned = [], []
    for depth in depths:
        cloud = perceive(depth, twin.camera, twin.perception)
        if cloud.empty:
            rows.append({"ok": False, "reason": "no points survived perception"})
            continue
        r = icp.align(cloud, np.eye(4))
        dt, dr = pose_error(r.T_ref_cur, np.eye(4))
        rows.append(
            {
                "ok": bool(r.converged), "reason": r.reason, "correction_mm": 1000 * dt,
                "correction_rad": dr, "residual_mm": 1000 * r.inlier_rmse,
                "overlap": r.overlap, "coverage": r.coverage,
            }
        )  # fmt: skip
        if r.converged:
            aligned.append((cloud, r.T_ref_cur))
    good = [x for x in rows if x["ok"]]
    out = ReferenceCheck(pose_id, "vine changed here", "", variant, frames=rows)
    if not good:
        why = "; ".join(sorted({str(x["reason"]) for x in rows})) or "no frames"
        out.reason = f"no frame aligned with the reference ({why})"
        return out, aligned

    def med(key: str) -> float:
        return float(np.median([x[key] for x in good]))

    out.correction_mm, out.correction_rad = med("correction_mm"), med("correction_rad")
    out.residual_mm, out.overlap, out.coverage = med("residual_mm"), med("overlap"), med("coverage")
    if out.coverage < cfg.min_coverage:
        out.reason = (
            f"the live view covers {100 * out.coverage:.0f}% of the reference (minimum "
            f"{100 * cfg.min_coverage:.0f}%): parts of the vine the twin holds are not there"
        )
    elif out.residual_mm > 1000 * cfg.max_rmse:
        out.reason = (
            f"residual {out.residual_mm:.2f} mm after alignment (limit {1000 * cfg.max_rmse:.2f} "
            "mm): the shape differs from the twin's"
        )
    elif out.correction_mm > 1000 * cfg.max_translation or out.correction_rad > cfg.max_rotation:
        out.verdict = "vine moved"
        out.reason = (
            f"the live view fits the reference {out.correction_mm:.1f} mm / "
            f"{out.correction_rad:.3f} rad away from the pose (limits "
            f"{1000 * cfg.max_translation:.1f} mm / {cfg.max_rotation} rad): the vine, or where "
            "the robot believes it is, moved since the twin was made"
        )
    else:
        out.verdict = "twin still valid"
        out.reason = (
            f"within {1000 * cfg.max_translation:.1f} mm / {cfg.max_rotation} rad, residual "
            f"under {1000 * cfg.max_rmse:.1f} mm, {100 * out.coverage:.0f}% of the reference covered"
        )
    return out, aligned


def plot_check(
    check: ReferenceCheck, twin: Twin, reference: Cloud, aligned: list[tuple[Cloud, Array]],
    path: Path,
) -> Path:  # fmt: skip
    """The reference (grey) and the last aligned live frame (coloured by its distance to the
    reference, mm) projected into the camera image, with the verdict as the title."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from scipy.spatial import KDTree

    cam = twin.camera

    def uv(p: Array) -> tuple[Array, Array]:
        z = np.maximum(p[:, 2], 1e-6)
        return cam.fx * p[:, 0] / z + cam.cx, cam.fy * p[:, 1] / z + cam.cy

    fig, ax = plt.subplots(figsize=(8.48, 4.8 + 0.4))
    u, v = uv(reference.points)
    ax.scatter(u, v, s=3, c="0.7", label="reference")
    if aligned:
        cloud, T = aligned[-1]
        u, v = uv(cloud.points)  # where the live view was before the alignment
        ax.scatter(u, v, s=2, c="tab:red", alpha=0.35, label="live, as taken")
        live = transform_points(T, cloud.points)
        d = KDTree(reference.points).query(live)[0] * 1000
        u, v = uv(live)
        sc = ax.scatter(u, v, s=3, c=np.minimum(d, 5.0), cmap="viridis", vmin=0, vmax=5,
                        label="live, aligned")  # fmt: skip
        fig.colorbar(sc, ax=ax, label="distance to the reference (mm)")
    ax.set_xlim(0, cam.width)
    ax.set_ylim(cam.height, 0)
    ax.set_aspect("equal")
    ax.legend(loc="lower right", fontsize=8)
    ax.set_title(f"{check.pose}: {check.verdict} ({check.correction_mm:.1f} mm, "
                 f"{check.correction_rad:.3f} rad)", fontsize=10)  # fmt: skip
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    save_figure(fig, path, 100)
    plt.close(fig)
    return path


def live_depths(twin: Twin, pose_id: str, config: CheckConfig) -> list[Any]:
    """`config.frames` depth images (metres) from the camera: `sim` renders the twin's mesh at
    the pose through the D405 model (with the vine moved by `sim_offset`, to try the check);
    otherwise a camera source (`capture.sources.open_source`: realsense, bag:FILE,
    folder:DIR), whose first frames are taken as they come."""
    cfg = config
    if cfg.camera == "sim":
        from vinetwin.frames import invert, make_pose
        from vinetwin.render.backends import raycaster
        from vinetwin.render.sensor import apply_d405_model

        mesh = twin.load_mesh()
        backend = raycaster(mesh.vertices, mesh.faces, twin.camera)
        T = invert(make_pose(t=cfg.sim_offset)) @ np.asarray(twin.pose(pose_id).T_vine_camera)
        rng = np.random.default_rng(cfg.seed)
        out = [apply_d405_model(backend.render(T), twin.camera, rng) for _ in range(cfg.frames)]
        backend.close()
        return out
    from vinetwin.capture.sources import open_source

    out = []
    with open_source(cfg.camera, camera=twin.camera) as src:
        while len(out) < cfg.frames:
            f = src.read(timeout=2.0)
            if f is None:
                if src.ended:
                    break
                continue
            out.append(f.depth)
    return out


def run_check(
    twin_dir: Path, config: CheckConfig, out: Path | None = None, overwrite: bool = False
) -> ReferenceCheck:
    """`vinetwin check-reference`: the frames, the check, `check.json` and `check.png` in `out`
    (default TWIN/checks/POSE, replaced at each check). A given `out` that is a file, or that
    holds an earlier check, is refused before anything runs, unless `overwrite`."""
    import json

    from vinetwin.files import atomic_write_text, refuse_existing_outputs
    from vinetwin.render.reference import reference_for

    if out is not None:
        refuse_existing_outputs(out, ("check.json", "check.png"), "--out", overwrite)
    twin = Twin.load(twin_dir)
    pose = twin.pose(config.pose) if config.pose else twin.poses[0]
    reference = reference_for(twin, pose.id).cloud
    check, aligned = check_reference(
        twin, pose.id, live_depths(twin, pose.id, config), reference, config
    )
    out = out or twin.root / "checks" / pose.id
    out.mkdir(parents=True, exist_ok=True)
    data = {"config": config.to_dict(), **check.to_dict()}
    atomic_write_text(out / "check.json", json.dumps(data, indent=1))
    plot_check(check, twin, reference, aligned, out / "check.png")
    return check
