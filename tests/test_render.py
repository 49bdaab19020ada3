"""Rendering backends, the D405 sensor model and reference export."""

from __future__ import annotations

import json
import shutil
from itertools import pairwise
from pathlib import Path

import numpy as np
import pytest
import trimesh

from tests.conftest import ROOT
from vinetwin import frames as fr
from vinetwin.camera import CameraModel, d405
from vinetwin.errors import BackendUnavailable, InputError, MeshError, TwinError
from vinetwin.render import reference as refmod
from vinetwin.render.backends import BACKENDS, get_backend, resolve_backend
from vinetwin.render.export import export_references
from vinetwin.render.sensor import SensorConfig, apply_d405_model
from vinetwin.twin import Twin


def _backend_or_skip(name: str, V, F, cam):  # type: ignore[no-untyped-def]
    try:
        return get_backend(name, V, F, cam)
    except BackendUnavailable as exc:  # never silently replaced: the test says why it skipped
        pytest.skip(str(exc))


@pytest.fixture(scope="module")
def sample(sample_twin_dir: Path) -> tuple[Twin, trimesh.Trimesh]:
    twin = Twin.load(sample_twin_dir)
    return twin, twin.load_mesh()


def test_the_backends_agree_on_the_sample(sample: tuple[Twin, trimesh.Trimesh]) -> None:
    twin, mesh = sample
    cam = d405("848x480")
    for pose in twin.poses[:3]:
        depths = {}
        for name in BACKENDS:
            b = _backend_or_skip(name, mesh.vertices, mesh.faces, cam)
            depths[name] = b.render(pose.T_vine_camera)
            b.close()
        valid = np.logical_and.reduce([d > 0 for d in depths.values()])
        assert valid.sum() > 10_000
        for name in ("pyrender", "mujoco", "raster"):
            diff = np.abs(depths[name][valid] - depths["open3d"][valid])
            assert diff.max() < 1e-3, f"{name} differs from open3d by {diff.max() * 1e3:.2f} mm"
            # silhouettes agree too: few pixels valid in one backend only
            assert ((depths[name] > 0) != (depths["open3d"] > 0)).sum() < 0.001 * valid.sum()


@pytest.mark.parametrize("name", BACKENDS)
def test_known_point_lands_on_expected_pixel(name: str) -> None:
    # an off-centre principal point and fx != fy pin each backend's intrinsics convention
    cam = CameraModel(width=320, height=240, fx=250.0, fy=270.0, cx=150.2, cy=131.7, min_depth=0.05)
    T_vine_camera = fr.look_at([0.1, -0.4, 0.2], [0.0, 0.0, 0.25])
    centre = np.array([0.04, 0.02, 0.22])
    ball = trimesh.creation.icosphere(subdivisions=4, radius=0.01)
    ball.apply_translation(centre)
    b = _backend_or_skip(name, ball.vertices, ball.faces, cam)
    depth = b.render(T_vine_camera)
    b.close()
    v, u = np.nonzero(depth > 0)
    uv, _ = cam.project(fr.transform_points(fr.invert(T_vine_camera), centre))
    np.testing.assert_allclose([u.mean(), v.mean()], uv[0], atol=0.35)
    # and the depth at that pixel is the near side of the ball
    z_expected = fr.transform_points(fr.invert(T_vine_camera), centre)[0, 2]
    assert depth[round(uv[0, 1]), round(uv[0, 0])] == pytest.approx(z_expected - 0.01, abs=3e-4)


def test_pyrender_teardown_leaves_mujoco_working() -> None:
    """pyrender's EGL teardown used to eglTerminate the display MuJoCo shares."""
    box = trimesh.creation.box(extents=[1, 1, 0.01])
    box.apply_translation([0, 0, 0.3])
    cam = d405("480x270")
    pr = _backend_or_skip("pyrender", box.vertices, box.faces, cam)
    pr.render(np.eye(4))
    pr.close()
    del pr
    mj = _backend_or_skip("mujoco", box.vertices, box.faces, cam)
    depth = mj.render(np.eye(4))
    mj.close()
    assert np.median(depth[depth > 0]) == pytest.approx(0.295, abs=1e-4)


@pytest.mark.parametrize("z", [0.07, 0.15, 0.30, 0.50])
@pytest.mark.parametrize("quantize", [False, True])
def test_noise_rms_on_a_flat_target(z: float, quantize: bool) -> None:
    cam = d405("640x480")  # minimum depth 55 mm, so 7 cm is inside the range
    depth = np.full((cam.height, cam.width), z, np.float32)
    noisy = apply_d405_model(depth, cam, np.random.default_rng(7), SensorConfig(quantize=quantize))
    valid = noisy > 0
    assert valid.mean() > 0.99  # a flat target has no silhouettes to lose
    rms = float(np.sqrt(np.mean((noisy[valid] - z) ** 2)))
    model = float(cam.depth_noise_rms(z))
    if quantize:  # rounding to 0.1 mm adds its own uniform error
        model = float(np.hypot(model, cam.depth_unit / np.sqrt(12)))
    assert rms == pytest.approx(model, rel=0.10)


