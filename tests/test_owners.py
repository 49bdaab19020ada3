"""One owner per artefact (docs/architecture.md, "Owners"): a pose's reference is built by
`render.reference.reference_for`, a simulated run by `sim.session.SimSpec`, every setting is
declared once; and the fixes that made the settings agree, each pinned by its behaviour."""

from __future__ import annotations

import ast
import inspect
import shutil
from pathlib import Path

import numpy as np
import pytest

from tests.conftest import ROOT

SRC = ROOT / "src" / "vinetwin"


def _sample_copy(tmp_path: Path) -> Path:
    from vinetwin.twin.model import bundled_sample

    dst = tmp_path / "t.twin"
    shutil.copytree(bundled_sample(), dst, ignore=shutil.ignore_patterns("references"))
    return dst


# ----------------------------------------------------------------------------- structure
def test_no_module_outside_render_names_a_backend() -> None:
    """Outside `render/` no code names a render backend: a string that is one (`"open3d"`,
    `"raster"`, ...) as a backend, or `get_backend`. "mujoco" stays the name of a simulated
    robot (`--robot mujoco`, `--sim mujoco`) and the module `_lazy` imports; "open3d" the
    library `_lazy` imports."""
    from vinetwin.render.backends import BACKENDS

    found = []
    for path in sorted(SRC.rglob("*.py")):
        rel = path.relative_to(SRC)
        if rel.parts[0] == "render":
            continue
        tree = ast.parse(path.read_text())
        for node in ast.walk(tree):
            if isinstance(node, ast.Name | ast.Attribute):
                name = node.id if isinstance(node, ast.Name) else node.attr
                if name == "get_backend":
                    found.append(f"{rel}:{node.lineno} get_backend")
            if isinstance(node, ast.Constant) and node.value in BACKENDS:
                allowed = (rel.name == "_lazy.py") or (
                    node.value == "mujoco" and rel.parts[0] in ("servo", "sim")
                )
                if not allowed:
                    found.append(f"{rel}:{node.lineno} {node.value!r}")
    assert not found, found


def test_the_reference_has_one_builder() -> None:
    """`render_reference` is called in `render/` only (export, `reference_for`) and by the
    session spec, which renders a simulated run's reference from its own world."""
    callers = set()
    for path in sorted(SRC.rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Call):
                f = node.func
                name = f.id if isinstance(f, ast.Name) else getattr(f, "attr", "")
                if name == "render_reference":
                    callers.add(str(path.relative_to(SRC)))
    assert callers == {"render/reference.py", "render/export.py", "sim/session.py"}, callers


def test_session_path_functions_take_at_most_six_parameters() -> None:
    """The session path: the reference's owner, the session spec and its run, the hardware
    session and the servo command."""
    from vinetwin.render import reference
    from vinetwin.servo import runner, session
    from vinetwin.sim import session as sim_session
    from vinetwin.sim import simulate

    too_many = []
    for module in (reference, runner, session, sim_session, simulate):
        for name, fn in inspect.getmembers(module, inspect.isfunction):
            if fn.__module__ != module.__name__:
                continue
            n = len(inspect.signature(fn).parameters)
            if n > 6:
                too_many.append(f"{module.__name__}.{name}: {n}")
        for _, cls in inspect.getmembers(module, inspect.isclass):
            if cls.__module__ != module.__name__:
                continue
            for name, fn in inspect.getmembers(cls, inspect.isfunction):
                if name.startswith("__"):
                    continue
                n = len(inspect.signature(fn).parameters) - 1  # self
                if n > 6:
                    too_many.append(f"{cls.__name__}.{name}: {n}")
    assert not too_many, too_many


def test_no_source_file_is_over_700_lines_and_no_cli_module_over_300() -> None:
    """The command line's modules hold argument definitions and calls only: a family of
    commands (`cli/twin.py`, `cli/sim.py`, `cli/capture.py`) stays short."""
    sizes = {p: len(p.read_text().splitlines()) for p in SRC.rglob("*.py")}
    assert not {str(p): n for p, n in sizes.items() if n > 700}
    cli = {p.name: n for p, n in sizes.items() if p.parent == SRC / "cli"}
    assert len(cli) >= 4 and max(cli.values()) <= 300, cli


