"""A simulated scanner, so that a scan's skeleton and twin can be checked against a known truth.

LiDAR-like (a terrestrial or handheld scanner): from `positions` stations around the plant, rays
on a spherical grid whose step gives `spacing` at the plant, cast into the true mesh (Open3D ray
casting); the errors real scans have, each a setting of `ScanQuality`:

- range noise along each ray (`noise`, Gaussian sigma);
- each station's points moved by its own small rigid error (`misregistration`: its translation,
  and a rotation of that size at 1 m), so that surfaces seen from two stations are doubled;
- gaps: `gaps` balls of diameter up to `gap` on the plant's surface are emptied (a cane hidden
  behind another, a dark spot), beside what occlusion hides anyway;
- stray points: `strays` of the points anywhere in the box around the plant, and mixed pixels
  (a point slid along its ray behind an edge);
- optionally the trellis: the ground under the plant, a wire along the row at the cordon's
  height, and two posts; all of it is what `CleanConfig` removes.

A D405 rig's fused frames instead: `reconstruct.synthetic.d405_scan`.

The scan is returned in a scanner's frame (a rotation and shift of the vine frame, y up as
photogrammetry tools write it, in the unit asked for), with `T_scan_vine`, so the import's
frame detection and unit detection are tested as well."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from vinetwin.frames import Array


@dataclass(frozen=True, kw_only=True)
class ScanQuality:
    """The errors of one simulated scan (metres)."""

    spacing: float = 0.004
    """Point spacing at the plant."""
    noise: float = 0.0015
    """Range noise (sigma)."""
    gap: float = 0.02
    """Largest diameter of an emptied gap."""
    gaps: int = 12
    """Gaps emptied."""
    misregistration: float = 0.002
    """Each station's translation error (and rotation error at 1 m)."""
    strays: float = 0.005
    """Share of stray points (half uniform in the box, half mixed pixels)."""
    positions: int = 4
    """Stations around the plant."""
    trellis: bool = False
    """Add the ground, a wire along the row at the cordon's height and two posts."""

    def label(self) -> str:
        return (f"{self.spacing * 1000:g} mm, noise {self.noise * 1000:g} mm, gaps {self.gap * 100:g} cm, "
                f"misreg {self.misregistration * 1000:g} mm")  # fmt: skip


#: The qualities the accuracy table reports, from a good scan to one where the skeleton breaks.
QUALITY_LADDER: dict[str, ScanQuality] = {
    "fine": ScanQuality(spacing=0.002, noise=0.001, gap=0.01, misregistration=0.001),
    "realistic": ScanQuality(spacing=0.004, noise=0.0015, gap=0.02, misregistration=0.002),
    "coarse": ScanQuality(spacing=0.006, noise=0.0025, gap=0.03, misregistration=0.003),
    "poor": ScanQuality(spacing=0.010, noise=0.004, gap=0.04, misregistration=0.005),
    "bad": ScanQuality(spacing=0.020, noise=0.006, gap=0.05, misregistration=0.008),
}


def _trellis(bounds: Array, wire_z: float) -> tuple[Array, np.ndarray]:
    """Vertices and faces of the ground (a square 0.6 m past the plant), a wire (radius 1.5 mm)
    along x at `wire_z` and two square posts (8 cm) at the wire's ends."""
    import trimesh

    lo, hi = bounds
    cx, cy = 0.5 * (lo[:2] + hi[:2])
    half = 0.5 * float(max(hi[0] - lo[0], hi[1] - lo[1])) + 0.6
    parts = [trimesh.creation.box((2 * half, 2 * half, 0.02),
                                  trimesh.transformations.translation_matrix([cx, cy, -0.011]))]  # fmt: skip
    x0, x1 = lo[0] - 0.5, hi[0] + 0.5
    wire = trimesh.creation.cylinder(0.0015, x1 - x0, sections=8)
    T = trimesh.transformations.rotation_matrix(math.pi / 2, [0, 1, 0])
    T[:3, 3] = [0.5 * (x0 + x1), cy, wire_z]
    wire.apply_transform(T)
    parts.append(wire)
    for x in (x0, x1):
        parts.append(trimesh.creation.box((0.08, 0.08, wire_z + 0.4),
                                          trimesh.transformations.translation_matrix(
                                              [x, cy, 0.5 * (wire_z + 0.4)])))  # fmt: skip
    m = trimesh.util.concatenate(parts)
    return np.asarray(m.vertices), np.asarray(m.faces)


