"""The benchmarks run end to end (quick mode) and write every figure; their timings are only
printed, never asserted."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from tests.conftest import ROOT


def _run(script: str, *args: str, timeout: float = 600) -> subprocess.CompletedProcess[str]:
    """Runs benchmarks/SCRIPT with `args`; asserts it exited 0."""
    proc = subprocess.run(
        [sys.executable, str(ROOT / "benchmarks" / script), *args],
        capture_output=True,
        text=True,
        timeout=timeout,
    )
    assert proc.returncode == 0, proc.stderr[-2000:]
    return proc


def _quick(script: str, out: Path, *args: str) -> tuple[subprocess.CompletedProcess[str], dict]:
    """Runs benchmarks/SCRIPT --json OUT (with `args`, default --quick); returns the JSON."""
    proc = _run(script, *(args or ("--quick",)), "--json", str(out))
    return proc, json.loads(out.read_text())


def test_icp_benchmark_quick(tmp_path: Path) -> None:
    out = tmp_path / "icp.json"
    proc, data = _quick("icp.py", out)
    assert [t["start"] for t in data["tables"]] == ["warm", "identity"]
    for table in data["tables"]:
        methods = {r["method"]: r for r in table["rows"]}
        assert len(methods) == 10
        for v in ("point_to_point", "point_to_plane", "symmetric"):
            assert methods[f"vinetwin {v}"]["ratio_to_fastest_peer"] > 0
        assert methods["vinetwin lm"]["ratio_to_our_point_to_plane"] > 0
        for v in ("point_to_point", "point_to_plane", "symmetric"):
            acc = methods[f"vinetwin {v}"]["accuracy_vs_fastest_peer"]
            lo, hi = acc["ci95_mm"]
            assert lo <= acc["median_diff_mm"] <= hi and acc["verdict"] in (
                "worse",
                "equal",
                "better",
            )
            assert len(methods[f"vinetwin {v}"]["t_mm_cases"]) == table["cases"]
    assert {c["voxel"] for c in data["cycles"]} == {0.004}
    assert {c["start"] for c in data["cycles"]} == {"tracking", "warm"}
    assert all(c["hz"] > 0 and c["perception_ms"] > 0 for c in data["cycles"])
    assert {c["variant"] for c in data["cycles"]} == {
        "point_to_point",
        "lm",
        "point_to_plane",
        "symmetric",
    }
    assert "servo cycle" in proc.stdout
    # the figures say where they were measured: timings of two machines do not compare
    m = data["machine"]
    assert m["cores"] >= 1 and m["cpu"] and m["python"].startswith("3.")
    assert m["measured"].startswith("20") and isinstance(m["commit"], str)


def test_paired_accuracy_verdicts(monkeypatch: pytest.MonkeyPatch) -> None:
    """The ICP benchmark's accuracy comparison on known per-case errors: a constant 1 mm worse
    is "worse" with the interval at 1 mm, 1 mm better is "better", a copy is "equal", and
    differences that scatter around 0 leave it "equal" with an interval spanning 0."""
    monkeypatch.syspath_prepend(str(ROOT / "benchmarks"))
    from icp import paired_accuracy  # type: ignore[import-not-found]

    peer = [0.5, 1.2, 2.0, 0.8, 3.1, 1.7, 0.9, 2.4, 1.1, 0.6, 1.9, 2.2]
    worse = paired_accuracy([x + 1.0 for x in peer], peer)
    assert worse["verdict"] == "worse" and worse["median_diff_mm"] == pytest.approx(1.0)
    assert (
        worse["ci95_mm"] == pytest.approx([1.0, 1.0]) and worse["within_tolerance_or_better"] == 0
    )
    assert paired_accuracy([x - 1.0 for x in peer], peer)["verdict"] == "better"
    assert paired_accuracy(peer, peer)["verdict"] == "equal"
    mixed = paired_accuracy([x + (0.4 if k % 2 else -0.4) for k, x in enumerate(peer)], peer)
    assert mixed["verdict"] == "equal" and mixed["ci95_mm"][0] < 0 < mixed["ci95_mm"][1]


def test_render_benchmark_quick(tmp_path: Path) -> None:
    """Per reference for each backend and resolution, and the export with the backend `auto`
    chose for that many references (20 in quick mode)."""
    from vinetwin.render.backends import BACKENDS, resolve_backend

    out = tmp_path / "render.json"
    _, data = _quick("render.py", out)
    assert data["twin"] and len(data["per_reference"]) == 2 * len(BACKENDS)  # two resolutions
    for r in data["per_reference"]:
        assert "skipped" in r or r["reference_ms"] >= r["render_ms"] > 0
    assert [e["workers"] for e in data["export"]] == [1, 2]
    for e in data["export"]:
        assert e["backend"] == resolve_backend(None, 20) and e["failed"] == 0
        assert e["rerun_skipped"] == e["references"] == 20


def test_scale_benchmark_quick(tmp_path: Path) -> None:
    """Every executor row is measured (local pool, in process, Ray) for export and validation."""
    out = tmp_path / "scale.json"
    _, data = _quick("scale.py", out)
    jobs = [(r["job"], r["executor"]) for r in data["rows"]]
    assert len(jobs) == 5 and ("export", "Ray, 2 CPUs") in jobs
    assert all(r["per_second"] > 0 for r in data["rows"])


def test_icp_tables_read_the_benchmark_json(tmp_path: Path) -> None:
    """`benchmarks/icp_tables.py` turns the committed results into the tables of
    docs/results/speed.md."""
    files = sorted(str(p) for p in (ROOT / "benchmarks" / "results").glob("icp*.json"))
    assert len(files) >= 3
    proc = _run("icp_tables.py", *files, timeout=120)
    assert proc.stdout.count("| tracking |") == 2 * len(files)


def test_the_speed_page_is_what_the_results_files_hold() -> None:
    """`benchmarks/tables.py` prints the current tables from the committed results, one file
    per benchmark and vine, each with its machine and commit; `docs/results/speed.md` holds that
    output (the tables are regenerated with the files, not edited by hand)."""
    results = ROOT / "benchmarks" / "results"
    proc = _run("tables.py", timeout=120)
    for name in ("icp", "render", "web"):
        assert f"`{name}.json`: " in proc.stdout and "commit " in proc.stdout
    page = (ROOT / "docs" / "results" / "speed.md").read_text()
    for table_line in [ln for ln in proc.stdout.splitlines() if ln.startswith("| ")]:
        assert table_line in page, table_line
    names = {p.name for p in results.glob("*.json")}
    assert not {n for n in names if n.startswith(("web_clock", "web_display", "web_llvmpipe"))}


def test_web_benchmark_quick(tmp_path: Path) -> None:
    """`benchmarks/web.py` clicks the sample in headless Chromium and writes each part of the
    click-to-preview time (figures printed, never asserted)."""
    from vinetwin.web.browser import CHROMIUM

    if not CHROMIUM.exists():
        pytest.skip("Debian's chromium is not installed")
    out = tmp_path / "web.json"
    proc, data = _quick("web.py", out, "--clicks", "2", "--pause", "0.2")
    assert set(data["runs"]) == {"fast", "full"}  # both shadings, in the same invocation
    assert data["gl"] == "swiftshader" and data["pause_s"] == 0.2
    for run in data["runs"].values():
        assert "SwiftShader" in run["renderer"]  # what --gl asked for, as the page reports it
        assert run["measured"] + run["missed"] == 2 and run["measured"] >= 1, proc.stdout[-3000:]
        for part in ("arrive_ms", "server_ms", "browser_ms", "drawn_ms"):
            assert run[part]["median"] > 0
        assert run["browser_ms"]["median"] >= run["server_ms"]["median"]
        # the page's clock (viser's test hook is there): the input to the preview's frame
        # drawn holds the server's part
        assert run["via"] == "pointer" and run["drawn_ms"]["median"] >= run["server_ms"]["median"]
    assert "click to preview" in proc.stdout and "full" in proc.stdout
    # clicks sent as messages by a script in the page, without the pointer: they place cut
    # points like the mouse's
    proc, data = _quick(
        "web.py", tmp_path / "msg.json", "--clicks", "2", "--pause", "0.2", "--shading", "fast",
        "--via", "message",
    )  # fmt: skip
    run = data["runs"]["fast"]
    assert data["via"] == run["via"] == "message"
    assert run["measured"] == 2 and run["missed"] == 0, proc.stdout[-3000:]
    assert run["drawn_ms"]["median"] >= run["server_ms"]["median"] > 0


def test_perception_benchmark_quick(tmp_path: Path) -> None:
    """Each outlier rule's chain time, Open3D's, and the four variants' errors on its clouds."""
    from vinetwin.cloud import OUTLIER_RULES

    proc, data = _quick("perception.py", tmp_path / "perception.json")
    (table,) = data["tables"]
    assert table["voxel"] == 0.004 and table["views"] >= 1
    assert [r["rule"] for r in table["rows"]] == list(OUTLIER_RULES)
    for r in table["rows"]:
        assert r["perception_ms"] > 0 and r["open3d_ms"] > 0 and r["points"] > 100
        assert set(r["icp"]) == {"point_to_point", "lm", "point_to_plane", "symmetric"}
        # the sample's warm starts converge with every rule (errors are in mm)
        assert r["icp"]["symmetric"]["t_mm_median"] < 1.0
    assert "Open3D ms" in proc.stdout
    # --decimation compares PerceptionConfig.decimation values instead of the rules
    _, dec = _quick("perception.py", tmp_path / "dec.json", "--quick", "--decimation", "1", "2")
    (table,) = dec["tables"]
    rows = table["rows"]
    assert [r["decimation"] for r in rows] == [1, 2] and rows[0]["rule"] == rows[1]["rule"]
    assert 0.5 * rows[0]["points"] < rows[1]["points"] < rows[0]["points"]
    assert rows[1]["icp"]["symmetric"]["t_mm_median"] < 1.0


