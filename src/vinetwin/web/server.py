"""Starting the authoring app (`web.app.App`): `vinetwin web [TWIN]` (`serve_folder`), a port
that is free and valid (`serve`), and the warning a non-loopback address gets."""

from __future__ import annotations

import logging
from pathlib import Path

from vinetwin.errors import InputError
from vinetwin.web.app import App
from vinetwin.web.config import WebConfig

log = logging.getLogger("vinetwin.web")


def serve(
    root: str | Path, host: str = "127.0.0.1", port: int = 8080, config: WebConfig | None = None
) -> App:
    """Starts the app (returns at once; the server runs in its own threads). Any host but a
    loopback address exposes the editor, which has no authentication, to the network: that is
    allowed, with a warning."""
    if host not in ("127.0.0.1", "localhost", "::1"):
        log.warning(
            "listening on %s: anyone who can reach this machine on port %d can edit and save %s "
            "(the app has no authentication); use --host 127.0.0.1 unless the network is yours",
            host, port, root,
        )  # fmt: skip
    _check_port(host, port)
    app = App(root, host, port, config)
    if app.server.get_port() != port:  # taken between the check and the start: viser moved on
        app.close()
        raise InputError(f"port {port} on {host} is in use; choose another with --port")
    log.info("vinetwin web on http://%s:%d  (twin %s)", host, port, root)
    return app


def _check_port(host: str, port: int) -> None:
    """Refuses, by name, a port out of range or in use: viser would quietly move to the next
    free port while the command printed the asked one (another service's page)."""
    import socket

    if not 1 <= port <= 65535:
        raise InputError(f"--port must lie in 1-65535, got {port}")
    try:
        infos = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM)
    except (OSError, UnicodeError) as exc:
        raise InputError(f"--host {host}: cannot resolve it ({exc})") from None
    family, _, _, _, address = infos[0]
    with socket.socket(family, socket.SOCK_STREAM) as sock:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)  # as servers bind
        try:
            sock.bind(address)
        except OSError as exc:
            raise InputError(
                f"cannot listen on {host}:{port}: {exc.strerror or exc} (in use? choose another "
                "with --port)"
            ) from None


def serve_folder(
    root: str | Path | None,
    host: str = "127.0.0.1",
    port: int = 8080,
    forever: bool = False,
    config: WebConfig | None = None,
) -> App:
    """`vinetwin web`: serves the twin at `root`, or, without one, a copy of the bundled sample
    in out/web (made once, then edited in place); with `forever`, until interrupted."""
    if root is None:
        from vinetwin.twin.model import copy_bundled_sample

        root = copy_bundled_sample(Path("out") / "web")
        log.info("no twin given: editing a copy of the bundled sample in %s", root)
    elif not (Path(root) / "twin.json").is_file():  # a typo: no page for a folder that is not
        raise InputError(  # a twin (a twin that cannot be read opens, its problem shown)
            f"{root}: no twin.json here; give a twin folder (`vinetwin sample`, `import-vine` "
            "and `import-scan` make one), or nothing for a copy of the bundled sample"
        )
    app = serve(root, host, port, config)
    if forever:
        import time

        print(f"vinetwin web: open http://{host}:{port} (Ctrl-C stops)", flush=True)
        while True:
            time.sleep(3600)
    return app
