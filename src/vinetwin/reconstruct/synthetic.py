"""Synthetic captures: a sweep of D405 frames around a twin's mesh with ground-truth poses.

The camera moves on a grid of viewpoints in front of the vine (the robot's side, -Y), at a
working distance suited to the D405, each looking at a point of the vine; depth comes from the
render module through the D405 sensor model, colour from a procedural bark texture (a function of
the 3D surface point, so the same spot looks the same in every frame: features can be matched)
over a plain background. Optional pose noise perturbs the recorded `T_base_camera` (as imperfect
robot kinematics would), not the rendered view.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from vinetwin.capture.folder import write_capture
from vinetwin.frames import Array, look_at, make_pose, so3_exp, transform_points
from vinetwin.render.backends import raycaster
from vinetwin.render.sensor import SensorConfig, apply_d405_model
from vinetwin.twin.model import Twin
from vinetwin.twin.poses import HALF_TURN, from_far_side


def bark_colour(points: Array) -> np.ndarray:
    """A deterministic bark-like texture: brown tones modulated by a few 3D sinusoids."""
    p = np.asarray(points, dtype=np.float64)
    f = (
        np.sin(p @ np.array([310.0, 170.0, 90.0]))
        + 0.7 * np.sin(p @ np.array([-120.0, 410.0, 230.0]) + 1.3)
        + 0.5 * np.sin(p @ np.array([60.0, -250.0, 520.0]) + 0.4)
        + 0.35 * np.sin(p @ np.array([900.0, 700.0, -800.0]))
    )
    t = (f - f.min()) / max(float(np.ptp(f)), 1e-9) if len(f) else f
    base = np.array([95.0, 65.0, 40.0])
    light = np.array([200.0, 160.0, 115.0])
    return (base + t[:, None] * (light - base)).astype(np.uint8)


def sweep_poses(twin: Twin, frames: int, distance: float = 0.3) -> list[Array]:
    """Camera poses (vine frame) on a grid in front of the vine, each looking at the vine: from
    the robot's side (-Y), and from the far aisle too, half the frames, when some of the twin's
    pruning poses look at the row from there (`twin.poses.from_far_side`: a far curtain pruned
    in `prune`'s far pass); from there alone when all do."""
    V = np.asarray(twin.load_mesh().vertices)
    lo, hi = np.percentile(V, 2, axis=0), np.percentile(V, 98, axis=0)
    sides = sweep_sides(twin)
    # the far aisle's grid: the near one turned half a turn about the plant's vertical centre line
    c = 0.5 * (lo + hi)
    turn = make_pose(HALF_TURN[:3, :3], [2 * c[0], 2 * c[1], 0.0])
    poses = []
    for k, side in enumerate(sides):
        n = frames // len(sides) + (1 if k < frames % len(sides) else 0)
        grid = _grid(lo, hi, n, distance)
        poses += [turn @ T for T in grid] if side else grid
    return poses


def sweep_sides(twin: Twin) -> list[bool]:
    """The aisles a grid sweep of the twin covers (False: the robot's, True: the far one): see
    `sweep_poses`."""
    far = [from_far_side(p.T_vine_camera) for p in twin.poses]
    return ([False] if not (far and all(far)) else []) + ([True] if any(far) else [])


def _grid(lo: Array, hi: Array, frames: int, distance: float) -> list[Array]:
    """`frames` viewpoints on a grid over the plant's extent (`lo`, `hi`) on the robot's side."""
    # the part with the canes: upper half of the vine's height
    zc = lo[2] + 0.6 * (hi[2] - lo[2])
    cols = max(2, round(float(np.sqrt(frames * 2))))
    rows = max(1, int(np.ceil(frames / cols)))
    poses: list[Array] = []
    for r in range(rows):
        for c in range(cols):
            if len(poses) == frames:
                break
            x = lo[0] + (hi[0] - lo[0]) * (c + 0.5) / cols
            z = zc + (hi[2] - zc) * ((r + 0.5) / rows - 0.5)
            target = np.array([x, 0.5 * (lo[1] + hi[1]), z])
            poses.append(_view(target, r * cols + c, distance))
    return poses


def _view(target: Array, k: int, distance: float) -> Array:
    """The k-th viewpoint of a grid sweep, `distance` from `target` on the robot's side (-Y),
    the viewing direction alternated a little so canes are seen from several sides."""
    yaw, pitch = 0.35 * np.sin(1.7 * k), 0.25 * np.cos(1.3 * k)
    d = np.array([np.sin(yaw), -np.cos(yaw) * np.cos(pitch), np.sin(pitch)])
    return look_at(target + distance * d, target)


def around_poses(twin: Twin, frames: int, distance: float = 0.3) -> list[Array]:
    """Viewpoints around the twin's pruning poses, shared among them: each looks at its pose's
    cut point from `distance`, from directions within 0.6 rad of the pose's own view (what a
    robot capturing the vine where it will prune would record; for large vines, where a sweep of
    the whole plant at the D405's range cannot fit)."""
    poses = []
    if not twin.poses:
        raise ValueError("the 'poses' trajectory needs a twin with pruning poses")
    for k in range(frames):
        pose = twin.poses[k % len(twin.poses)]
        cut = twin.cut_point(pose.cut_point).point
        T = np.asarray(pose.T_vine_camera)
        j = k // len(twin.poses)
        yaw, pitch = 0.6 * np.sin(2.4 * j + 0.3), 0.4 * np.cos(1.7 * j)
        view = T[:3, :3] @ np.array([np.sin(yaw), np.sin(pitch), np.cos(yaw) * np.cos(pitch)])
        up = -T[:3, 1]  # keep the pose's image "up"
        poses.append(look_at(cut - distance * view / np.linalg.norm(view), cut, up))
    return poses


def path_poses(twin: Twin, frames: int, distance: float = 0.3) -> list[Array]:
    """A video-like path: the camera sweeps along the vine and back at two heights, a small step
    between frames (what a hand-held or arm-held camera records at video rate)."""
    V = np.asarray(twin.load_mesh().vertices)
    lo, hi = np.percentile(V, 2, axis=0), np.percentile(V, 98, axis=0)
    zc = lo[2] + 0.6 * (hi[2] - lo[2])
    s = np.linspace(0.0, 1.0, frames)
    # out along the vine at the lower height, back at the upper one
    x = np.where(s < 0.5, lo[0] + (hi[0] - lo[0]) * 2 * s, hi[0] - (hi[0] - lo[0]) * (2 * s - 1))
    rise = np.clip((s - 0.45) / 0.1, 0.0, 1.0)  # climb between the two passes, no jump
    z = zc - 0.05 + 0.15 * rise * rise * (3 - 2 * rise)
    poses = []
    for k in range(frames):
        target = np.array([x[k], 0.5 * (lo[1] + hi[1]), z[k]])
        yaw = 0.25 * np.sin(6 * np.pi * s[k])
        d = np.array([np.sin(yaw), -np.cos(yaw), 0.15])
        poses.append(look_at(target + distance * d / np.linalg.norm(d), target))
    return poses


def synthetic_capture(
    twin: Twin,
    out: str | Path,
    frames: int = 120,
    distance: float = 0.3,
    seed: int = 0,
    pose_noise: tuple[float, float] = (0.0, 0.0),
    progress: Callable[[Any, int, int], None] | None = None,
    trajectory: str = "grid",
) -> Path:
    """Renders the sweep into a capture folder; returns its path. `pose_noise` (m, rad) is the
    standard deviation of the error added to the recorded poses. `trajectory`: "grid" (viewpoints
    spread over the vine, for fusion and structure-from-motion), "path" (a continuous sweep with
    small steps, as a video, for frame-to-frame odometry) or "poses" (around the twin's pruning
    poses: for vines too large to sweep whole at the D405's range)."""
    mesh = twin.load_mesh()
    cam = twin.camera
    backend = raycaster(mesh.vertices, mesh.faces, cam)
    rng = np.random.default_rng(seed)
    rows = []
    makers = {"grid": sweep_poses, "path": path_poses, "poses": around_poses}
    if trajectory not in makers:
        raise ValueError(f"unknown trajectory '{trajectory}'; choose grid, path or poses")
    poses = makers[trajectory](twin, frames, distance)
    for i, T in enumerate(poses):
        clean = backend.render(T)
        depth = apply_d405_model(clean, cam, rng, SensorConfig())
        colour = np.empty((cam.height, cam.width, 3), np.uint8)
        colour[:] = (200, 215, 230)  # sky-like background
        valid = np.isfinite(clean) & (clean > 0)
        if valid.any():
            v, u = np.nonzero(valid)
            pts_c = cam.deproject_pixels(np.column_stack([u, v]).astype(float), clean[valid])
            colour[v, u] = bark_colour(transform_points(T, pts_c))
        T_rec = T
        if pose_noise[0] > 0 or pose_noise[1] > 0:
            T_rec = T @ make_pose(
                so3_exp(rng.normal(0, pose_noise[1], 3)), rng.normal(0, pose_noise[0], 3)
            )
        rows.append((colour, depth, T_rec))
        if progress:
            progress(None, i + 1, len(poses))
    backend.close()
    extra = {"provenance": {"generator": "vinetwin.reconstruct.synthetic", "twin": twin.name,
                            "seed": seed, "distance": distance, "pose_noise": list(pose_noise)}}  # fmt: skip
    return write_capture(out, cam, rows, extra=extra)


def d405_scan(
    V: Array,
    F: np.ndarray,
    frames: int = 120,
    seed: int = 0,
    *,
    pose_noise: tuple[float, float] = (0.001, 0.002),
    distance: float = 0.3,
    voxel: float = 0.002,
) -> Array:
    """Points (vine frame, metres) of the mesh (V, F) seen by a simulated D405 from `frames`
    viewpoints on each side of the row (the vine frame's -Y and +Y), fused with per-frame pose
    errors (`pose_noise`: m and rad, standard deviations per axis) and thinned to one point per
    `voxel`: a D405 rig's frames fused into one cloud by another tool, as a group holding a
    robot or a handheld RGB-D camera would have it (a scan for `vinetwin import-scan`: its
    benchmark's `--qualities d405`). A grid of viewpoints over the whole plant, `distance` from
    it, from both sides of the row, each frame through the D405 depth model (depth noise
    growing with the square of the depth, edge and speckle dropouts), back-projected with its
    recorded pose (an error per frame: the capture's odometry or robot kinematics, so the
    frames disagree by a few millimetres)."""
    from vinetwin.camera import d405
    from vinetwin.cloud import voxel_downsample

    cam = d405()
    rng = np.random.default_rng(seed)
    mirror = np.diag([1.0, -1.0, 1.0, 1.0])  # the other side of the row: y -> -y
    sides = [(V, F, np.eye(4)), (V @ mirror[:3, :3], F[:, ::-1], mirror)]
    parts = []
    for Vs, Fs, M in sides:
        backend = raycaster(Vs, Fs, cam)
        try:
            for T in _grid_views(Vs, frames, distance):
                depth = apply_d405_model(backend.render(T), cam, rng, SensorConfig())
                pts, _ = cam.deproject(depth)
                if not len(pts):
                    continue
                dT = make_pose(so3_exp(rng.normal(0, pose_noise[1], 3)),
                               rng.normal(0, pose_noise[0], 3))  # fmt: skip
                parts.append(transform_points(M @ T @ dT, pts))
        finally:
            backend.close()
    if not parts:
        return np.zeros((0, 3))
    return voxel_downsample(np.concatenate(parts), voxel)[0]


def _grid_views(V: Array, frames: int, distance: float) -> list[Array]:
    """`frames` camera poses on a grid over the whole plant's front (the vine frame's -Y side),
    `distance` from the plane through its middle, rows and columns in proportion to its width and
    height, each looking at the plant as `sweep_poses`' views do (`_view`)."""
    lo, hi = np.percentile(V, 1, axis=0), np.percentile(V, 99, axis=0)
    w, h = max(hi[0] - lo[0], 1e-3), max(hi[2] - lo[2], 1e-3)
    cols = max(1, round(float(np.sqrt(frames * w / h))))
    rows = max(1, int(np.ceil(frames / cols)))
    y = 0.5 * (lo[1] + hi[1])
    poses = []
    for k in range(rows * cols):
        if len(poses) == frames:
            break
        r, c = divmod(k, cols)
        target = np.array([lo[0] + w * (c + 0.5) / cols, y, lo[2] + h * (r + 0.5) / rows])
        poses.append(_view(target, k, distance))
    return poses
