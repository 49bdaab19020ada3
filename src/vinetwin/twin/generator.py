"""A seeded procedural generator of dormant grapevines (cordon-trained, spur-pruned).

Vine frame: origin at the foot of the trunk, +Z up, +X along the row (the cordon wire), +Y across
the row; the robot stands on the -Y side by default. What it grows, with the ranges used:

- a trunk 20-40 mm thick, 0.55-0.85 m high, leaning and wobbling a little, flared at the foot;
- one or two cordons (unilateral or bilateral) that bend onto a wire at trunk height and run
  0.35-0.7 m along it, 18-30 mm thick, tapering;
- spurs (two-year wood) every 12-20 cm on the cordon, 2-5 cm long, 12-18 mm thick;
- one or two dormant canes per spur, 6-12 mm at the base, 0.25-0.8 m long, rising with bends and
  irregularity, with a node (swelling with a bud) every 5-9 cm;
- cut-point candidates where a pruner shortens a cane to a two-bud spur: 30% of the way from the
  second node to the third.

Same seed, same vine (bit for bit): all randomness comes from one `numpy.random.Generator`.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Literal

import numpy as np

from vinetwin.errors import InputError
from vinetwin.frames import Array
from vinetwin.twin.skeleton import Branch, CutCandidate, Skeleton, arc_length

if TYPE_CHECKING:
    from vinetwin.twin.model import Twin


@dataclass(frozen=True, kw_only=True)
class VineParams:
    """Knobs of the generator; defaults give a typical double-cordon vine."""

    cordons: int = 2
    """Number of cordon arms: 1 (unilateral) or 2 (bilateral)."""
    trunk_height: tuple[float, float] = (0.55, 0.85)
    """Range of the wire height, metres."""
    trunk_diameter: tuple[float, float] = (0.020, 0.040)
    """Range of the trunk diameter, metres."""
    cordon_length: tuple[float, float] = (0.35, 0.70)
    """Range of each cordon's length along the wire, metres."""
    spur_spacing: tuple[float, float] = (0.12, 0.20)
    """Range of the spacing of spurs along a cordon, metres."""
    canes_per_spur: tuple[int, int] = (1, 2)
    """Range (inclusive) of canes on one spur."""
    cane_diameter: tuple[float, float] = (0.006, 0.012)
    """Range of cane base diameters, metres."""
    cane_length: tuple[float, float] = (0.25, 0.80)
    """Range of cane lengths, metres."""
    internode: tuple[float, float] = (0.05, 0.09)
    """Range of internode lengths on canes, metres."""
    step: float = 0.004
    """Centre-line sampling step, metres."""


def _wander(
    rng: np.random.Generator,
    start: Array,
    direction: Array,
    length: float,
    step: float,
    target: Callable[[Array], Array],
    pull: float,
    wobble: float,
) -> Array:
    """A centre line from `start`, first heading along `direction`.

    The heading relaxes towards `target(position)` at rate `pull` (1/m) and is shaken by white
    noise of strength `wobble` (rad/sqrt(m)), an Ornstein-Uhlenbeck walk on the sphere: its
    typical angle from the target is wobble / sqrt(2 * pull).
    """
    n = max(2, math.ceil(length / step) + 1)
    d = np.asarray(direction, dtype=np.float64)
    d = d / np.linalg.norm(d)
    pts = np.empty((n, 3))
    pts[0] = start
    noise = rng.normal(size=(n, 3)) * wobble * math.sqrt(step)
    for i in range(n - 1):
        goal = target(pts[i])
        kick = pull * step * (goal - (goal @ d) * d) + (noise[i] - (noise[i] @ d) * d)
        d = d + kick
        d /= np.linalg.norm(d)
        pts[i + 1] = pts[i] + step * d
    return pts


def _unit(v: Array) -> Array:
    return v / np.linalg.norm(v)


