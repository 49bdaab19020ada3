"""The twin folder: round trips, validation of bad files, atomic saves, cut points and poses."""

from __future__ import annotations

import json
import math
import os
import shutil
import time
from pathlib import Path

import numpy as np
import pytest

from vinetwin import frames as fr
from vinetwin.errors import MeshError, TwinError, TwinFieldError, TwinVersionError, VinetwinError
from vinetwin.twin import Approach, Twin, pruning_pose
from vinetwin.twin import poses as tp


def box_mesh() -> tuple[np.ndarray, np.ndarray]:
    import trimesh

    m = trimesh.creation.box(extents=[0.1, 0.1, 0.1])
    return np.asarray(m.vertices), np.asarray(m.faces)


@pytest.fixture
def twin(tmp_path: Path) -> Twin:
    V, F = box_mesh()
    t = Twin.create(tmp_path / "a.twin", V, F)
    c = t.add_cut_point([0.0, 0.0, 0.05], [0, 0, 1])
    t.add_pose(c.id)
    t.save()
    return t


def test_round_trip_preserves_everything(twin: Twin) -> None:
    loaded = Twin.load(twin.root)
    assert loaded.to_json() == json.loads(json.dumps(twin.to_json()))
    np.testing.assert_allclose(loaded.poses[0].T_vine_camera, twin.poses[0].T_vine_camera)
    assert loaded.camera == twin.camera
    mesh = loaded.load_mesh()
    assert len(mesh.faces) == 12


def test_unknown_fields_survive(twin: Twin) -> None:
    data = json.loads(twin.json_path.read_text())
    data["future_field"] = {"x": 1}
    data["cut_points"][0]["color"] = "red"
    data["pruning_poses"][0]["note"] = "keep me"
    twin.json_path.write_text(json.dumps(data))
    t = Twin.load(twin.root)
    t.save()
    again = json.loads(twin.json_path.read_text())
    assert again["future_field"] == {"x": 1}
    assert again["cut_points"][0]["color"] == "red"
    assert again["pruning_poses"][0]["note"] == "keep me"


def _corrupt(path: Path, edit) -> bytes:  # type: ignore[no-untyped-def]
    data = json.loads(path.read_text())
    edit(data)
    path.write_text(json.dumps(data))
    return path.read_bytes()


def _nan_pose(d: dict) -> None:
    d["pruning_poses"][0]["T_vine_camera"][0][3] = math.nan


@pytest.mark.parametrize(
    ("edit", "error", "needle"),
    [
        (lambda d: d.pop("camera"), TwinFieldError, "'camera': is missing"),
        (lambda d: d["camera"].update(width="848"), TwinFieldError, "camera.width"),
        (_nan_pose, TwinFieldError, "pruning_poses[0].T_vine_camera"),
        (lambda d: d.update(format_version=99), TwinVersionError, "version 99"),
        (lambda d: d.update(mesh="gone.ply"), TwinFieldError, "'gone.ply' does not exist"),
        (lambda d: d.update(mesh="../escape.ply"), TwinFieldError, "inside the twin folder"),
        (lambda d: d["cut_points"][0].pop("cane_axis"), TwinFieldError, "cut_points[0].cane_axis"),
        (
            lambda d: d["pruning_poses"][0].update(icp_variant="p2l"),
            TwinFieldError,
            "choose one of",
        ),
        (
            lambda d: d["pruning_poses"][0].update(cut_point="c99"),
            TwinFieldError,
            "names no cut point",
        ),
        (lambda d: d["perception"].update(voxel_size=-1), TwinFieldError, "perception.voxel_size"),
        (
            lambda d: d["perception"].update(outlier_rule="median"),
            TwinFieldError,
            "perception.outlier_rule",
        ),
        (lambda d: d["perception"].update(decimation=0), TwinFieldError, "perception.decimation"),
        (lambda d: d["perception"].update(decimation=1.5), TwinFieldError, "perception.decimation"),
        (lambda d: d.update(format="other"), TwinFieldError, "'format'"),
    ],
)
def test_bad_files_name_the_problem_and_stay_untouched(twin: Twin, edit, error, needle) -> None:  # type: ignore[no-untyped-def]
    before = _corrupt(twin.json_path, edit)
    with pytest.raises(error) as exc:
        Twin.load(twin.root)
    assert isinstance(exc.value, VinetwinError)
    assert needle in str(exc.value)
    assert twin.json_path.read_bytes() == before


