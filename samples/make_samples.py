"""Regenerates the bundled sample twins from the procedural generator.

Run: `.venv/bin/python samples/make_samples.py`. The samples use a 4 mm triangle edge so that both
fit in a few MB; `vinetwin sample` defaults to 2 mm (about 300k triangles) for real work.
"""

from __future__ import annotations

from pathlib import Path

from vinetwin.twin.generator import VineParams, generate_vine
from vinetwin.twin.model import twin_from_skeleton

HERE = Path(__file__).resolve().parent
SAMPLES = {
    "vine_bilateral.twin": dict(seed=3, cordons=2, cut_points=5),
    "vine_unilateral.twin": dict(seed=11, cordons=1, cut_points=4),
}


def main() -> None:
    for name, cfg in SAMPLES.items():
        sk = generate_vine(int(cfg["seed"]), VineParams(cordons=int(cfg["cordons"])))
        twin = twin_from_skeleton(
            HERE / name,
            sk,
            edge=0.004,
            source={
                "generator": "vinetwin.twin.generator",
                "seed": cfg["seed"],
                "cordons": cfg["cordons"],
            },
            cut_points=int(cfg["cut_points"]),
            overwrite=True,
        )
        twin.provenance["created"] = "sample"  # stable file across regenerations
        twin.save()
        print(f"{name}: {len(twin.poses)} poses")


if __name__ == "__main__":
    main()