def _cane(
    rng: np.random.Generator,
    p: VineParams,
    start: Array,
    direction: Array,
    index: int,
) -> tuple[Branch, list[tuple[float, Array, Array]]]:
    """One cane with nodes; returns the branch and (arc position, point, tangent) of its nodes."""
    length = rng.uniform(*p.cane_length)
    goal = _unit(np.asarray(direction, dtype=np.float64) * [0.6, 0.6, 1.0])
    pts = _wander(rng, start, direction, length, p.step, lambda _: goal, pull=4.0, wobble=0.9)
    s = arc_length(pts)
    d0 = rng.uniform(*p.cane_diameter)
    r = 0.5 * d0 * (1.0 - 0.45 * s / s[-1])
    # nodes: swellings with a bud, every internode
    nodes = []
    pos = rng.uniform(0.01, 0.025)
    while pos < s[-1] - 0.02:
        nodes.append(pos)
        pos += rng.uniform(*p.internode)
    for z in nodes:
        r = r * (1.0 + 0.28 * np.exp(-0.5 * ((s - z) / 0.0035) ** 2))
    # irregularity of the cross-section along the cane
    r = r * (1.0 + 0.04 * np.convolve(rng.normal(size=len(s)), np.ones(9) / 3, mode="same"))
    r = np.maximum(r, 0.0015)
    tangents = np.gradient(pts, axis=0)
    tangents /= np.linalg.norm(tangents, axis=1, keepdims=True)
    node_info = []
    for z in nodes:
        i = int(np.searchsorted(s, z))
        i = min(i, len(s) - 1)
        node_info.append((z, pts[i], tangents[i]))
    branch = Branch(pts, r, kind="cane", label=f"cane{index}", nodes=np.array(nodes))
    return branch, node_info


def generate_vine(seed: int = 0, params: VineParams | None = None) -> Skeleton:
    """Grows a dormant grapevine skeleton; deterministic for a given seed and params."""
    p = params or VineParams()
    rng = np.random.default_rng(seed)
    sk = Skeleton()

    # trunk: near vertical, a slight lean
    height = rng.uniform(*p.trunk_height)
    d_trunk = rng.uniform(*p.trunk_diameter)
    lean = _unit(np.array([rng.normal(0, 0.05), rng.normal(0, 0.05), 1.0]))
    trunk = _wander(rng, np.zeros(3), lean, height, p.step, lambda _: lean, pull=10.0, wobble=0.4)
    s = arc_length(trunk)
    r = 0.5 * d_trunk * (1.0 - 0.15 * s / s[-1]) * (1.0 + 0.35 * np.exp(-s / 0.05))
    r = r * (1.0 + 0.05 * np.sin(s * rng.uniform(20, 40) + rng.uniform(0, 6)))
    sk.branches.append(Branch(trunk, r, kind="trunk", label="trunk"))
    top = trunk[-1]
    wire = np.array([0.0, top[1], top[2] + 0.03])  # the cordon wire runs along X

    n_cane = 0
    sides = [1.0, -1.0][: max(1, min(2, p.cordons))]
    for side in sides:
        length = rng.uniform(*p.cordon_length)

        def along_wire(pos: Array, side: float = side) -> Array:
            # head along the row, steered back onto the wire
            return _unit(np.array([side, 8.0 * (wire[1] - pos[1]), 8.0 * (wire[2] - pos[2])]))

        start_dir = trunk[-1] - trunk[-4]
        cordon = _wander(rng, top, start_dir, length + 0.05, p.step, along_wire, 30.0, 0.4)
        cs = arc_length(cordon)
        d_cordon = min(rng.uniform(0.018, 0.030), d_trunk)
        cr = 0.5 * d_cordon * (1.0 - 0.35 * cs / cs[-1])
        cordon_index = len(sk.branches)
        sk.branches.append(Branch(cordon, cr, kind="cordon", parent=0, label=f"cordon{side:+.0f}"))

        pos = rng.uniform(0.08, 0.14)
        while pos < cs[-1] - 0.03:
            i = int(np.searchsorted(cs, pos))
            base = cordon[i]
            # spur: a short stub rising from the top of the cordon
            tilt = _unit(np.array([rng.normal(0, 0.35), rng.normal(0, 0.35), 1.0]))
            spur_len = rng.uniform(0.02, 0.05)
            spur_start = base + np.array([0, 0, 0.5 * cr[i]])
            spur = _wander(rng, spur_start, tilt, spur_len, p.step, lambda _, t=tilt: t, 5.0, 1.0)
            rs = np.full(len(spur), 0.5 * rng.uniform(0.012, 0.018))
            spur_index = len(sk.branches)
            sk.branches.append(
                Branch(spur, rs, kind="spur", parent=cordon_index, label=f"spur{spur_index}")
            )
            for _ in range(int(rng.integers(p.canes_per_spur[0], p.canes_per_spur[1] + 1))):
                direction = np.array([rng.normal(0, 0.45), rng.normal(0, 0.3), 1.0])
                cane, nodes = _cane(rng, p, spur[-1], direction, n_cane)
                cane.parent = spur_index
                cane_index = len(sk.branches)
                sk.branches.append(cane)
                if len(nodes) >= 3:
                    s2, s3 = nodes[1][0], nodes[2][0]
                    cs_ = arc_length(cane.points)
                    k = int(np.searchsorted(cs_, s2 + 0.3 * (s3 - s2)))
                    k = min(max(k, 1), len(cs_) - 2)
                    axis = cane.points[k + 1] - cane.points[k - 1]
                    axis /= np.linalg.norm(axis)
                    sk.candidates.append(
                        CutCandidate(
                            point=cane.points[k].copy(),
                            cane_axis=axis,
                            branch=cane_index,
                            radius=float(cane.radii[k]),
                            label=f"cane{n_cane}/node2",
                        )
                    )
                n_cane += 1
            pos += rng.uniform(*p.spur_spacing)
    return sk


