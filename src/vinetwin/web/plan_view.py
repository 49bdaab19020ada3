"""The web app's view of the whole job's plan (the first step of `vinetwin prune`): Plan runs
`plan.job.plan_vine` on the twin being edited, in a thread, and for the poses that look at the
row from its far side the same on the twin seen from the far aisle (`plan.sides`), as `prune`'s
far pass does; the panel lists the platform stops along the row, each stop's poses in the order
the arm cuts them and the poses no stop reaches, with the reason. In the scene, each stop is
drawn as the robot base's frame on the platform (in the far aisle for the far pass), labelled,
and each planned pose is labelled with its stop and place in the order."""

from __future__ import annotations

from typing import Any

import numpy as np

from vinetwin.conventions import viser_wxyz_position
from vinetwin.errors import VinetwinError


def add_panel(app: Any) -> Any:
    """The "Pruning plan" folder; returns its status text (Markdown)."""
    g = app.server.gui
    app.plan_nodes = []
    with g.add_folder("Pruning plan"):
        app.plan_btn = g.add_button("Plan the job (stops, reach, order)")
        app.plan_btn.on_click(lambda _: app._in_thread(lambda: plan(app)))
        return g.add_markdown("")


def describe(result: Any, far: Any = None) -> str:
    """The plan as Markdown: stops with their poses in order, then the unreachable ones; with
    `far`, the far aisle's plan (its stops at x along the row in the vine frame) after it."""
    lines: list[str] = []
    for name, r, sign in (("", result, 1.0), ("far aisle: ", far, -1.0)):
        if r is None:
            continue
        lines.append(f"**{name}{len(r.stops)} platform stops**, planned in {r.planning_s:.2f} s "
                     f"(base {r.platform['offset']:.2f} m from the row, "
                     f"{r.platform['height']:.2f} m up).")  # fmt: skip
        for k, s in enumerate(r.stops):
            poses = ", ".join(c.pose for c in r.order.get(s, [])) or "-"
            lines.append(f"- {name}stop {k + 1} at x = {sign * s:+.2f} m: {poses}")
        if r.unreachable:
            lines.append(f"**{name}{len(r.unreachable)} not reachable:**")
            lines += [f"- {pid}: {why}" for pid, why in sorted(r.unreachable.items())]
    return "\n".join(lines)


def plan(app: Any) -> None:
    """Plans the twin's job (seconds on a dense vine: the panel says so meanwhile) and draws it."""
    from vinetwin.frames import transform_points
    from vinetwin.plan.job import Planner, plan_vine
    from vinetwin.plan.reach import stop_pose
    from vinetwin.plan.sides import far_pose_ids, far_side_twin
    from vinetwin.twin.poses import HALF_TURN

    app.plan_status.content = "*Planning the job: platform stops, reach, order...*"
    with app.lock:
        sess = app.session
        try:
            twin = sess.twin
            if twin is None:
                raise VinetwinError(sess.problem or "no twin loaded")
            planner = Planner.for_twin(twin, mesh=(sess.vertices, sess.faces))
            result = plan_vine(twin, planner)
            far_ids, far, far_planner = far_pose_ids(twin), None, None
            if far_ids:  # `prune`'s far pass: the twin seen from the far aisle
                far_twin = far_side_twin(twin, far_ids, write=False)
                V = transform_points(HALF_TURN, sess.vertices)
                far_planner = Planner.for_twin(far_twin, mesh=(V, sess.faces))
                far = plan_vine(far_twin, far_planner)
                for pid in far_ids:
                    result.unreachable.pop(pid, None)
        except VinetwinError as exc:
            app.plan_status.content = f"**Cannot plan:** {exc}"
            return
        for h in app.plan_nodes:
            h.remove()
        app.plan_nodes = []
        scene = app.server.scene
        passes = [("", result, planner, np.eye(4))]
        if far is not None and far_planner is not None:
            passes.append(("far ", far, far_planner, HALF_TURN))
        for tag, r, pl, T in passes:
            key = tag.strip().replace(" ", "_")
            for k, s in enumerate(r.stops):
                wxyz, pos = viser_wxyz_position(T @ stop_pose(s, pl.cfg.platform))
                app.plan_nodes.append(scene.add_frame(f"/plan/{key}stop{k}", wxyz=wxyz,
                                                      position=pos, axes_length=0.15,
                                                      axes_radius=0.006))  # fmt: skip
                app.plan_nodes.append(scene.add_label(f"/plan/{key}stop{k}/label",
                                                      f"{tag}stop {k + 1}"))  # fmt: skip
                for i, c in enumerate(r.order.get(s, [])):
                    cut = twin.cut_point(c.cut).point
                    app.plan_nodes.append(scene.add_label(
                        f"/plan/order/{c.pose}", f"{tag}{k + 1}.{i + 1}", position=tuple(cut)))  # fmt: skip
        app.plan_result, app.plan_far = result, far
        app.plan_status.content = describe(result, far)
