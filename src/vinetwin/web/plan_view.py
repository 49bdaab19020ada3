"""The web app's view of the whole job's plan (the first step of `vinetwin prune`): Plan runs
`plan.job.plan_vine` on the twin being edited, in a thread; the panel lists the platform stops
along the row, each stop's poses in the order the arm cuts them and the poses no stop reaches,
with the reason. In the scene, each stop is drawn as the robot base's frame on the platform,
labelled, and each planned pose is labelled with its stop and place in the order."""

from __future__ import annotations

from typing import Any

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


def describe(result: Any) -> str:
    """The plan as Markdown: stops with their poses in order, then the unreachable ones."""
    lines = [f"**{len(result.stops)} platform stops**, planned in {result.planning_s:.2f} s "
             f"(base {result.platform['offset']:.2f} m from the row, "
             f"{result.platform['height']:.2f} m up)."]  # fmt: skip
    for k, s in enumerate(result.stops):
        poses = ", ".join(r.pose for r in result.order.get(s, [])) or "-"
        lines.append(f"- stop {k + 1} at x = {s:+.2f} m: {poses}")
    if result.unreachable:
        lines.append(f"**{len(result.unreachable)} not reachable:**")
        lines += [f"- {pid}: {why}" for pid, why in sorted(result.unreachable.items())]
    return "\n".join(lines)


def plan(app: Any) -> None:
    """Plans the twin's job (seconds on a dense vine: the panel says so meanwhile) and draws it."""
    from vinetwin.plan.job import Planner, plan_vine
    from vinetwin.plan.reach import stop_pose

    app.plan_status.content = "*Planning the job: platform stops, reach, order...*"
    with app.lock:
        sess = app.session
        try:
            twin = sess.twin
            if twin is None:
                raise VinetwinError(sess.problem or "no twin loaded")
            planner = Planner.for_twin(twin, mesh=(sess.vertices, sess.faces))
            result = plan_vine(twin, planner)
        except VinetwinError as exc:
            app.plan_status.content = f"**Cannot plan:** {exc}"
            return
        for h in app.plan_nodes:
            h.remove()
        app.plan_nodes = []
        scene = app.server.scene
        for k, s in enumerate(result.stops):
            wxyz, pos = viser_wxyz_position(stop_pose(s, planner.cfg.platform))
            app.plan_nodes.append(scene.add_frame(f"/plan/stop{k}", wxyz=wxyz, position=pos,
                                                  axes_length=0.15, axes_radius=0.006))  # fmt: skip
            app.plan_nodes.append(scene.add_label(f"/plan/stop{k}/label", f"stop {k + 1}"))
            for i, r in enumerate(result.order.get(s, [])):
                cut = twin.cut_point(r.cut).point
                app.plan_nodes.append(scene.add_label(
                    f"/plan/order/{r.pose}", f"{k + 1}.{i + 1}", position=tuple(cut)))  # fmt: skip
        app.plan_result = result
        app.plan_status.content = describe(result)
