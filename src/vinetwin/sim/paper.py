"""The seed paper's experiments as data (Gebrayel, Mujica, Danes, LAAS-CNRS; the figures are in
`data/paper/results.json` beside the project): the initial errors of its Tables 1 and 2 (the
campaign's presets), its names of the ICP variants, and its Table 1 results on the real robot,
which the campaign report prints beside the simulated ones."""

from __future__ import annotations

#: Initial errors (translation m, rotation rad) of the paper's Tables 1 and 2.
PRESETS: dict[str, tuple[tuple[float, float], ...]] = {
    "table1": (
        (0.184749, 0.351915),
        (0.166275, 0.567889),
        (0.034708, 0.550662),
        (0.316327, 0.12695),
    ),
    "table2": (
        (0.193, 0.35),
        (0.167, 0.566),
        (0.034, 0.55),
        (0.185, 0.22),
        (0.20, 0.168),
        (0.037, 0.47),
    ),
    "quick": ((0.05, 0.15),),
}
#: The paper's names of the variants (data/paper/results.json).
PAPER_NAMES = {
    "point_to_point": "ICP",
    "lm": "LM-ICP",
    "point_to_plane": "PP-ICP",
    "symmetric": "SYMM-ICP",
}
#: The paper's Table 1 (sparse vine, real robot): final static error (m, rad) and convergence
#: time (s) per test and variant; None: did not converge.
PAPER_TABLE1: tuple[dict[str, tuple[float, float, float] | None], ...] = (
    {"ICP": (0.003072, 0.002162, 24.89), "LM-ICP": (0.003333, 0.003612, 33.76), "PP-ICP": None, "SYMM-ICP": (0.002912, 0.004765, 14.27)},
    {"ICP": (0.002969, 0.022047, 18.31), "LM-ICP": (0.002691, 0.021488, 26.53), "PP-ICP": (0.002524, 0.022144, 17.73), "SYMM-ICP": (0.002115, 0.021275, 18.24)},
    {"ICP": (0.002027, 0.02138, 16.85), "LM-ICP": (0.001722, 0.022581, 16.62), "PP-ICP": None, "SYMM-ICP": None},
    {"ICP": (0.002007, 0.019513, 8.83), "LM-ICP": None, "PP-ICP": (0.003296, 0.01839, 6.74), "SYMM-ICP": (0.004129, 0.016704, 7.37)},
)  # fmt: skip