def simulate_scan(
    V: Array,
    F: np.ndarray,
    quality: ScanQuality,
    seed: int = 0,
    *,
    wire_height: float | None = None,
) -> tuple[Array, Array]:
    """Points of a simulated scan of the mesh (V, F) in the vine frame (metres), and the label
    of each (0 plant, 1 trellis, 2 stray)."""
    from vinetwin import _lazy

    o3d = _lazy.open3d()

    rng = np.random.default_rng(seed)
    lo, hi = V.min(0), V.max(0)
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(V.astype(np.float32)), o3d.core.Tensor(F.astype(np.uint32)))
    plant_ids = 1
    if quality.trellis:
        TV, TF = _trellis(
            np.stack([lo, hi]), wire_height if wire_height is not None else hi[2] * 0.6
        )
        scene.add_triangles(
            o3d.core.Tensor(TV.astype(np.float32)), o3d.core.Tensor(TF.astype(np.uint32))
        )
    centre = 0.5 * (lo + hi)
    size = float(np.linalg.norm(hi - lo))
    R = max(1.5, 0.9 * size)
    pts_all, lab_all = [], []
    az0 = rng.uniform(0, 2 * math.pi)
    for k in range(quality.positions):
        az = az0 + 2 * math.pi * k / quality.positions
        origin = centre + np.array([R * math.cos(az), R * math.sin(az), 0.3 * (hi[2] - lo[2])])
        corners = np.array(
            [[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])]
        )
        d = corners - origin
        yaw = np.arctan2(d[:, 1], d[:, 0])
        yaw = np.unwrap(yaw - yaw[0]) + yaw[0]
        pitch = np.arctan2(d[:, 2], np.linalg.norm(d[:, :2], axis=1))
        step = quality.spacing / float(np.linalg.norm(centre - origin))
        ys = np.arange(yaw.min() - 0.05, yaw.max() + 0.05, step)
        ps = np.arange(pitch.min() - 0.05, pitch.max() + 0.05, step)
        Y, Pp = np.meshgrid(ys, ps, indexing="xy")
        dirs = np.stack([np.cos(Pp) * np.cos(Y), np.cos(Pp) * np.sin(Y), np.sin(Pp)], -1).reshape(
            -1, 3
        )
        rays = np.hstack([np.broadcast_to(origin, dirs.shape), dirs]).astype(np.float32)
        ans = scene.cast_rays(o3d.core.Tensor(rays))
        t = ans["t_hit"].numpy()
        gid = ans["geometry_ids"].numpy()
        hit = np.isfinite(t)
        t, dirs_h, gid = t[hit].astype(np.float64), dirs[hit], gid[hit]
        t = t + rng.normal(0, quality.noise, len(t))
        p = origin + t[:, None] * dirs_h
        lab = np.where(gid == 0, 0, plant_ids)
        # this station's registration error
        rot = Rotation.from_rotvec(rng.normal(size=3) * quality.misregistration / math.sqrt(3))
        shift = rng.normal(size=3) * quality.misregistration / math.sqrt(3)
        p = rot.apply(p - centre) + centre + shift
        # mixed pixels: half the strays slid along the ray
        nm = int(0.5 * quality.strays * len(p))
        if nm:
            i = rng.choice(len(p), nm, replace=False)
            p[i] += dirs_h[i] * rng.uniform(0.01, 0.3, nm)[:, None]
            lab[i] = 2
        pts_all.append(p)
        lab_all.append(lab)
    P = np.concatenate(pts_all)
    L = np.concatenate(lab_all)
    # gaps: balls emptied on the plant
    plant = np.flatnonzero(L == 0)
    if quality.gaps and len(plant):
        from scipy.spatial import cKDTree

        tree = cKDTree(P)
        drop = np.zeros(len(P), bool)
        for c in rng.choice(plant, min(quality.gaps, len(plant)), replace=False):
            r = 0.5 * quality.gap * rng.uniform(0.5, 1.0)
            drop[tree.query_ball_point(P[c], r)] = True
        P, L = P[~drop], L[~drop]
    nu = int(0.5 * quality.strays * len(P))
    if nu:
        box = rng.uniform(lo - 0.3, hi + 0.3, size=(nu, 3))
        P = np.vstack([P, box])
        L = np.concatenate([L, np.full(nu, 2)])
    perm = rng.permutation(len(P))
    return P[perm], L[perm]


def scanner_frame(seed: int = 0) -> Array:
    """T_scan_vine of a scanner: y up (as photogrammetry tools write), the row at a random
    heading, the origin a few metres away."""
    rng = np.random.default_rng(seed)
    heading = Rotation.from_euler("z", rng.uniform(0, 2 * math.pi))
    y_up = Rotation.from_euler("x", -90, degrees=True)  # vine +z becomes scan +y
    T = np.eye(4)
    T[:3, :3] = (y_up * heading).as_matrix()
    T[:3, 3] = rng.uniform(-5, 5, 3)
    return T