def test_sim_benchmark_quick(tmp_path: Path) -> None:
    """A closed-loop run per scene backend, its time split into render, D405 model, servo step
    and the rest."""
    out = tmp_path / "sim.json"
    proc, data = _quick("sim.py", out)
    names = [r["backend"] for r in data["rows"]]
    # MuJoCo is left out, saying why, where it cannot start; the others start anywhere
    assert names in (["open3d", "mujoco", "raster"], ["open3d", "raster"]), names
    assert "mujoco" in names or "mujoco left out" in proc.stdout
    for r in data["rows"]:
        assert r["frames"] > 0 and r["x_real_time"] > 0 and r["render_ms"] > 0
        parts = r["render_ms"] + r["sensor_ms"] + r["servo_step_ms"] + r["rest_ms"]
        assert abs(parts - r["ms_per_frame"]) < 1e-6 * max(1.0, r["ms_per_frame"])
    assert "goal 3x" in proc.stdout


def test_propose_benchmark_quick(tmp_path: Path) -> None:
    """`benchmarks/propose.py` on the sample with the spur rule: every cut has a pose, none
    collides by the independent check, and references were rendered."""
    out, stab = tmp_path / "propose.json", tmp_path / "stability.json"
    _, data = _quick("propose.py", out, "--plants", "sample", "--rules", "spur", "--stability",
                     "--stability-json", str(stab))  # fmt: skip
    (row,) = data["rows"]
    assert row["proposed"] >= 8 and row["with_pose"] == row["proposed"]
    assert row["collisions"] == 0 and row["min_body_distance_mm"] > 0
    assert row["median_reference_points"] > 100
    # the rule's own stability: resampling the sample's skeleton moves none of its cuts, and
    # the jitter moves its axis by about the sigma asked (median of a 3D offset: 1.1 sigma)
    (st,) = json.loads(stab.read_text())["stability"]
    rows = {r["sigma_mm"]: r for r in st["rows"]}
    assert rows[0.0]["share"] == 1.0 and rows[0.0]["median_offset_mm"] == 0.0
    for sigma in (0.5, 1.0, 2.0):
        assert 0.8 * sigma <= rows[sigma]["median_offset_mm"] <= 1.4 * sigma
        assert rows[sigma]["share"] >= 0.9  # the sample's canes are far apart: few flips


