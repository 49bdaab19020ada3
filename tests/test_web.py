"""The authoring app: its logic without a browser, and end to end in headless Chromium."""

from __future__ import annotations

import json
import math
import shutil
import socket
import tempfile
import time
import warnings
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from vinetwin import frames as fr
from vinetwin.twin import Twin
from vinetwin.twin.poses import Approach
from vinetwin.web.browser import CHROMIUM, launch
from vinetwin.web.session import AuthoringSession


@pytest.fixture
def twin_dir(sample_twin_dir: Path, tmp_path: Path) -> Path:
    root = tmp_path / "edit.twin"
    shutil.copytree(sample_twin_dir, root)
    return root


def ray_at(twin: Twin, pose_index: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A ray from a pose's camera through its cut point (which lies on a cane)."""
    pose = twin.poses[pose_index]
    cut = twin.cut_point(pose.cut_point).point
    origin = np.asarray(pose.T_vine_camera)[:3, 3]
    return origin, cut - origin, cut


def test_click_places_a_cut_point_and_its_pose(twin_dir: Path) -> None:
    sess = AuthoringSession(twin_dir)
    origin, direction, cut = ray_at(sess._require())
    hit = sess.click(origin, direction)
    assert hit is not None
    c, p = hit
    # the hit is on the cane's surface, a cane radius (3-6 mm) short of its axis
    assert 0.002 < np.linalg.norm(c.point - cut) < 0.008
    T = p.T_vine_camera
    assert np.linalg.norm(T[:3, 3] - c.point) == pytest.approx(0.15, abs=1e-9)
    # optical axis through the cut, perpendicular to the cane
    z = T[:3, 2]
    assert np.linalg.norm(np.cross(z, c.point - T[:3, 3])) < 1e-9
    assert abs(float(z @ c.cane_axis)) < 1e-9
    # saved at once, and nothing but twin.json changed in the folder
    saved = Twin.load(twin_dir)
    assert saved.cut_point(c.id).extra == {} and saved.pose(p.id).cut_point == c.id
    assert sess.click(origin, -direction) is None or True  # a ray away from the vine may miss
    assert sess.pick(origin + np.array([0, 0, 10.0]), np.array([0, 0, 1.0])) is None


def test_adjust_snap_undo_redo_delete(twin_dir: Path) -> None:
    sess = AuthoringSession(twin_dir)
    twin = sess._require()
    pid = twin.poses[0].id
    before = np.asarray(twin.pose(pid).T_vine_camera).copy()
    sess.set_approach(pid, Approach(standoff=0.2, azimuth=0.3, elevation=0.1, roll=0.2))
    moved = sess._require().pose(pid)
    cut = sess._require().cut_point(moved.cut_point).point
    assert np.linalg.norm(moved.T_vine_camera[:3, 3] - cut) == pytest.approx(0.2)
    # a gizmo turn away from the cut, then snap the axis back on it
    sess.set_transform(pid, moved.T_vine_camera @ fr.make_pose(fr.so3_exp([0.1, 0.05, 0.0])))
    snapped = sess.snap(pid)
    z, pos = snapped.T_vine_camera[:3, 2], snapped.T_vine_camera[:3, 3]
    assert np.linalg.norm(np.cross(z, cut - pos)) < 1e-9
    sess.rename(pid, "first spur")
    sess.set_variant(pid, "symmetric")
    assert Twin.load(twin_dir).pose(pid).name == "first spur"
    for _ in range(5):
        assert sess.undo()
    np.testing.assert_allclose(sess._require().pose(pid).T_vine_camera, before, atol=1e-12)
    assert Twin.load(twin_dir).pose(pid).icp_variant == "point_to_plane"  # the undo was saved
    assert sess.redo() and sess.redo()
    n = len(sess._require().poses)
    sess.delete_pose(pid)
    assert len(Twin.load(twin_dir).poses) == n - 1


def test_unwritable_and_invalid_twins_are_reported(
    twin_dir: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    import vinetwin.twin.store as store

    sess = AuthoringSession(twin_dir)

    def refuse(path: Path, text: str) -> None:
        raise PermissionError(13, "Permission denied", str(path))

    monkeypatch.setattr(store, "atomic_write_text", refuse)
    origin, direction, _ = ray_at(sess._require())
    assert sess.click(origin, direction) is not None  # the edit stays in the page
    assert "not saved" in sess.problem and "Permission denied" in sess.problem
    monkeypatch.undo()
    assert sess.save() and sess.problem == ""
    (twin_dir / "twin.json").write_text("{ not json")
    broken = AuthoringSession(twin_dir)
    assert broken.twin is None and "twin.json" in broken.problem


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def in_browser(
    twin_dir: Path, body: Callable[[Any, Any, int], None], deadline_s: float = 240
) -> None:
    """Serves `twin_dir` and runs `body(page, app, port)` on the app's page in headless Chromium.

    Chromium's software renderer has been seen to spin for 20 minutes in a run of the whole
    suite (never alone): `launch` kills a browser at its deadline, and then the body gets one
    more try, on the twin as it was before the first (with a warning, so that CI's log shows
    it). Any other failure is the test's."""
    from playwright.sync_api import sync_playwright

    from vinetwin.web import browser
    from vinetwin.web.server import serve

    before = Path(tempfile.mkdtemp()) / twin_dir.name
    shutil.copytree(twin_dir, before)
    try:
        for attempt in (1, 2):
            kills = browser.kills
            port = _free_port()
            app = serve(twin_dir, port=port)
            try:
                with sync_playwright() as pw, tempfile.TemporaryDirectory() as profile:
                    ctx = launch(pw, profile, deadline_s=deadline_s)
                    try:
                        body(ctx.new_page(), app, port)
                    finally:
                        ctx.close()
                return
            except Exception:
                if browser.kills == kills or attempt == 2:
                    raise
                warnings.warn("Chromium was killed at its deadline: trying once more", stacklevel=1)
                shutil.rmtree(twin_dir)
                shutil.copytree(before, twin_dir)
            finally:
                app.close()
    finally:
        shutil.rmtree(before.parent, ignore_errors=True)


def test_a_folder_that_is_not_a_twin_is_refused_before_serving(tmp_path: Path) -> None:
    """`vinetwin web PATH`: a path with no twin.json (a typo) is refused by name, with what
    makes a twin, before any server starts (it served an empty page)."""
    from vinetwin.errors import InputError
    from vinetwin.web.server import serve_folder

    (tmp_path / "empty").mkdir()
    for path in (tmp_path / "nope", tmp_path / "empty"):
        with pytest.raises(InputError, match=r"no twin\.json here.*import-scan"):
            serve_folder(path, port=1)  # port 1 would be refused too: never reached


def test_page_sends_only_what_changed(twin_dir: Path) -> None:
    """After a click the app sends the new cut point and pose; the pose that was selected is
    recoloured in place and the other nodes stay as they were sent. A deleted pose leaves the
    page, undo brings it back. The gizmo and the preview's point cloud are moved and refilled,
    never sent again (the page would compile their shaders again), and the preview's shader
    keeper stays."""
    from vinetwin.web.server import serve

    app = serve(twin_dir, port=_free_port())
    try:
        sess = app.session
        twin = sess._require()
        assert set(app._pose_nodes) == {p.id for p in twin.poses}
        assert set(app._cut_nodes) == {c.id for c in twin.cut_points}
        sent = {pid: node[1] for pid, node in app._pose_nodes.items()}
        cuts = {cid: node[1] for cid, node in app._cut_nodes.items()}
        app.refresh()  # nothing changed: nothing is sent again
        assert all(app._pose_nodes[pid][1] is h for pid, h in sent.items())
        keeper = app._shader_keeper
        gizmos, previews = [], []
        for _ in range(2):
            was = sess.selected
            origin, direction, _ = ray_at(twin)
            hit = sess.click(origin, direction)
            assert hit is not None
            c, p = hit
            app.refresh()
            app._show_preview(p.id)
            assert sess.selected == p.id and app._pose_nodes[p.id][1].color == (255, 120, 0)
            assert c.id in app._cut_nodes
            assert all(app._pose_nodes[pid][1] is h for pid, h in sent.items())  # none re-sent
            if was:
                assert app._pose_nodes[was][1].color == (40, 40, 200)
                assert (app._pose_nodes[was][2].colors == (40, 40, 200)).all()
            assert all(app._cut_nodes[cid][1] is h for cid, h in cuts.items())
            assert app.gizmo is not None and app._gizmo_key is not None
            assert app._gizmo_key[0] == p.id
            T = np.asarray(p.T_vine_camera)
            assert np.allclose(app.gizmo.position, T[:3, 3], atol=1e-6)
            gizmos.append(app.gizmo)
            previews.append(app._preview)
            sent = {pid: node[1] for pid, node in app._pose_nodes.items()}
        assert gizmos[0] is gizmos[1] and previews[0] is previews[1] is not None
        assert app._preview.visible and len(app._preview.points) > 0
        assert app._shader_keeper is keeper
        last = sess.selected
        assert last is not None
        sess.delete_pose(last)
        app.refresh()
        assert last not in app._pose_nodes
        assert set(app._pose_nodes) == {q.id for q in sess._require().poses}
        sess.undo()
        app.refresh()
        assert last in app._pose_nodes
    finally:
        app.close()  # waits for the warm-up: stopping the server alone left it to update the
        # panel of a stopped server (viser's warning, seen in the next test)


def test_page_draws_the_vine_within_its_triangle_budget(
    twin_dir: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A vine with more triangles than `WebConfig.display_faces` is drawn decimated to the
    budget, its surface within 1 mm of the full mesh; clicks still hit the full mesh. A larger
    mesh (here: over a lowered threshold) is drawn clustered at once, then decimated in the
    background. Budget 0 draws every triangle; a budget under 1000 is refused by name."""
    import open3d as o3d

    from vinetwin.errors import InputError
    from vinetwin.web import app as web_app
    from vinetwin.web.config import WebConfig
    from vinetwin.web.display import quick_display_mesh
    from vinetwin.web.server import serve

    def off_surface(app: web_app.App) -> np.ndarray:
        """Distances of the drawn mesh's vertices to the full mesh."""
        assert app.vine_mesh is not None
        scene = o3d.t.geometry.RaycastingScene()
        sess = app.session
        scene.add_triangles(sess.vertices.astype(np.float32), sess.faces.astype(np.uint32))
        return scene.compute_distance(app.vine_mesh[0].astype(np.float32)).numpy()

    app = serve(twin_dir, port=_free_port(), config=WebConfig(display_faces=20_000))
    try:
        assert app.wait_ready()
        assert app.vine_display == "decimated" and 19_000 <= app.vine_faces <= 20_000
        assert len(app.session.faces) > 100_000  # the session keeps the full mesh
        assert np.percentile(off_surface(app), 99) < 0.001
        origin, direction, cut = ray_at(app.session._require())
        hit = app.session.click(origin, direction)
        assert hit is not None and np.linalg.norm(hit[0].point - cut) < 0.008
    finally:
        app.close()

    monkeypatch.setattr(web_app, "SYNC_DECIMATION_FACES", 1000)
    app = serve(twin_dir, port=_free_port(), config=WebConfig(display_faces=20_000))
    try:
        first = app.vine_display
        assert app.wait_ready()
        assert first in ("clustered", "decimated")  # the background may already have finished
        assert app.vine_display == "decimated" and app.vine_faces <= 20_000
    finally:
        app.close()

    app = serve(twin_dir, port=_free_port(), config=WebConfig(display_faces=0))
    try:
        assert app.vine_display == "full" and app.vine_faces == len(app.session.faces)
    finally:
        app.close()

    V, F = app.session.vertices, app.session.faces
    qv, qf = quick_display_mesh(V, F, 5000)
    assert 0 < len(qf) <= 5000 and qf.max() < len(qv)
    with pytest.raises(InputError, match="display_faces"):
        WebConfig(display_faces=10)


def test_status_says_while_the_preview_warms_up(
    twin_dir: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """While the start's warm-up runs (after an install: numba compiles the kernels, tens of
    seconds), the status line says that the camera preview is being prepared and that a click
    waits; once it is done, it no longer says so."""
    import threading

    from vinetwin.web.server import serve
    from vinetwin.web.session import AuthoringSession

    release = threading.Event()
    preview = AuthoringSession.preview

    def slow_preview(self: AuthoringSession, pose_id: str) -> object:
        release.wait(30)
        return preview(self, pose_id)

    monkeypatch.setattr(AuthoringSession, "preview", slow_preview)
    app = serve(twin_dir, port=_free_port())
    try:
        for _ in range(200):  # the warm-up thread takes the lock and says so
            if "Preparing the camera preview" in app.status.content:
                break
            threading.Event().wait(0.05)
        assert "Preparing the camera preview" in app.status.content
        assert "a click waits" in app.status.content
        release.set()
        assert app.wait_ready()
        assert "Preparing" not in app.status.content
        assert "cut points" in app.status.content
    finally:
        release.set()
        app.close()


def test_shading_setting_reaches_the_page(twin_dir: Path) -> None:
    """`WebConfig.shading`: "fast" draws the vine toon-shaded without shadows, "full" physically
    based with shadows; anything else is refused by name."""
    from vinetwin.errors import InputError
    from vinetwin.web.config import Shading, WebConfig
    from vinetwin.web.server import serve

    shadings: tuple[tuple[Shading, str, bool], ...] = (
        ("fast", "toon3", False),
        ("full", "standard", True),
    )
    for shading, material, shadow in shadings:
        app = serve(twin_dir, port=_free_port(), config=WebConfig(shading=shading))
        try:
            assert app.vine.material == material
            assert app.vine.cast_shadow is shadow and app.vine.receive_shadow is shadow
        finally:
            app.close()
    with pytest.raises(InputError, match="shading"):
        WebConfig(shading="pretty")  # type: ignore[arg-type]


@pytest.mark.skipif(not CHROMIUM.exists(), reason="Debian's chromium is not installed")
def test_browser_draws_webgl_as_asked() -> None:
    """`launch(gl=...)`: Chromium's SwiftShader by default, the machine's Mesa llvmpipe through
    EGL when asked (what `benchmarks/web.py --gl llvmpipe` measures), as the page reports; an
    unknown choice is refused by name."""
    import ctypes.util

    from playwright.sync_api import sync_playwright

    from vinetwin.web.browser import RENDERER_JS

    wanted = {"swiftshader": "SwiftShader"}
    if ctypes.util.find_library("EGL"):
        wanted["llvmpipe"] = "llvmpipe"
    with sync_playwright() as pw:
        for gl, name in wanted.items():
            with tempfile.TemporaryDirectory() as profile:
                ctx = launch(pw, profile, gl)  # type: ignore[arg-type]
                try:
                    page = ctx.new_page()
                    page.set_content("<html><body></body></html>")
                    assert name in page.evaluate(RENDERER_JS)
                finally:
                    ctx.close()
        with pytest.raises(ValueError, match="gl must be one of"):
            launch(pw, "/nonexistent", "metal")  # type: ignore[arg-type]


@pytest.mark.skipif(not CHROMIUM.exists(), reason="Debian's chromium is not installed")
def test_a_browser_past_its_deadline_is_killed() -> None:
    """`launch(deadline_s=...)`: a browser still open at its deadline is killed, so that what
    waits on it fails instead of hanging; a closed one's deadline is cancelled."""
    from playwright.sync_api import Error, sync_playwright

    from vinetwin.web.browser import _chromium_descendants

    with sync_playwright() as pw:
        with tempfile.TemporaryDirectory() as profile:
            ctx = launch(pw, profile, deadline_s=2)
            assert _chromium_descendants()
            ctx.close()
        with tempfile.TemporaryDirectory() as profile:
            ctx = launch(pw, profile, deadline_s=60)
            page = ctx.new_page()
            time.sleep(3)  # past the closed browser's deadline
            assert page.evaluate("() => 1 + 1") == 2
            ctx.close()
        with tempfile.TemporaryDirectory() as profile:
            ctx = launch(pw, profile, deadline_s=3)
            page = ctx.new_page()
            page.set_content("<html><body></body></html>")
            with pytest.raises(Error):
                page.wait_for_function("() => false", timeout=30_000)
            assert not _chromium_descendants()


@pytest.mark.skipif(not CHROMIUM.exists(), reason="Debian's chromium is not installed")
def test_a_browser_killed_at_its_deadline_gets_one_more_try(twin_dir: Path) -> None:
    """`in_browser`: a body whose browser was killed runs once more, on the twin as it was; a
    body that fails for any other reason fails at once."""
    calls: list[int] = []

    def hangs_once(page: Any, app: Any, port: int) -> None:
        calls.append(port)
        assert not (twin_dir / "touched").exists()
        if len(calls) == 1:
            (twin_dir / "touched").write_text("first try")
            page.wait_for_function("() => false", timeout=60_000)

    with pytest.warns(UserWarning, match="killed at its deadline"):
        in_browser(twin_dir, hangs_once, deadline_s=4)
    assert len(calls) == 2

    def fails(page: Any, app: Any, port: int) -> None:
        calls.append(port)
        raise AssertionError("not the browser's fault")

    with pytest.raises(AssertionError, match="not the browser"):
        in_browser(twin_dir, fails)
    assert len(calls) == 3


@pytest.mark.skipif(not CHROMIUM.exists(), reason="Debian's chromium is not installed")
def test_browser_click_creates_a_cut_point(twin_dir: Path, tmp_path: Path) -> None:
    n0 = len(json.loads((twin_dir / "twin.json").read_text())["cut_points"])

    def body(page: Any, app: Any, port: int) -> None:
        page.goto(f"http://127.0.0.1:{port}")
        page.wait_for_selector("canvas", timeout=60_000)
        page.wait_for_timeout(5000)
        shot = tmp_path / "page.png"
        page.screenshot(path=str(shot))
        import matplotlib.image as mpimg

        img = mpimg.imread(str(shot))[..., :3]
        assert img.std() > 0.05, "the page looks blank"
        # brown vine pixels in the 3D view (left of the side panel)
        r, g, b = img[..., 0], img[..., 1], img[..., 2]
        assert ((r > g + 0.08) & (g > b) & (r < 0.8))[:, :850].mean() > 0.01
        box = page.locator("canvas").first.bounding_box()
        assert box is not None
        # the initial view is centred on the first pose's cut point, on its cane
        page.mouse.click(box["x"] + box["width"] / 2, box["y"] + box["height"] / 2)
        data: dict[str, list[dict[str, object]]] = {}
        for _ in range(100):
            time.sleep(0.1)
            data = json.loads((twin_dir / "twin.json").read_text())
            if len(data["cut_points"]) > n0:
                break
        assert len(data["cut_points"]) == n0 + 1 and data["cut_points"][-1]["source"] == "click"
        page.reload()
        page.wait_for_selector("canvas", timeout=60_000)
        # the pose survives a reload of the twin, and the click-to-preview time is known
        assert len(Twin.load(twin_dir).poses) == n0 + 1
        assert np.isfinite(app.last_latency)
        print(f"click to preview: {1000 * app.last_latency:.0f} ms")

    in_browser(twin_dir, body)


def test_app_reports_a_broken_twin_and_validates_a_pose(twin_dir: Path, tmp_path: Path) -> None:
    """Without a browser: an invalid twin.json shows in the page's status and the server runs;
    the validate button's work runs the simulated servo to the selected pose."""
    from vinetwin.web.server import serve

    broken = tmp_path / "broken.twin"
    shutil.copytree(twin_dir, broken)
    (broken / "twin.json").write_text('{"format": "vinetwin-twin", "format_version": 99}')
    app = serve(broken, port=_free_port())
    try:
        assert "Problem" in app.status.content and "version 99" in app.status.content
    finally:
        app.close()
    app = serve(twin_dir, port=_free_port())
    try:
        app._validate()
        assert "converged" in app.validation.content and "did not" not in app.validation.content
    finally:
        app.close()


def test_session_proposes_reviews_and_undoes(twin_dir: Path) -> None:
    """Proposals through the editing session: drawn apart, accepted or rejected one or all,
    an undo takes a whole proposal run back."""
    from vinetwin.plan.config import ProposeConfig, RuleConfig
    from vinetwin.plan.proposer import describe_cut, is_proposal
    from vinetwin.web.proposals import COLOURS, cut_colour

    sess = AuthoringSession(twin_dir)
    assert sess.twin is not None
    n0 = len(sess.twin.cut_points)
    result = sess.propose(ProposeConfig(rule=RuleConfig(rule="spur")))
    twin = sess.twin
    assert result.rows and len(twin.cut_points) == n0 + len(result.rows)
    on_disk = Twin.load(twin_dir)
    assert sum(is_proposal(c, "proposed") for c in on_disk.cut_points) == len(result.rows)
    prop = twin.cut_point(result.rows[0]["id"])
    assert (
        cut_colour(prop) == COLOURS["proposed"] and cut_colour(twin.cut_points[0]) == COLOURS["cut"]
    )
    assert "spur rule" in describe_cut(twin, prop.id) and "clearance" in describe_cut(twin, prop.id)
    # the selected pose is the first proposal's: reject it, accept the rest
    assert twin.pose(sess.selected).cut_point == prop.id
    assert sess.review(False) == [prop.id]
    assert len(sess.review(True, all_proposals=True)) == len(result.rows) - 1
    assert not any(is_proposal(c, "proposed") for c in sess.twin.cut_points)
    # a person's own cut cannot be rejected as a proposal: named, nothing changes
    sess.selected = sess.twin.poses[0].id
    with pytest.raises(Exception, match="not a proposal"):
        sess.review(False)
    for _ in range(3):  # accept all, reject one, propose
        assert sess.undo()
    assert len(Twin.load(twin_dir).cut_points) == n0


@pytest.mark.skipif(not CHROMIUM.exists(), reason="Debian's chromium is not installed")
def test_browser_proposes_and_reviews_cuts(twin_dir: Path, tmp_path: Path) -> None:
    """In headless Chromium: Propose draws the proposals (magenta cut points), Reject selected
    deletes one, Accept all accepts the rest; twin.json follows each click."""

    def proposals() -> list[dict[str, object]]:
        cuts = json.loads((twin_dir / "twin.json").read_text())["cut_points"]
        return [c["proposal"] for c in cuts if "proposal" in c]

    def wait_for(cond: object, seconds: float = 60) -> None:
        end = time.monotonic() + seconds
        while time.monotonic() < end and not cond():  # type: ignore[operator]
            time.sleep(0.2)

    def body(page: Any, app: Any, port: int) -> None:
        page.goto(f"http://127.0.0.1:{port}")
        page.wait_for_selector("canvas", timeout=60_000)
        page.get_by_role("button", name="Propose cuts").click()
        wait_for(lambda: len(proposals()) > 0)
        n = len(proposals())
        assert n >= 5 and all(p["status"] == "proposed" for p in proposals())
        page.wait_for_timeout(3000)
        shot = tmp_path / "proposals.png"
        page.screenshot(path=str(shot))
        assert page.get_by_text(f"{n} proposals to review").count() >= 1
        import matplotlib.image as mpimg

        img = mpimg.imread(str(shot))[..., :3]
        r, g, b = img[..., 0], img[..., 1], img[..., 2]
        # the proposals' poses drawn green (`web.proposals.COLOURS`), their cut points magenta
        assert ((g > 0.5) & (r < 0.3) & (b < 0.4))[:, :850].sum() > 20, "no proposal drawn"
        colours = {k[1] for k, _ in app._cut_nodes.values()}
        assert (200, 0, 200) in colours and (230, 30, 30) in colours
        page.get_by_role("button", name="Reject selected").click()
        wait_for(lambda: len(proposals()) == n - 1)
        assert len(proposals()) == n - 1
        page.get_by_role("button", name="Accept all").click()
        wait_for(lambda: all(p["status"] == "accepted" for p in proposals()))
        assert [p["status"] for p in proposals()] == ["accepted"] * (n - 1)

    in_browser(twin_dir, body)


def test_browser_shows_the_pruning_plan(twin_dir: Path) -> None:
    """In headless Chromium: Plan the job lists the platform stops with each stop's poses in
    order (every pose of the sample reached) and draws the stops and the order in the scene;
    a pose out of the arm's reach is listed with its reason; a pose looking from the row's far
    side is planned from the far aisle (its stop drawn there), as `prune`'s far pass does."""
    pytest.importorskip("ompl")
    from vinetwin.twin.poses import Approach

    twin = Twin.load(twin_dir)
    high = twin.add_pose(twin.add_cut_point([0.0, 0.0, 2.6], [0, 0, 1]).id)
    back = twin.add_pose(twin.pose("p1").cut_point, Approach(0.15, -math.pi / 2, 0.2, 0.0))
    twin.save()

    def body(page: Any, app: Any, port: int) -> None:
        page.goto(f"http://127.0.0.1:{port}")
        page.wait_for_selector("canvas", timeout=60_000)
        page.get_by_role("button", name="Plan the job").click()
        end = time.monotonic() + 120
        while time.monotonic() < end and getattr(app, "plan_result", None) is None:
            time.sleep(0.2)
        result, far = app.plan_result, app.plan_far
        planned = {r.pose for rs in result.order.values() for r in rs}
        assert planned == {p.id for p in twin.poses} - {high.id, back.id}
        assert "out of the arm's reach" in result.unreachable[high.id]
        assert back.id not in result.unreachable
        assert {r.pose for rs in far.order.values() for r in rs} == {back.id}
        page.get_by_text("platform stops").first.wait_for(timeout=30_000)
        page.get_by_text(f"{high.id}: out of the arm's reach").first.wait_for(timeout=30_000)
        page.get_by_text("far aisle: 1 platform stops").first.wait_for(timeout=30_000)
        assert len(app.plan_nodes) == 2 * len(result.stops) + len(planned) + 2 * len(far.stops) + 1
        # the far aisle's stop stands on +Y, past the row, facing it
        assert len(far.stops) == 1
        frame = next(h for h in app.plan_nodes if h.name == "/plan/farstop0")
        assert frame.position[1] > 0.3

    in_browser(twin_dir, body)