# ----------------------------------------------------------------------------- settings
def test_the_d405_modes_are_one_list() -> None:
    """The camera presets, the live source and the minimum depths read one list; a mode
    without a datasheet minimum depth (424x240) is refused by the live source."""
    from vinetwin.camera import D405_MIN_DEPTH, D405_RESOLUTIONS, d405
    from vinetwin.capture.sources import D405_MODES, open_source
    from vinetwin.errors import InputError

    assert D405_MODES == tuple(D405_MIN_DEPTH)
    assert D405_RESOLUTIONS == tuple(f"{w}x{h}" for w, h in D405_MIN_DEPTH)
    for res in D405_RESOLUTIONS:
        cam = d405(res)
        assert cam.min_depth == D405_MIN_DEPTH[(cam.width, cam.height)]
    with pytest.raises(InputError, match="streams depth at"):
        open_source("realsense", width=424, height=240)


def _plane_capture(root: Path, resolution: str, z: float) -> object:
    """A capture of six frames of a plane `z` metres in front of the camera."""
    from vinetwin.camera import d405
    from vinetwin.capture.folder import CaptureWriter, read_capture

    cam = d405(resolution)
    counts = np.zeros((cam.height, cam.width), np.uint16)
    h, w = cam.height // 4, cam.width // 4
    counts[h : 3 * h, w : 3 * w] = round(z / cam.depth_unit)
    writer = CaptureWriter(root, cam, cam.depth_unit)
    for k in range(6):
        T = np.eye(4)
        T[0, 3] = 0.001 * k
        writer.add(counts, None, T)
    writer.close()
    return read_capture(root)


def test_fusion_keeps_no_depth_the_camera_calls_invalid(tmp_path: Path) -> None:
    """The D405 at 1280x720 reports nothing nearer than 0.100 m: fusion used to keep depth
    down to 0.07 m at every resolution. A plane at 0.085 m is fused at 848x480 (minimum
    0.070) and skipped, named, at 1280x720."""
    from vinetwin.capture.folder import CaptureError
    from vinetwin.reconstruct.fusion import fuse, kinematic_poses

    near = _plane_capture(tmp_path / "848", "848x480", 0.085)
    res = fuse(near, kinematic_poses(near))  # type: ignore[arg-type]
    assert len(res.frames_used) == 6 and len(res.faces) > 0
    hd = _plane_capture(tmp_path / "1280", "1280x720", 0.085)
    with pytest.raises(CaptureError, match="no frame could be fused"):
        fuse(hd, kinematic_poses(hd))  # type: ignore[arg-type]
    far = _plane_capture(tmp_path / "1280far", "1280x720", 0.12)
    assert len(fuse(far, kinematic_poses(far)).frames_used) == 6  # type: ignore[arg-type]


def test_a_pose_at_another_standoff_keeps_its_cut_point_as_the_target(tmp_path: Path) -> None:
    """`--law target` servos the cut point's image: a pose 0.25 m from its cut got a target
    0.15 m along its axis in `simulate` and the validation (the old fallback); now every
    simulated session (servo command, validation, campaign) has the pose's cut point."""
    from vinetwin.render.backends import raycaster
    from vinetwin.servo.config import RunnerConfig, ServoConfig
    from vinetwin.sim.config import ValidateConfig
    from vinetwin.sim.session import SimSpec, SimWorld, servo_spec
    from vinetwin.sim.validate import _plan
    from vinetwin.twin.model import Twin
    from vinetwin.twin.poses import Approach, default_approach

    twin = Twin.load(_sample_copy(tmp_path))
    cut = twin.cut_points[0]
    ap = default_approach(cut.cane_axis, 0.25)
    pose = twin.add_pose(cut.id, Approach(0.25, ap.azimuth, ap.elevation, ap.roll))
    twin.save()
    at = np.array([0.0, 0.0, 0.25])  # the cut in the pose's camera frame

    spec = servo_spec(twin, pose, RunnerConfig(servo=ServoConfig(law="target")))
    assert np.allclose(spec.cut, cut.point)
    groups = _plan(twin, ValidateConfig(poses=(pose.id,), variants=("point_to_plane",)))[1]
    assert np.allclose(groups[0].cut, cut.point)
    mesh = twin.load_mesh()
    world = SimWorld(raycaster(mesh.vertices, mesh.faces, twin.camera), twin.perception)
    goal = np.asarray(pose.T_vine_camera)
    session = SimSpec(goal, goal, spec.config, pose.id, np.asarray(groups[0].cut)).setup(world)
    assert np.allclose(session.servo.target, at, atol=1e-9)
    session.close()
    world.backend.close()


