"""The web app's review of cut proposals: the rule and its options, Propose, accept or reject the
selected proposal or all, and the selected cut's status (the rule's reason, the pose's clearance
and sight, its servo validations). Proposals are drawn apart from accepted cuts (`COLOURS`)."""

from __future__ import annotations

from typing import Any

from vinetwin.plan.config import (
    CANE_BUDS_RANGE,
    INTERNODE_RANGE,
    RULES,
    SPUR_BUDS_RANGE,
    ProposeConfig,
    RuleConfig,
)

#: Colours of cut points and pose frustums: a proposal not yet reviewed, an accepted one or a
#: person's own cut, the selected pose.
COLOURS = {"proposed": (200, 0, 200), "cut": (230, 30, 30), "pose_proposed": (30, 160, 60),
           "pose": (40, 40, 200), "selected": (255, 120, 0)}  # fmt: skip


def cut_colour(cut: Any) -> tuple[int, int, int]:
    from vinetwin.plan.proposer import is_proposal

    return COLOURS["proposed"] if is_proposal(cut, "proposed") else COLOURS["cut"]


def pose_colour(cut: Any, selected: bool) -> tuple[int, int, int]:
    from vinetwin.plan.proposer import is_proposal

    if selected:
        return COLOURS["selected"]
    return (
        COLOURS["pose_proposed"]
        if cut is not None and is_proposal(cut, "proposed")
        else COLOURS["pose"]
    )


def add_panel(app: Any) -> Any:
    """The "Proposals" folder of the side panel, its callbacks attached here; returns its
    status text (Markdown)."""
    g, sess, on = app.server.gui, app.session, app._guarded
    rule = RuleConfig()
    with g.add_folder("Proposals"):
        app.rule = g.add_dropdown("rule", RULES, initial_value=rule.rule)
        app.buds = g.add_number("buds per spur", rule.buds, min=SPUR_BUDS_RANGE[0],
                                max=SPUR_BUDS_RANGE[1], step=1)  # fmt: skip
        app.cane_buds = g.add_number("buds per cane", rule.cane_buds, min=CANE_BUDS_RANGE[0],
                                     max=CANE_BUDS_RANGE[1], step=1)  # fmt: skip
        app.internode = g.add_number("internode (m; 0: the skeleton's nodes)", rule.internode,
                                     min=0.0, max=INTERNODE_RANGE[1], step=0.005)  # fmt: skip
        app.propose_btn = g.add_button("Propose cuts (replaces open proposals)")
        app.propose_btn.on_click(lambda _: app._in_thread(lambda: _propose(app)))
        app.accept_btn = g.add_button("Accept selected")
        app.accept_btn.on_click(on(lambda: sess.review(True)))
        app.reject_btn = g.add_button("Reject selected")
        app.reject_btn.on_click(on(lambda: sess.review(False)))
        app.accept_all = g.add_button("Accept all")
        app.accept_all.on_click(on(lambda: sess.review(True, all_proposals=True)))
        app.reject_all = g.add_button("Reject all")
        app.reject_all.on_click(on(lambda: sess.review(False, all_proposals=True)))
        return g.add_markdown("")


def _propose(app: Any) -> None:
    """Proposes in a thread of its own (a dense vine takes seconds): the panel says so
    meanwhile; an error shows in the status line."""
    from vinetwin.errors import VinetwinError

    app.proposal_status.content = "*Proposing cuts and searching their poses...*"
    with app.lock:
        try:
            cfg = ProposeConfig(
                rule=RuleConfig(rule=app.rule.value, buds=int(app.buds.value),
                                cane_buds=int(app.cane_buds.value),
                                internode=float(app.internode.value)),
                replace=True,
            )  # fmt: skip
            result = app.session.propose(cfg)
            c = result.counts()
            app.proposal_summary = (
                f"{c['proposed']} cuts proposed ({c['with_pose']} with a pose, "
                f"{c['without_pose']} without) in {result.seconds:.1f} s; "
                f"{c['already_there']} already there."
            )
        except VinetwinError as exc:
            app.session.problem = str(exc)
        app.refresh()


def status(app: Any) -> str:
    """The proposals' line and the selected cut's status."""
    from vinetwin.plan.proposer import describe_cut, is_proposal

    twin = app.session.twin
    if twin is None:
        return ""
    open_ = sum(is_proposal(c, "proposed") for c in twin.cut_points)
    lines = [getattr(app, "proposal_summary", ""), f"{open_} proposals to review."]
    if app.session.selected:
        lines.append(describe_cut(twin, twin.pose(app.session.selected).cut_point))
    return "\n\n".join(x for x in lines if x)