def test_sensor_model_silhouettes_range_and_determinism() -> None:
    cam = d405("480x270")
    depth = np.zeros((cam.height, cam.width), np.float32)
    depth[:, :] = 0.40
    depth[:, 200:215] = 0.15  # a thin cane in front of a wall
    depth[:5, :] = 0.04  # too near for the sensor (45 mm at 480x270)
    a = apply_d405_model(depth, cam, np.random.default_rng(1))
    b = apply_d405_model(depth, cam, np.random.default_rng(1))
    np.testing.assert_array_equal(a, b)
    assert np.all(a[:3] == 0)  # below minimum depth (row 4 borders the wall: smeared)
    edge_cols = a[10:, [199, 200, 214, 215]]
    inner = a[10:, 203:212]
    assert (edge_cols == 0).mean() > 0.25  # silhouettes lose pixels
    assert (inner > 0).mean() > 0.99  # the cane's middle does not
    assert np.all(np.abs(np.round(a / cam.depth_unit) * cam.depth_unit - a) < 1e-7)  # quantised
    clean = apply_d405_model(depth, cam, np.random.default_rng(1), SensorConfig(enabled=False))
    np.testing.assert_array_equal(clean, depth)
    with pytest.raises(InputError, match="shape"):
        apply_d405_model(np.zeros((3, 3), np.float32), cam, np.random.default_rng(0))


@pytest.mark.parametrize("name", BACKENDS)
def test_bad_meshes_are_refused_by_every_backend(name: str) -> None:
    V = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0.0]])
    with pytest.raises(MeshError, match="non-finite"):
        get_backend(name, np.where(V == 1, np.nan, V), [[0, 1, 2]], d405())
    with pytest.raises(MeshError, match="no triangle faces"):
        get_backend(name, V, np.zeros((0, 3), int), d405())
    with pytest.raises(InputError, match="choose one of"):
        get_backend("blender", V, [[0, 1, 2]], d405())


@pytest.fixture
def twin_copy(sample_twin_dir: Path, tmp_path: Path) -> Twin:
    dst = tmp_path / sample_twin_dir.name
    shutil.copytree(sample_twin_dir, dst, ignore=shutil.ignore_patterns("references", "validation"))
    return Twin.load(dst)


def test_export_writes_loadable_files_and_resumes(twin_copy: Twin) -> None:
    import open3d as o3d

    ids = [p.id for p in twin_copy.poses[:3]]
    report = export_references(twin_copy, ids, workers=1)
    assert [r.status for r in report.results] == ["rendered"] * 3
    for pid in ids:
        ply, pcd, meta = (
            twin_copy.references_dir / f"{pid}.{ext}" for ext in ("ply", "pcd", "json")
        )
        info = json.loads(meta.read_text())
        n = info["points"]
        assert n > 100 and info["noise_seed"] == refmod.pose_seed(0, pid)
        assert info["backend"] == resolve_backend(None, 3)  # the one used, never "auto"
        pc = o3d.io.read_point_cloud(str(ply))
        assert len(pc.points) == n and pc.has_normals()
        pc2 = o3d.io.read_point_cloud(str(pcd))
        np.testing.assert_allclose(np.asarray(pc2.points), np.asarray(pc.points))
        tm = trimesh.load(ply)
        assert len(tm.vertices) == n
        header = pcd.read_bytes().split(b"DATA binary\n")[0].decode().splitlines()
        assert header[1:] == [
            "VERSION 0.7",
            "FIELDS x y z normal_x normal_y normal_z",
            "SIZE 4 4 4 4 4 4",
            "TYPE F F F F F F",
            "COUNT 1 1 1 1 1 1",
            f"WIDTH {n}",
            "HEIGHT 1",
            "VIEWPOINT 0 0 0 1 0 0 0",
            f"POINTS {n}",
        ]
        # the reference is in the reference camera frame: its points lie in front of the camera
        pts = np.asarray(pc.points)
        assert pts[:, 2].min() > twin_copy.camera.min_depth * 0.9
        assert pts[:, 2].max() <= twin_copy.perception.max_depth + 1e-6
    # unchanged inputs are skipped; a moved pose is re-rendered alone
    assert [r.status for r in export_references(twin_copy, ids, workers=1).results] == [
        "skipped"
    ] * 3
    cut = twin_copy.cut_point(twin_copy.pose(ids[1]).cut_point)
    twin_copy.move_cut_point(cut.id, cut.point + np.array([0.0, 0.0, 0.005]))
    statuses = [r.status for r in export_references(twin_copy, ids, workers=1).results]
    assert statuses == ["skipped", "rendered", "skipped"]