def test_truncated_json(twin: Twin) -> None:
    text = twin.json_path.read_bytes()
    twin.json_path.write_bytes(text[: len(text) // 2])
    with pytest.raises(TwinError, match="truncated"):
        Twin.load(twin.root)
    assert twin.json_path.read_bytes() == text[: len(text) // 2]


def test_missing_folder_and_mesh(tmp_path: Path, twin: Twin) -> None:
    with pytest.raises(TwinError, match=r"no twin\.json"):
        Twin.load(tmp_path / "nothing")
    twin.mesh_path.unlink()
    with pytest.raises(TwinFieldError, match="does not exist"):
        Twin.load(twin.root)


def test_corrupt_mesh_is_a_mesh_error(twin: Twin) -> None:
    twin.mesh_path.write_bytes(
        b"ply\nformat binary_little_endian 1.0\nelement vertex 99\nend_header\n\x00"
    )
    with pytest.raises(MeshError):
        Twin.load(twin.root).load_mesh()


def test_mesh_arrays_read_as_trimesh_reads_them(tmp_path: Path, sample_twin_dir: Path) -> None:
    """`load_mesh_arrays` reads binary PLY triangle meshes itself (no trimesh import in the
    export and campaign workers) and gives trimesh's arrays to the bit; other files go through
    trimesh (ASCII, quads, extra elements), and a corrupt or truncated one is a MeshError."""
    import trimesh

    from vinetwin.mesh import _binary_ply_triangles, load_mesh_arrays

    def same(path: Path) -> None:
        V, F = load_mesh_arrays(path)
        m = trimesh.load(path, force="mesh", process=False)
        assert isinstance(m, trimesh.Trimesh)
        assert V.dtype == np.float64 and F.dtype == np.int64
        assert np.array_equal(V, m.vertices) and np.array_equal(F, m.faces)

    sample = sample_twin_dir / "vine.ply"
    assert _binary_ply_triangles(sample) is not None  # the twins' own form: read without trimesh
    same(sample)
    V, F = box_mesh()
    rng = np.random.default_rng(0)
    V = V + rng.normal(0, 1e-3, V.shape)
    box = trimesh.Trimesh(V, F, process=False)
    for name, kwargs in (("le.ply", {"encoding": "binary"}), ("ascii.ply", {"encoding": "ascii"})):
        data = box.export(file_type="ply", **kwargs)
        assert isinstance(data, bytes)
        (tmp_path / name).write_bytes(data)
        same(tmp_path / name)
    assert _binary_ply_triangles(tmp_path / "ascii.ply") is None  # read by trimesh
    # big-endian, double vertices with extra properties, int16 counts, uint indices
    header = (
        "ply\nformat binary_big_endian 1.0\nelement vertex 8\nproperty double x\n"
        "property double y\nproperty double z\nproperty uchar red\nelement face 12\n"
        "property list short uint vertex_indices\nend_header\n"
    )
    vert = np.zeros(8, [("x", ">f8"), ("y", ">f8"), ("z", ">f8"), ("r", "u1")])
    vert["x"], vert["y"], vert["z"] = V.T
    face = np.zeros(12, [("n", ">i2"), ("i", ">u4", 3)])
    face["n"], face["i"] = 3, F
    (tmp_path / "be.ply").write_bytes(header.encode() + vert.tobytes() + face.tobytes())
    assert _binary_ply_triangles(tmp_path / "be.ply") is not None
    same(tmp_path / "be.ply")
    # quads: not the fast form; trimesh triangulates them
    quads = np.zeros(2, [("n", ">i2"), ("i", ">u4", 4)])
    quads["n"], quads["i"] = 4, [[0, 1, 2, 3], [4, 5, 6, 7]]
    qhead = header.replace("element face 12", "element face 2")
    (tmp_path / "quad.ply").write_bytes(qhead.encode() + vert.tobytes() + quads.tobytes())
    assert _binary_ply_triangles(tmp_path / "quad.ply") is None
    assert load_mesh_arrays(tmp_path / "quad.ply")[1].shape == (4, 3)
    # truncated, and faces indexing missing vertices
    data = (tmp_path / "le.ply").read_bytes()
    (tmp_path / "cut.ply").write_bytes(data[:-7])
    with pytest.raises(MeshError):
        load_mesh_arrays(tmp_path / "cut.ply")
    face["i"][0] = [0, 1, 99]
    (tmp_path / "range.ply").write_bytes(header.encode() + vert.tobytes() + face.tobytes())
    with pytest.raises(MeshError, match="out of range"):
        load_mesh_arrays(tmp_path / "range.ply")
    with pytest.raises(MeshError, match="does not exist"):
        load_mesh_arrays(tmp_path / "none.ply")


def test_create_refuses_bad_meshes(tmp_path: Path) -> None:
    V, F = box_mesh()
    V = V.copy()
    V[0, 0] = np.nan
    with pytest.raises(MeshError, match="non-finite"):
        Twin.create(tmp_path / "nan.twin", V, F)
    with pytest.raises(MeshError, match="no triangle faces"):
        Twin.create(tmp_path / "nofaces.twin", V[1:], np.zeros((0, 3), int))
    assert not (tmp_path / "nan.twin" / "twin.json").exists()


def test_create_refuses_to_overwrite(twin: Twin) -> None:
    V, F = box_mesh()
    with pytest.raises(TwinError, match="already holds a twin"):
        Twin.create(twin.root, V, F)


def test_crash_during_save_keeps_previous_file(twin: Twin, monkeypatch: pytest.MonkeyPatch) -> None:
    before = twin.json_path.read_bytes()
    twin.add_cut_point([0.01, 0, 0.05], [0, 0, 1])

    def boom(src: str, dst: str) -> None:
        raise OSError("disk full")

    monkeypatch.setattr(os, "replace", boom)
    with pytest.raises(TwinError, match="disk full"):
        twin.save()
    assert twin.json_path.read_bytes() == before
    assert [p.name for p in twin.root.iterdir() if p.name.endswith((".tmp", ".vttmp"))] == []


def test_orphan_temp_files_are_removed_and_live_ones_kept(tmp_path: Path) -> None:
    """A writer killed between writing its temporary file and the rename leaves an orphan: one
    from a process that is gone, or older than ORPHAN_AGE_S, is removed; one a live process is
    still writing is kept, and so are files that are not temporary files."""
    import subprocess
    import sys

    from vinetwin.files import ORPHAN_AGE_S, _host_tag, remove_orphan_temp_files

    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"],
                          capture_output=True, text=True, check=True)  # fmt: skip
    host = _host_tag()
    names = {
        "dead": f".p1.ply.vinetwin-{host}-{dead.stdout.strip()}.abc1230000.vttmp",
        "live": f".p2.ply.vinetwin-{host}-{os.getpid()}.def4560000.vttmp",
        "elsewhere": ".p3.ply.vinetwin-otherhost-1.0789abcdef.vttmp",
        "elsewhere_old": ".p4.ply.vinetwin-otherhost-1.0123456789.vttmp",
        "users_old": ".notes.tmp",  # not a name vinetwin makes: never removed, however old
        "users_old_2": f".p5.ply.{host}-{dead.stdout.strip()}.abc123.tmp",
        "data": "p6.ply",
    }
    for n in names.values():
        (tmp_path / n).write_bytes(b"partial")
    old = time.time() - ORPHAN_AGE_S - 10
    for k in ("elsewhere_old", "users_old", "users_old_2"):
        os.utime(tmp_path / names[k], (old, old))
    removed = sorted(p.name for p in remove_orphan_temp_files(tmp_path))
    assert removed == sorted(names[k] for k in ("dead", "elsewhere_old"))
    left = sorted(p.name for p in tmp_path.iterdir())
    keep = ("live", "elsewhere", "users_old", "users_old_2", "data")
    assert left == sorted(names[k] for k in keep)
    assert remove_orphan_temp_files(tmp_path / "missing") == []


def test_cut_point_editing_keeps_poses_consistent(twin: Twin) -> None:
    cut = twin.cut_points[0]
    pose = twin.poses[0]
    twin.move_cut_point(cut.id, [0.02, 0.0, 0.04])
    assert tp.axis_miss_distance(pose.T_vine_camera, cut.point) < 1e-12
    c2 = twin.add_cut_point([0.0, 0.01, 0.05], [1, 0, 0])
    assert c2.id == "c2"
    twin.add_pose(c2.id, icp_variant="symmetric")
    gone = twin.delete_cut_point(cut.id)
    assert [p.id for p in gone] == ["p1"]
    assert [p.cut_point for p in twin.poses] == ["c2"]
    twin.save()
    assert [c.id for c in Twin.load(twin.root).cut_points] == ["c2"]


def test_set_pose_updates_description(twin: Twin) -> None:
    pose = twin.poses[0]
    cut = twin.cut_point(pose.cut_point)
    T = pruning_pose(cut.point, cut.cane_axis, Approach(0.2, 1.0, 0.3, 0.4))
    twin.set_pose(pose.id, T)
    assert pose.standoff == pytest.approx(0.2)
    assert (pose.approach.azimuth, pose.approach.elevation, pose.approach.roll) == pytest.approx(
        (1.0, 0.3, 0.4)
    )


@pytest.mark.parametrize("axis", [[0, 0, 1], [1, 0, 0], [0.3, 0.2, 0.9], [0, 1, 0]])
def test_default_pruning_pose_geometry(axis: list[float]) -> None:
    p = np.array([0.1, -0.2, 0.8])
    a = np.asarray(axis, float) / np.linalg.norm(axis)
    T = pruning_pose(p, a)
    fr.check_pose(T)
    z = T[:3, 2]
    assert np.linalg.norm(p - T[:3, 3]) == pytest.approx(0.15)  # standoff
    assert tp.axis_miss_distance(T, p) < 1e-12  # optical axis through the cut
    assert abs(z @ a) < 1e-9  # approach perpendicular to the cane
    # the cane runs across the image: its direction in the camera frame is +x
    a_cam = T[:3, :3].T @ a
    np.testing.assert_allclose(a_cam, [1, 0, 0], atol=1e-9)
    if abs(a[1]) < 0.99:
        assert z[1] > 0  # from the robot's side (-Y) towards the row


def test_approach_round_trip_and_snap(rng: np.random.Generator) -> None:
    p = np.array([0.0, 0.0, 0.7])
    a = np.array([0.1, 0.0, 1.0])
    for _ in range(20):
        ap = Approach(
            rng.uniform(0.08, 0.3), rng.uniform(-3, 3), rng.uniform(-1.2, 1.2), rng.uniform(-3, 3)
        )
        T = pruning_pose(p, a, ap)
        back = tp.approach_of(T, p, a)
        assert (back.standoff, back.azimuth, back.elevation, back.roll) == pytest.approx(
            (ap.standoff, ap.azimuth, ap.elevation, ap.roll), abs=1e-9
        )
        moved = T.copy()
        moved[:3, 3] += rng.normal(size=3) * 0.03
        snapped = tp.snap_to_cut_point(moved, p, a)
        assert tp.axis_miss_distance(snapped, p) < 1e-12
        np.testing.assert_allclose(snapped[:3, 3], moved[:3, 3], atol=1e-12)


def test_estimate_cane_axis_from_mesh() -> None:
    from vinetwin.twin.skeleton import Branch, tube_mesh

    d = np.array([0.2, 0.1, 1.0]) / np.linalg.norm([0.2, 0.1, 1.0])
    V, _ = tube_mesh([Branch(np.outer(np.linspace(0, 0.3, 10), d), np.full(10, 0.004))])
    axis = tp.estimate_cane_axis(V, 0.15 * d)
    assert abs(axis @ d) > 0.999


def test_a_tube_mesh_past_its_vertex_ceiling_is_refused_before_it_is_made(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    from vinetwin.errors import InputError
    from vinetwin.twin import skeleton as skm
    from vinetwin.twin.generator import generate_vine

    sk = generate_vine(0)
    V, _ = skm.tube_mesh(sk, edge=0.003, caps="flat")
    # the count made before meshing is the mesh's own (the flat caps' centres aside)
    n = sum(m * rings for m, _, _, rings in
            (skm._rings(b.points, b.radii, 0.003, 2e-4) for b in sk.branches))  # fmt: skip
    assert n <= len(V) <= n + 2 * len(sk.branches)
    monkeypatch.setattr(skm, "MAX_TUBE_VERTICES", n - 1)
    with pytest.raises(InputError, match=r"million vertices .* coarser edge"):
        skm.tube_mesh(sk, edge=0.003, caps="flat")
    # a thin branch carrying one thick radius: fine rings all along it
    thin = skm.Branch(
        np.outer(np.linspace(0, 20.0, 200), [1.0, 0, 0]), np.r_[0.1, np.full(199, 5e-4)]
    )
    monkeypatch.setattr(skm, "MAX_TUBE_VERTICES", 30_000_000)
    with pytest.raises(InputError, match="thin branch carrying a thick radius"):
        skm.tube_mesh([thin] * 20, edge=0.0005)


def test_bundled_samples_load(sample_twin_dir: Path) -> None:
    root = sample_twin_dir.parent
    samples = sorted(root.glob("*.twin"))
    assert len(samples) >= 2
    total = 0
    for s in samples:
        t = Twin.load(s)
        mesh = t.load_mesh()
        assert len(mesh.faces) > 50_000
        assert len(t.poses) >= 3 and t.load_skeleton() is not None
        total += sum(f.stat().st_size for f in s.rglob("*") if f.is_file())
    assert total < 6e6  # "a few MB at most in all"


def test_copy_of_twin_is_independent(twin: Twin, tmp_path: Path) -> None:
    dst = tmp_path / "copy.twin"
    shutil.copytree(twin.root, dst)
    t = Twin.load(dst)
    t.add_cut_point([0, 0, 0], [0, 0, 1])
    t.save()
    assert len(Twin.load(twin.root).cut_points) == 1
