"""The `vinetwin` command: argument definitions and calls. Each subcommand is a dataclass parsed by
tyro that nests the library's config dataclasses: every setting has one declaration and one
default, in the library. `run()` imports lazily: `--help` stays fast. The jobs are library calls.
The commands live by family: `cli.twin` (making, proposing, exporting, the web app), `cli.sim`
(the servo and its simulations), `cli.capture` (captures and reconstruction), `cli.prune` (the
whole job)."""

from __future__ import annotations

import logging
import sys

import tyro

from vinetwin.cli.capture import CaptureSynthetic, ImportRecording, Reconstruct
from vinetwin.cli.prune import Prune
from vinetwin.cli.sim import Campaign, CheckReference, Fidelity, ServoCmd, ServoPlot, Validate
from vinetwin.cli.twin import (
    Demo,
    Export,
    ImportScan,
    ImportVine,
    Info,
    Preview,
    Propose,
    Sample,
    Web,
)
from vinetwin.errors import exit_status

log = logging.getLogger("vinetwin")

COMMANDS: dict[str, type] = {
    "sample": Sample, "import-vine": ImportVine, "import-scan": ImportScan, "info": Info,
    "propose": Propose,
    "export": Export, "preview": Preview, "demo": Demo, "campaign": Campaign, "validate": Validate,
    "web": Web, "capture-synthetic": CaptureSynthetic, "import-recording": ImportRecording,
    "servo": ServoCmd, "servo-plot": ServoPlot, "check-reference": CheckReference,
    "fidelity": Fidelity, "reconstruct": Reconstruct, "prune": Prune,
}  # fmt: skip


def main(argv: list[str] | None = None) -> int:
    """Entry point of the `vinetwin` command; returns the exit status."""
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    try:  # a config dataclass refuses a bad value while the arguments are parsed
        cmd = tyro.extras.subcommand_cli_from_dict(
            COMMANDS,
            args=sys.argv[1:] if argv is None else argv,
            description="vinetwin: reference clouds and digital twins for robotic vine pruning.",
        )
        cmd.run()
    except BaseException as exc:
        return exit_status(exc, log)
    return 0


if __name__ == "__main__":
    sys.exit(main())