def test_export_isolates_a_failing_pose(twin_copy: Twin, monkeypatch: pytest.MonkeyPatch) -> None:
    import vinetwin.render.export as ex

    real = ex.render_reference

    def flaky(backend, T, perception, sensor, seed):  # type: ignore[no-untyped-def]
        if seed == refmod.pose_seed(0, "p2"):
            raise RuntimeError("GPU on fire")
        return real(backend, T, perception, sensor, seed)

    monkeypatch.setattr(ex, "render_reference", flaky)
    report = export_references(twin_copy, ["p1", "p2", "p3"], workers=1)
    assert [r.status for r in report.results] == ["rendered", "failed", "rendered"]
    assert "GPU on fire" in report.results[1].error
    assert not (twin_copy.references_dir / "p2.json").exists()


@pytest.mark.numpy_noise
def test_parallel_export_matches_serial(twin_copy: Twin, tmp_path: Path) -> None:
    other = Twin.load(shutil.copytree(twin_copy.root, tmp_path / "other.twin"))
    export_references(twin_copy, workers=1)
    report = export_references(other, workers=2)
    assert report.ok and report.count("rendered") == len(other.poses)
    for p in other.poses:
        a = (twin_copy.references_dir / f"{p.id}.ply").read_bytes()
        b = (other.references_dir / f"{p.id}.ply").read_bytes()
        assert a == b


def test_view_of_nothing_gives_empty_cloud_and_warning(
    twin_copy: Twin, caplog: pytest.LogCaptureFixture
) -> None:
    pose = twin_copy.poses[0]
    away = pose.T_vine_camera @ fr.make_pose(fr.so3_exp([0, np.pi, 0]))  # look the other way
    twin_copy.set_pose(pose.id, away)
    report = export_references(twin_copy, [pose.id], workers=1)
    r = report.results[0]
    assert r.status == "rendered" and r.points == 0 and "sees nothing" in r.warning
    assert "sees nothing" in caplog.text
    assert json.loads((twin_copy.references_dir / f"{pose.id}.json").read_text())["points"] == 0


def test_unknown_pose_and_backend(twin_copy: Twin) -> None:
    with pytest.raises(TwinError, match="no pruning pose 'p99'"):
        export_references(twin_copy, ["p99"])
    with pytest.raises(InputError, match="choose auto or one of"):
        export_references(twin_copy, backend="vtk")


@pytest.mark.parametrize(
    ("backend", "env", "needle"),
    [
        ("mujoco", {"MUJOCO_GL": "bogus"}, "MUJOCO_GL"),
        ("pyrender", {"PYOPENGL_PLATFORM": "bogus"}, "PYOPENGL_PLATFORM"),
    ],
)
def test_backend_that_cannot_start_says_why(backend: str, env: dict[str, str], needle: str) -> None:
    import os
    import subprocess
    import sys

    code = (
        "import numpy as np\n"
        "from vinetwin.camera import d405\n"
        "from vinetwin.errors import BackendUnavailable\n"
        "from vinetwin.render.backends import get_backend\n"
        "try:\n"
        f"    get_backend({backend!r}, np.eye(3), [[0, 1, 2]], d405())\n"
        "except BackendUnavailable as exc:\n"
        "    print('UNAVAILABLE', exc.backend, exc.reason)\n"
    )
    environ = {
        k: v
        for k, v in os.environ.items()
        if k not in ("MUJOCO_GL", "PYOPENGL_PLATFORM", "DISPLAY")
    }
    out = subprocess.run(
        [sys.executable, "-c", code], env=environ | env, capture_output=True, text=True, timeout=120
    )
    assert f"UNAVAILABLE {backend}" in out.stdout and needle in out.stdout, out.stderr[-1000:]