def test_check_reference_aligns_with_the_poses_own_variant(tmp_path: Path) -> None:
    from vinetwin.servo.check import run_check
    from vinetwin.servo.config import CheckConfig
    from vinetwin.twin.model import Twin

    root = _sample_copy(tmp_path)
    twin = Twin.load(root)
    twin.poses[0].icp_variant = "symmetric"
    twin.save()
    check = run_check(root, CheckConfig(frames=1), tmp_path / "c1")
    assert check.variant == "symmetric" and check.valid, check.describe()
    other = run_check(root, CheckConfig(frames=1, variant="lm"), tmp_path / "c2")
    assert other.variant == "lm"


def test_the_arrival_and_odometry_settings_are_on_the_command_line(
    capsys: pytest.CaptureFixture[str],
) -> None:
    from vinetwin.cli import main
    from vinetwin.reconstruct.config import OdometryConfig
    from vinetwin.servo.config import ArrivalConfig

    assert main(["servo", "--help"]) == 0
    out = capsys.readouterr().out
    assert "--arrival-settings.voxel" in out and str(ArrivalConfig().voxel) in out
    assert main(["reconstruct", "--help"]) == 0
    out = capsys.readouterr().out
    assert "--odometry.voxel" in out and str(OdometryConfig().voxel) in out


def test_the_reference_is_read_or_rendered_once_by_its_owner(tmp_path: Path) -> None:
    """`reference_for`: the exported cloud when there is one (nothing rendered), else one
    render for the cloud and its dense cloud; an exported file that does not match its hash
    is refused."""
    from vinetwin.errors import InputError
    from vinetwin.render import reference as refmod
    from vinetwin.render.export import export_references
    from vinetwin.twin.model import Twin

    twin = Twin.load(_sample_copy(tmp_path))
    calls = []
    real = refmod.render_reference

    def counted(*args, **kwargs):  # type: ignore[no-untyped-def]
        calls.append(1)
        return real(*args, **kwargs)

    refmod.render_reference = counted  # type: ignore[assignment]
    try:
        rendered = refmod.reference_for(twin, "p1", dense=True)
        assert len(calls) == 1 and rendered.dense is not None and not rendered.exported
        assert export_references(twin, ["p1"], workers=1).ok
        calls.clear()
        read = refmod.reference_for(twin, "p1")
        assert not calls and read.exported and read.depth is None
        assert len(read.cloud) == len(rendered.cloud)
        assert read.cut is not None and abs(read.cut[2] - twin.pose("p1").standoff) < 1e-9
    finally:
        refmod.render_reference = real  # type: ignore[assignment]
    ply = twin.references_dir / "p1.ply"
    ply.write_bytes(ply.read_bytes()[:-12])
    with pytest.raises(InputError, match="does not match the hash"):
        refmod.reference_for(twin, "p1")


def test_an_exported_reference_of_a_moved_pose_is_refused(tmp_path: Path) -> None:
    """A reference exported before the pose moved (or the twin's settings changed) is the view
    of where the pose was: the servo would go there. `reference_for` refuses it, naming why,
    until the export is run again."""
    from dataclasses import replace

    from vinetwin.errors import InputError
    from vinetwin.frames import make_pose
    from vinetwin.render.export import export_references
    from vinetwin.render.reference import reference_for
    from vinetwin.twin.model import Twin

    root = _sample_copy(tmp_path)
    twin = Twin.load(root)
    assert export_references(twin, ["p1", "p2"], workers=1).ok
    assert reference_for(twin, "p1").exported
    twin.set_pose("p1", twin.pose("p1").T_vine_camera @ make_pose(t=[0.0, 0.002, 0.0]))
    twin.save()
    twin = Twin.load(root)
    with pytest.raises(InputError, match="pose p1 moved since its reference was exported"):
        reference_for(twin, "p1")
    assert reference_for(twin, "p2").exported  # the others are still current
    twin.perception = replace(twin.perception, voxel_size=0.003)
    twin.save()
    with pytest.raises(InputError, match="perception settings changed"):
        reference_for(Twin.load(root), "p2")
    assert export_references(Twin.load(root), ["p1", "p2"], workers=1).ok
    assert reference_for(Twin.load(root), "p1").exported