def test_prune_benchmark_quick(tmp_path: Path) -> None:
    """`benchmarks/prune.py --quick`: the sample pruned (kinematic, ideal) with every cut done
    right and no collision; our collision check and Open3D's in the same planner; our IK."""
    out = tmp_path / "prune.json"
    _, data = _quick("prune.py", out)
    (row,) = data["rows"]
    assert row["done_right"] == row["reachable"] == 5 and row["collisions"] == 0
    checks = data["collision_checks"]
    assert checks["vinetwin"]["median_transit_s"] > 0 and checks["open3d"]["check_us"] > 0
    assert data["inverse_kinematics"]["vinetwin"]["solved"] >= 35


def test_prune_row_benchmark_quick(tmp_path: Path) -> None:
    """`benchmarks/prune_row.py` on two generated vines (kinematic, ideal, no Ray): in process and
    on the local pool, every vine's result the same."""
    pytest.importorskip("ompl")
    out = tmp_path / "row.json"
    _, data = _quick("prune_row.py", out, "--vines", "2", "--cuts", "2", "--sim", "kinematic",
                     "--no-ray", "--keep", str(tmp_path / "work"))  # fmt: skip
    assert data["agree"] is True and len(data["per_vine"]) == 2
    assert all(len(v) == 2 and all(v) for v in data["same"].values())


def test_scan_accuracy_benchmark_on_a_generated_vine_of_another_seed(tmp_path: Path) -> None:
    """`sample@N` scans `generate_vine(N)` (the held-out and development sets are such vines):
    seed 2's vine has 8 candidates and 10 canes, and its scan's skeleton is found."""
    out = tmp_path / "scan.json"
    proc, data = _quick("scan_accuracy.py", out, "--plants", "sample@2", "--qualities", "realistic")
    (row,) = data["rows"]
    assert row["plant"] == "sample@2" and "| sample@2 |" in proc.stdout
    assert row["candidates_true"] == 8 and row["canes_seen"] == 10, row
    assert row["completeness"] >= 0.98 and row["precision"] >= 0.98, row


def test_scan_up_benchmark_on_the_bundled_trees(tmp_path: Path) -> None:
    """`scan_up.py` scans each tree model of a folder without ground and reports the up found:
    the bundled spindle apple at the coarse quality stands within 5 degrees, from its trunk."""
    from tests.conftest import shared

    trees = tmp_path / "trees"
    trees.mkdir()
    name = "Apple_1_TallSpindle.txt"
    (trees / name).write_bytes(shared("trees", "tree-models-library", name).read_bytes())
    out = tmp_path / "up.json"
    proc, data = _quick("scan_up.py", out, "--trees", str(trees), "--qualities", "coarse")
    (row,) = data["rows"]
    assert row["tree"] == "Apple_1_TallSpindle" and row["up_error_deg"] <= 5.0, row
    assert "the trunk's direction" in row["up_from"] and not row["uncertain"], row
    assert "1 of 1 scans within 5 degrees" in proc.stdout