def test_auto_backend_by_batch_size_and_where_it_can_start(
    monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    """auto (or None) gives SINGLE_BACKEND below AUTO_MIN_VIEWS views, BATCH_BACKEND from there
    where it starts, else SINGLE_BACKEND with a warning that says why; a named backend is never
    replaced."""
    from vinetwin.render import backends
    from vinetwin.render.backends import AUTO_MIN_VIEWS, BATCH_BACKEND, SINGLE_BACKEND

    assert resolve_backend("pyrender", 10_000) == "pyrender"
    assert resolve_backend("auto", AUTO_MIN_VIEWS - 1) == SINGLE_BACKEND
    with pytest.raises(InputError, match="choose auto or one of"):
        resolve_backend("vtk")
    # the batch backend (vinetwin's raster) needs no OpenGL: it starts here, whatever MUJOCO_GL
    assert backends._cannot_start(BATCH_BACKEND) == ""
    assert resolve_backend(None, AUTO_MIN_VIEWS) == BATCH_BACKEND == "raster"
    assert resolve_backend("auto", 10 * AUTO_MIN_VIEWS) == BATCH_BACKEND
    # where it cannot start, the single backend renders, and the log says why
    monkeypatch.setattr(backends, "_cannot_start", lambda name: f"{name}: no numba here")
    with caplog.at_level("WARNING", logger="vinetwin.render.backends"):
        assert resolve_backend(None, AUTO_MIN_VIEWS) == SINGLE_BACKEND
        assert resolve_backend("mujoco") == "mujoco"  # named: never replaced
    assert f"rendering with {SINGLE_BACKEND}" in caplog.text and "no numba here" in caplog.text


def test_raster_backend_is_the_ray_casters_image(sample: tuple[Twin, trimesh.Trimesh]) -> None:
    """vinetwin's rasteriser against Open3D's exact ray casting (every pixel cast), on the
    sample's poses and views near them: the same pixels hit, the same depth to micrometres."""
    twin, mesh = sample
    cam = d405("848x480")
    raster = get_backend("raster", mesh.vertices, mesh.faces, cam)
    o3d = get_backend("open3d", mesh.vertices, mesh.faces, cam, coarse_step=1)
    rng = np.random.default_rng(3)
    poses = [p.T_vine_camera for p in twin.poses[:3]]
    poses += [T @ fr.random_pose(rng, 0.02, 0.2) for T in poses]
    for T in poses:
        a, b = raster.render(T), o3d.render(T)
        assert a.dtype == np.float32 and a.shape == (cam.height, cam.width)
        both = (a > 0) & (b > 0)
        assert both.sum() > 5_000
        assert ((a > 0) != (b > 0)).sum() <= 5  # a pixel centre on an edge may fall either way
        assert np.abs(a[both] - b[both]).max() < 2e-5  # 0.02 mm
        assert 0 < raster.drawn < raster.pieces  # the frustum left pieces out
    assert not np.array_equal(raster.render(poses[0]), raster.render(poses[1]))  # no stale buffer


def test_raster_backend_back_faces_and_the_near_plane() -> None:
    """A face seen from behind is drawn only with `two_sided` (as a ray caster sees it), which
    is the default unless the mesh is closed and outward-facing; a triangle reaching behind the
    camera is clipped at the near plane, its part in front drawn as the ray caster draws it."""
    cam = CameraModel(width=64, height=48, fx=50.0, fy=50.0, cx=31.5, cy=23.5, min_depth=0.01)
    T = np.eye(4)  # the camera at the origin looking along +z
    facing = np.array([[-0.1, -0.1, 0.3], [0.1, -0.1, 0.3], [0.0, 0.1, 0.3]])
    F = np.array([[0, 1, 2]])
    one = get_backend("raster", facing, F, cam, two_sided=False).render(T)
    other = get_backend("raster", facing, F[:, ::-1], cam, two_sided=False).render(T)
    both_sides = get_backend("raster", facing, F, cam).render(T)  # open: both sides by default
    o3d = get_backend("open3d", facing, F, cam, coarse_step=1).render(T)
    front, back = (one, other) if (one > 0).any() else (other, one)
    assert (front > 0).sum() > 100 and not (back > 0).any()
    np.testing.assert_allclose(both_sides, o3d, atol=1e-6)
    np.testing.assert_allclose(front, o3d, atol=1e-6)
    # by default, front faces alone only for a closed surface whose faces face outward
    ball = trimesh.creation.icosphere(subdivisions=3, radius=0.05)
    ball.apply_translation([0.0, 0.0, 0.3])
    open_ball = ball.faces[ball.triangles_center[:, 2] > 0.28]  # its near cap cut: inside shows
    for faces, culls in ((ball.faces, True), (ball.faces[:, ::-1], False), (open_ball, False)):
        r = get_backend("raster", ball.vertices, faces, cam)
        assert r.two_sided is not culls
        want = get_backend("open3d", ball.vertices, faces, cam, coarse_step=1).render(T)
        np.testing.assert_allclose(r.render(T), want, atol=1e-6)  # the ray caster's image
    # a floor plane from behind the camera to 1 m ahead: clipped, not dropped or wrapped
    floor = np.array([[-1.0, 0.05, -0.5], [1.0, 0.05, -0.5], [0.0, 0.05, 1.0]])
    for f in (F, F[:, ::-1]):
        got = get_backend("raster", floor, f, cam, two_sided=True).render(T)
        want = get_backend("open3d", floor, f, cam, coarse_step=1).render(T)
        assert (want > 0).sum() > 200
        assert ((got > 0) != (want > 0)).sum() <= 2
        ok = (got > 0) & (want > 0)
        np.testing.assert_allclose(got[ok], want[ok], rtol=1e-5)


def test_export_of_a_batch_uses_the_batch_backend(
    twin_copy: Twin, monkeypatch: pytest.MonkeyPatch
) -> None:
    from vinetwin.render import backends

    if backends._cannot_start(backends.BATCH_BACKEND):
        pytest.skip(backends._cannot_start(backends.BATCH_BACKEND))
    monkeypatch.setattr(backends, "AUTO_MIN_VIEWS", 2)
    ids = [p.id for p in twin_copy.poses[:2]]
    assert export_references(twin_copy, ids, workers=1).count("rendered") == 2
    for pid in ids:
        info = json.loads((twin_copy.references_dir / f"{pid}.json").read_text())
        assert info["backend"] == backends.BATCH_BACKEND and info["points"] > 100
    # one pose is under this batch size: open3d, a changed input, rendered again
    assert export_references(twin_copy, ids[:1], workers=1).count("rendered") == 1
    info = json.loads((twin_copy.references_dir / f"{ids[0]}.json").read_text())
    assert info["backend"] == backends.SINGLE_BACKEND


def test_scene_backend_for_several_threads_takes_mujoco_only_with_egl(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """A simulation that may render from several threads (the web app's validations) gets
    MuJoCo only where its context can move between threads (EGL); with a display and no
    MUJOCO_GL (MuJoCo's GLFW) or with OSMesa, Open3D."""
    from vinetwin.render import backends

    made: list[str] = []
    monkeypatch.setattr(backends, "resolve_backend", lambda name, views=1: "mujoco")
    monkeypatch.setattr(backends, "get_backend", lambda name, *a, **k: made.append(name))
    for env, display, want in (
        ("egl", "", "mujoco"),
        ("osmesa", "", "open3d"),
        (None, ":0", "open3d"),
        (None, "", "mujoco"),
    ):
        if env is None:
            monkeypatch.delenv("MUJOCO_GL", raising=False)
        else:
            monkeypatch.setenv("MUJOCO_GL", env)
        monkeypatch.setenv("DISPLAY", display)
        backends.scene_backend([], [], d405("848x480"), any_thread=True)
        assert made[-1] == want, (env, display)
    backends.scene_backend([], [], d405("848x480"))  # one thread: whatever resolve_backend says
    assert made[-1] == "mujoco"


def test_mujoco_survives_a_pyrender_renderer_deleted_directly() -> None:
    """pyrender's own `OffscreenRenderer.delete` terminates the EGL display the process shares;
    a MuJoCo backend made afterwards initialises it again instead of failing with
    EGL_NOT_INITIALIZED."""
    import os

    pyrender = pytest.importorskip("pyrender")
    if os.environ.get("MUJOCO_GL", "egl").lower() != "egl":
        pytest.skip("EGL only")
    box = trimesh.creation.box((0.1, 0.1, 0.1))
    box.apply_translation([0, 0, 0.3])
    cam = d405("848x480")
    _backend_or_skip("mujoco", box.vertices, box.faces, cam).close()  # the display is up
    r = pyrender.OffscreenRenderer(64, 48)
    r.delete()  # eglTerminate
    mj = get_backend("mujoco", box.vertices, box.faces, cam)
    assert (mj.render(np.eye(4)) > 0).sum() > 10_000
    mj.close()


def test_mujoco_renders_from_any_thread_one_at_a_time(
    sample: tuple[Twin, trimesh.Trimesh],
) -> None:
    """With EGL the renderer releases its context after each view: a server thread or a
    simulation's worker thread renders with a scene another thread built (the same image), two
    threads at once take turns, and another thread can close it. Elsewhere (OSMesa, GLFW)
    another thread gets a named error, not one from deep inside OpenGL."""
    import os
    import threading

    twin, mesh = sample
    mj = _backend_or_skip("mujoco", mesh.vertices, mesh.faces, twin.camera)
    T = [p.T_vine_camera for p in twin.poses[:4]]
    mine = [mj.render(t) for t in T]
    got: dict[int, list[np.ndarray]] = {}
    errors: list[Exception] = []

    def other(k: int) -> None:
        try:
            got[k] = [mj.render(t) for t in T]
        except Exception as exc:
            errors.append(exc)

    threads = [threading.Thread(target=other, args=(k,)) for k in range(2)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    if os.environ.get("MUJOCO_GL", "egl").lower() != "egl":
        assert len(errors) == 2 and isinstance(errors[0], BackendUnavailable)
        assert "thread that created it" in str(errors[0])
        mj.close()
        return
    assert not errors, errors
    for k in range(2):
        for a, b in zip(mine, got[k], strict=True):
            np.testing.assert_array_equal(a, b)
    assert (mj.render(T[0]) > 0).sum() > 10_000  # still renders in its own
    closer = threading.Thread(target=mj.close)
    closer.start()
    closer.join()


def test_mujoco_renders_a_mesh_beyond_its_stl_limit() -> None:
    """MuJoCo reads at most 200k faces from one STL file: a bigger vine goes in as pieces, and
    renders as Open3D does."""
    from vinetwin.render.backends.mujoco_gl import MUJOCO_STL_FACES

    ball = trimesh.creation.icosphere(subdivisions=7, radius=0.05)  # 327,680 faces
    assert len(ball.faces) > MUJOCO_STL_FACES
    ball.apply_translation([0.01, -0.005, 0.25])
    cam = d405("848x480")
    mj = _backend_or_skip("mujoco", ball.vertices, ball.faces, cam)
    o3 = get_backend("open3d", ball.vertices, ball.faces, cam, coarse_step=1)
    a, b = mj.render(np.eye(4)), o3.render(np.eye(4))
    mj.close()
    both = (a > 0) & (b > 0)
    assert both.sum() > 20_000  # a 10 cm ball at 25 cm; a missing part would show below
    assert np.abs(a[both] - b[both]).max() < 1e-3
    assert ((a > 0) != (b > 0)).sum() < 0.01 * both.sum()


def test_frustum_test_keeps_what_shows_and_drops_what_cannot() -> None:
    """Boxes wholly behind one side of the view are dropped; every box holding a point that
    projects into the image (or lies within the margin of it) is kept."""
    from vinetwin.render.backends._pieces import frustum_hits

    cam = d405("848x480")

    def box(centre, half=0.01):  # type: ignore[no-untyped-def]
        pick = np.array([[(k >> a) & 1 for a in range(3)] for k in range(8)])
        return np.asarray(centre) + (2 * pick - 1) * half

    cases = {  # camera at the origin looking along +z (OpenCV)
        (0.0, 0.0, 0.3): 1,  # straight ahead
        (0.0, 0.0, -0.3): 0,  # behind
        (0.0, 0.0, 0.0): 1,  # around the camera: straddles the near plane
        (1.0, 0.0, 0.3): 0,  # far right, beyond the image
        (-1.0, 0.0, 0.3): 0,
        (0.0, 1.0, 0.3): 0,
        (0.0, -1.0, 0.3): 0,
        (0.0, 0.0, 5.0): 1,  # far but in view (depth is not culled)
    }
    got = frustum_hits(np.stack([box(c) for c in cases]), np.eye(4), cam, 2.0)
    assert got.tolist() == list(cases.values())
    # random poses and points: a box around any point projecting into the image is kept
    rng = np.random.default_rng(3)
    for _ in range(20):
        T = fr.random_pose(rng, 0.5, np.pi)
        P = rng.uniform(-0.6, 0.6, (400, 3))
        Pc = (P - T[:3, 3]) @ T[:3, :3]
        u = cam.fx * Pc[:, 0] / Pc[:, 2] + cam.cx
        v = cam.fy * Pc[:, 1] / Pc[:, 2] + cam.cy
        shows = (
            (Pc[:, 2] > 0.005)
            & (u > -0.5)
            & (u < cam.width - 0.5)
            & (v > -0.5)
            & (v < cam.height - 0.5)
        )
        hit = frustum_hits(np.stack([box(p, 0.002) for p in P]), T, cam, 2.0)
        assert np.all(hit[shows] == 1)
        assert hit[~shows].sum() < len(P)  # something is dropped


def test_mujoco_culling_fused_readback_and_own_draw_leave_the_image_unchanged(
    sample: tuple[Twin, trimesh.Trimesh], monkeypatch: pytest.MonkeyPatch
) -> None:
    """The MuJoCo backend draws only the vine pieces in the frustum and converts the depth
    buffer in one compiled pass. With MuJoCo drawing the vine's geoms (`own_draw=False`), the
    images are those of drawing every piece through `mujoco.Renderer.render`, to the bit, on
    views around the sample's poses (and the views do leave pieces out). Drawn from our own
    buffers, flushed piece by piece (the default, the vine then out of MuJoCo's model), the
    images are the same within 0.1 mm but for at most 3 pixels a view where a triangle edge's
    tie falls the other way (float32 vertices that MuJoCo re-centres per piece)."""
    from vinetwin.render import backends

    twin, mesh = sample
    own = _backend_or_skip("mujoco", mesh.vertices, mesh.faces, twin.camera)
    assert own._fused is not None, "this MuJoCo's renderer should take the fused readback"
    assert own._vine is not None, "this MuJoCo's renderer should draw the vine from our buffers"
    assert own.model.ngeom == 0 and own.model.nmesh == 0  # the vine is not compiled into MuJoCo
    mj = backends.MujocoBackend(mesh.vertices, mesh.faces, twin.camera, own_draw=False)
    assert mj._vine is None and len(mj._geoms) == mj.pieces >= 8
    rng = np.random.default_rng(0)
    poses = [p.T_vine_camera @ fr.random_pose(rng, 0.02, 0.1) for p in twin.poses for _ in range(2)]
    ours, culled, drawn = [], [], []
    for T in poses:
        ours.append(own.render(T))
        culled.append(mj.render(T))
        drawn.append(mj.drawn)
        assert own.drawn == mj.drawn
    mj._fused = None
    monkeypatch.setattr(backends.mujoco_gl, "frustum_hits", lambda c, *a: np.ones(len(c)))
    for T, a, c in zip(poses, culled, ours, strict=True):
        b = mj.render(T)
        assert (b > 0).sum() > 10_000
        np.testing.assert_array_equal(a, b)
        both = (b > 0) & (c > 0)
        off = np.abs(c - b)[both] > 1e-4
        assert off.sum() <= 3 and ((b > 0) != (c > 0)).sum() <= 3
        assert np.abs(c - b)[both][~off].max() < 1e-4
    own.close()
    mj.close()
    assert max(drawn) < mj.pieces


def test_mujoco_draws_the_vine_itself_where_our_buffers_cannot_be_made(
    sample: tuple[Twin, trimesh.Trimesh], monkeypatch: pytest.MonkeyPatch
) -> None:
    """Where PyOpenGL cannot make the vine's buffers in MuJoCo's context, the backend compiles the
    vine into MuJoCo's model and renders what `own_draw=False` renders, to the bit."""
    from vinetwin.render import backends

    if backends._cannot_start("mujoco"):
        pytest.skip(backends._cannot_start("mujoco"))
    twin, mesh = sample
    monkeypatch.setattr(
        backends.mujoco_gl._VineBuffers, "create", classmethod(lambda cls, *a: None)
    )
    fallback = backends.MujocoBackend(mesh.vertices, mesh.faces, twin.camera)
    assert fallback._vine is None and len(fallback._geoms) == fallback.pieces
    mj = backends.MujocoBackend(mesh.vertices, mesh.faces, twin.camera, own_draw=False)
    for pose in twin.poses[:2]:
        np.testing.assert_array_equal(
            fallback.render(pose.T_vine_camera), mj.render(pose.T_vine_camera)
        )
    fallback.close()
    mj.close()


def test_stl_bytes_round_trip() -> None:
    from vinetwin.render.backends.mujoco_gl import stl_bytes

    ball = trimesh.creation.icosphere(subdivisions=2, radius=0.1)
    import io

    back = trimesh.load(
        io.BytesIO(stl_bytes(ball.vertices, ball.faces)), file_type="stl", process=False
    )
    np.testing.assert_allclose(back.triangles, ball.triangles.astype(np.float32), atol=1e-7)
    np.testing.assert_allclose(back.face_normals, ball.face_normals, atol=1e-5)


def _d405_numpy(
    depth: np.ndarray, camera: CameraModel, rng: np.random.Generator, cfg: SensorConfig
) -> np.ndarray:
    """The D405 model written with numpy, step by step (the formulation the compiled kernels
    replaced; window extremes from scipy's filters): the reference they must reproduce
    exactly."""
    from scipy import ndimage

    d = np.array(depth, dtype=np.float32, copy=True)
    d[~np.isfinite(d) | (d < 0)] = 0.0
    valid = d > 0
    rows, cols = np.nonzero(valid.any(1))[0], np.nonzero(valid.any(0))[0]
    m = cfg.edge_width + 1
    box = (
        slice(max(rows[0] - m, 0), rows[-1] + m + 1),
        slice(max(cols[0] - m, 0), cols[-1] + m + 1),
    )
    full = d
    d = d[box].copy()
    size = 2 * cfg.edge_width + 1  # the window, clipped at the border
    valid_d = d > 0
    near = ndimage.minimum_filter(np.where(valid_d, d, np.inf), size, mode="constant", cval=np.inf)
    far = ndimage.maximum_filter(np.where(valid_d, d, 0), size, mode="constant", cval=0)
    holes = ndimage.maximum_filter(~valid_d, size, mode="constant", cval=False)
    near_ok = np.isfinite(near)
    big_jump = (far - near) > cfg.edge_jump * np.where(near_ok, near, 1.0)
    ev, eu = np.nonzero(near_ok & (big_jump | holes))
    dv, nv, fv = d[ev, eu], near[ev, eu], far[ev, eu]
    u1 = rng.random(len(ev), dtype=np.float32)
    u2 = rng.random(len(ev), dtype=np.float32)
    u3 = rng.random(len(ev), dtype=np.float32)
    on = dv > 0
    fatten = ((~on) | (dv > nv * (1 + cfg.edge_jump))) & (u1 < cfg.edge_fatten)
    invalid = ~fatten & (u2 < cfg.edge_invalid)
    smear = (
        ~fatten & ~invalid & on & (u2 < cfg.edge_invalid + (1 - cfg.edge_invalid) * cfg.edge_smear)
    )
    new = dv.copy()
    new[fatten] = nv[fatten]
    hi = np.where(fv > 0, fv, nv)
    new[smear] = nv[smear] + u3[smear] * (hi[smear] - nv[smear])
    new[invalid] = 0.0
    d[ev, eu] = new
    vv, vu = np.nonzero(d > 0)
    z = d[vv, vu].astype(np.float64)
    if cfg.bias:
        z *= 1.0 + cfg.bias
    if cfg.noise:
        sub = camera.subpixel if cfg.subpixel is None else cfg.subpixel
        z += rng.standard_normal(len(z)) * (z * z * sub / (camera.fx * camera.baseline))
    if cfg.dropout > 0:
        z[rng.random(len(z)) < cfg.dropout] = 0.0
    z[(z < camera.min_depth) | (z > camera.max_depth)] = 0.0
    if cfg.quantize:
        z = np.round(z / camera.depth_unit) * camera.depth_unit
    d[vv, vu] = z
    full[box] = d
    return full


@pytest.mark.numpy_noise
@pytest.mark.parametrize(
    "cfg",
    [
        SensorConfig(),
        SensorConfig(dropout=0.1, bias=0.004, edge_width=2),
        SensorConfig(quantize=False, noise=False, edge_fatten=0.0),
    ],
)
def test_compiled_d405_model_reproduces_the_numpy_formulation(
    cfg: SensorConfig, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The compiled D405 model gives, bit for bit, what its numpy formulation gives from the
    same generator state, on a rendered view of the sample (silhouettes, range, holes), in one
    band of rows and in three run on threads (`vinetwin._bands`)."""
    from vinetwin import _bands
    from vinetwin.render import sensor
    from vinetwin.twin import Twin

    twin = Twin.load(ROOT / "samples" / "vine_bilateral.twin")
    mesh = twin.load_mesh()
    backend = get_backend("open3d", mesh.vertices, mesh.faces, twin.camera)
    monkeypatch.setattr(sensor, "_MIN_BAND_PIXELS", 1000)
    for pose in twin.poses[:3]:
        clean = backend.render(pose.T_vine_camera)
        clean[100:110, 200:260] = np.nan  # holes that are NaN rather than 0
        clean[300:302, 10:20] = -0.2  # and negative
        ref = _d405_numpy(clean, twin.camera, np.random.default_rng(5), cfg)
        for threads in (1, 3):
            monkeypatch.setattr(_bands, "threads", lambda n=threads: n)
            ours = apply_d405_model(clean, twin.camera, np.random.default_rng(5), cfg)
            assert np.array_equal(ours, ref)
        assert (ref > 0).sum() > 1000


@pytest.mark.numpy_noise
def test_compiled_normal_draws_are_numpys() -> None:
    """The D405 model's normal draws, made in compiled code, are numpy's `standard_normal`'s to
    the bit and leave the generator where numpy leaves it (the next draws agree too)."""
    from vinetwin.render import _sensor_kernels

    for seed, n in ((0, 1), (5, 1000), (7, 140_000)):
        a, b = np.random.default_rng(seed), np.random.default_rng(seed)
        np.testing.assert_array_equal(_sensor_kernels.standard_normals(a, n), b.standard_normal(n))
        np.testing.assert_array_equal(a.random(7), b.random(7))


@pytest.mark.parametrize(("shape", "w"), [((37, 53), 1), ((40, 31), 2), ((25, 1), 1), ((1, 30), 3)])
def test_silhouette_search_matches_scipy_window_filters(shape: tuple[int, int], w: int) -> None:
    """`_sensor_kernels.d405_edges` (separable vectorised window extremes) finds the pixels, nearest
    and farthest depths that scipy's clipped window filters give, on random depth with holes,
    jumps and images one pixel wide."""
    from scipy import ndimage

    from vinetwin.render import _sensor_kernels

    rng = np.random.default_rng(sum(shape) + w)
    d = rng.uniform(0.1, 0.3, shape).astype(np.float32)
    d[rng.random(shape) < 0.3] = 0.0
    d[rng.random(shape) < 0.1] *= 1.5
    ev, eu, nv, fv = _sensor_kernels.d405_edges(d, w, np.float32(0.05))
    size = 2 * w + 1
    near = ndimage.minimum_filter(np.where(d > 0, d, np.inf), size, mode="constant", cval=np.inf)
    far = ndimage.maximum_filter(d, size, mode="constant", cval=0)
    holes = ndimage.maximum_filter(d <= 0, size, mode="constant", cval=False)
    ok = np.isfinite(near)
    rv, ru = np.nonzero(ok & (holes | ((far - near) > np.float32(0.05) * np.where(ok, near, 1))))
    assert len(rv) > 0
    np.testing.assert_array_equal(ev, rv)
    np.testing.assert_array_equal(eu, ru)
    np.testing.assert_array_equal(nv, near[rv, ru])
    np.testing.assert_array_equal(fv, far[rv, ru])
    # in bands of rows (each reads w rows beyond its own), joined in order: the same pixels
    for split in ((0, shape[0] // 3, shape[0]), (0, 1, shape[0] // 2, shape[0])):
        cuts = sorted(set(split))  # the one-row image: a single band
        bands = [
            _sensor_kernels.d405_edges_rows(d, w, np.float32(0.05), a, b) for a, b in pairwise(cuts)
        ]
        for k, want in enumerate((ev, eu, nv, fv)):
            np.testing.assert_array_equal(np.concatenate([b[k] for b in bands]), want)
