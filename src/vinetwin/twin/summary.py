"""A twin's summary, as `vinetwin info` prints it."""

from __future__ import annotations

from vinetwin.errors import TwinError
from vinetwin.twin.model import Twin


def print_summary(twin: Twin, mesh: bool = True) -> None:
    """Prints what a twin holds: mesh, camera, skeleton, cut points, and each pose with its
    servo-ability; raises TwinError, after printing, when the skeleton cannot be read."""
    from rich.console import Console
    from rich.markup import escape
    from rich.table import Table

    con = Console()  # names, paths and ids are the user's: printed as text, never as markup
    con.print(f"[bold]{escape(twin.name)}[/] at {escape(str(twin.root))}")
    if mesh:
        m = twin.load_mesh()
        ext = m.bounds[1] - m.bounds[0]
        con.print(
            f"mesh {escape(str(twin.mesh_file))}: {len(m.vertices)} vertices, {len(m.faces)} triangles, "
            f"extent {ext[0]:.3f} x {ext[1]:.3f} x {ext[2]:.3f} m"
        )
    con.print(f"camera {escape(twin.camera.name)}: {twin.camera.width}x{twin.camera.height}")
    broken = ""
    if twin.skeleton_file:
        try:
            sk = twin.load_skeleton()
        except TwinError as exc:  # said after the rest, and the command fails on it
            broken = str(exc)
            con.print(f"skeleton {escape(twin.skeleton_file)}: [bold red]cannot be read[/]")
        else:
            assert sk is not None
            length = sum(b.length for b in sk.branches)
            con.print(f"skeleton {escape(twin.skeleton_file)}: {len(sk.branches)} branches, "
                      f"{length:.2f} m of wood, {len(sk.candidates)} cut candidates")  # fmt: skip
    table = Table(
        "pose", "cut point", "standoff (m)", "ICP variant", "camera position (m)", "servo-ability"
    )
    for p in twin.poses:
        t = p.T_vine_camera[:3, 3]
        table.add_row(
            escape(p.id),
            escape(p.cut_point),
            f"{p.standoff:.3f}",
            escape(p.icp_variant),
            f"{t[0]:+.3f} {t[1]:+.3f} {t[2]:+.3f}",
            escape(_all_profiles(p.extra, p.icp_variant)),
        )
    status = [c.extra["proposal"].get("status") for c in twin.cut_points
              if isinstance(c.extra.get("proposal"), dict)]  # fmt: skip
    props = (
        f" ({status.count('proposed')} proposals open, {status.count('accepted')} accepted: "
        "`vinetwin web` reviews them)"
        if status
        else ""
    )
    con.print(f"{len(twin.cut_points)} cut points{props}, {len(twin.poses)} pruning poses")
    if twin.poses:
        con.print(table)
    if broken:
        raise TwinError(broken)


def _all_profiles(extra: dict[str, object], variant: str) -> str:
    """The pose's servo-ability under each profile it was validated with (ideal first)."""
    keys = sorted(k for k in extra if k.startswith("validation")) or ["validation"]
    return "; ".join(
        ("" if k == "validation" else f"{k.removeprefix('validation_')}: ")
        + servo_ability(extra.get(k), variant)
        for k in keys
    )


def servo_ability(validation: object, variant: str) -> str:
    """One pose's validation summary for its own ICP variant ('not validated' without one)."""
    if not isinstance(validation, dict):
        return "not validated"
    cell = validation.get("variants", {}).get(variant)
    if not isinstance(cell, dict):
        return f"not validated with {variant}"
    return (
        f"{100 * cell.get('success_rate', 0):.0f}% of {cell.get('starts', '?')} starts; basin "
        f"{1000 * cell.get('basin_translation', 0):.0f} mm / {cell.get('basin_rotation', 0):.2f} rad"
    )