@dataclass(frozen=True, kw_only=True)
class SampleConfig:
    """The vine `vinetwin sample` grows."""

    seed: int = 0
    """Random seed: the same seed gives the same vine."""
    cordons: Literal[1, 2] = 2
    """One cordon arm (unilateral) or two (bilateral)."""
    edge: float = 0.002
    """Target triangle edge length of the tube mesh, metres (smaller: denser mesh)."""
    cut_points: int = 4
    """How many cut-point candidates become cut points with a default pruning pose."""
    dense: bool = False
    """Grow a dense vine (spurs twice as close, 2-4 canes each: the paper's Table 2 vines)."""


#: A dense vine (the paper's Table 2 vines): spurs twice as close, two to four canes each.
DENSE = {"spur_spacing": (0.06, 0.10), "canes_per_spur": (2, 4), "cane_length": (0.35, 0.90)}


def sample_twin(
    out: str | Path,
    seed: int = 0,
    *,
    cordons: int = 2,
    edge: float = 0.002,
    cut_points: int = 4,
    overwrite: bool = False,
    dense: bool = False,
) -> Twin:
    """`vinetwin sample`: a procedural vine (`generate_vine`) written as a twin folder, its first
    `cut_points` candidates made cut points with default pruning poses; `dense`: the `DENSE`
    growth (many canes crossing, as on the paper's Table 2 vines)."""
    from vinetwin.twin.model import twin_from_skeleton

    if not 0 <= seed < 2**32:
        raise InputError(f"seed must lie in [0, 2^32), got {seed}")
    sk = generate_vine(seed, VineParams(cordons=cordons, **(DENSE if dense else {})))  # type: ignore[arg-type]
    source = {"generator": "vinetwin.twin.generator", "seed": seed, "cordons": cordons,
              **({"dense": True} if dense else {})}  # fmt: skip
    return twin_from_skeleton(
        out, sk, edge=edge, source=source, cut_points=cut_points, overwrite=overwrite
    )
