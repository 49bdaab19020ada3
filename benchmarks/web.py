"""Benchmark: web click to preview, in headless Chromium.

Serves a copy of a twin (`--twin`, default the bundled sample) with `vinetwin web`'s app, opens
it in Debian's Chromium (`/usr/bin/chromium`, driven by Playwright; no browser is downloaded) and
clicks the vine `--clicks` times near the centre of the 3D view (the initial view is centred on
the first pose's cut point, on its cane). Each click places a cut point and a pruning pose and
shows what the camera would see from it (the app's renderer, `AuthoringSession.renderer`:
the simulation's raster backend; the D405 model; the perception chain). Measured per
click:

- arrive: from Playwright's mouse click to the app's click handler starting (the browser's
  handling of the pointer events and the click's trip over the websocket);
- server: from the click event's arrival to the preview sent (`App.last_latency`: the pick, the
  pose, the render, the D405 model, the perception chain, the point cloud, image and panel
  messages; the autosave comes after);
- page: from Playwright's mouse click to the page showing the status line the app sends in
  the same message batch as the preview;
- idle: from the click to the page's next animation frame after that, so past the frame that
  draws the preview (the page updates the panel's text before it draws the 3D view): the
  goal's measure;
- drawn: on the page's own clock, from the input (the pointer press's event time) to the end of
  the first render of the 3D view after the status line changed, waited for on the GPU
  (`readPixels` right after it): when the preview's pixels are drawn, without the harness's
  round trips to Python. Needs viser's end-to-end test hook (`window.__viserMutable`); "-"
  without it;
- the page's frame time (median interval of `requestAnimationFrame` while nothing changes;
  viser draws the 3D view on demand, so this is not the cost of drawing it).

`--via message` sends each click's message from a script in the page (the message viser's page
sends on the pointer's release, with the ray of the warm-up click turned by about 0.1 deg)
instead of pressing the mouse: no pointer events, so none of the frames viser's page draws for
the pointer's press and release (its camera controls ask for one). It measures what the page
would take if its pointer handling drew nothing: a bound on what a change to viser's page
could gain, not what a person gets. The drawn time then starts at the script's send.

Clicks come `--pause` seconds (default 1) after the last one's preview, as a person looks at
each preview before clicking again; with `--pause 0` a click comes while the page is still
drawing the last one's frames (viser's page keeps drawing for 250 ms after each change) and
its preview waits behind them.

Each `--shading` (`WebConfig.shading`; default both, "fast" then "full") and each
`--display-faces` (`WebConfig.display_faces`, the most triangles of the vine the page draws;
default its default) is a run of its own (a fresh server, browser and copy of the twin), so
they are compared in the same invocation. Prints the medians and the 90th percentiles
against the issue's goal (150 ms) and the triangles drawn; `--json` writes them, one entry per
run under "runs" (keyed by shading, or "shading/faces" with several `--display-faces`), each
with the WebGL renderer the page reported. `--gl` picks how the page draws WebGL without a GPU
(`vinetwin.web.browser.GL_ARGS`): Chromium's SwiftShader (the default, as in the tests) or the
machine's Mesa llvmpipe through EGL. Timings are of this machine, shared with whatever else runs on it.

    .venv/bin/python benchmarks/web.py [--twin TWIN] [--clicks 15] [--pause 1] [--shading fast full] [--display-faces 60000 0] [--gl swiftshader|llvmpipe] [--via pointer|message] [--json out.json]
"""

from __future__ import annotations

import argparse
import shutil
import socket
import statistics
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np
from results_file import write_json

from vinetwin.web.browser import CHROMIUM, GL_ARGS, RENDERER_JS, Gl, launch
from vinetwin.web.config import WebConfig

ROOT = Path(__file__).resolve().parents[1]
SAMPLE = ROOT / "samples" / "vine_bilateral.twin"
GOAL_MS = 150.0
STATUS = "last click to preview"


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


#: the page's status line after a preview ('' before the first), with the text before it (the
#: twin's cut point and pose counts), so that two clicks whose latencies round alike change it
STATUS_JS = f"""() => {{ const t = document.body.textContent || "";
    const i = t.lastIndexOf("{STATUS}"); return i < 0 ? "" : t.slice(Math.max(0, i - 80), i + 40); }}"""


def _status_text(page: Any) -> str:
    return str(page.evaluate(STATUS_JS))


#: In the page: `window.__vt` times each click on the page's clock. `input` is the pointer
#: press's event time on the canvas (or the script's send, `window.__vtSend`); `status` is when
#: the status line changed; `drawn` is the end of the first render of the 3D view after that,
#: with the GPU's work waited for (`readPixels`). False when viser's test hook is missing.
PAGE_CLOCK_JS = f"""() => {{
    const M = window.__viserMutable;
    if (!M || !M.scene || !M.canvas || !M.sendMessage) return false;
    const canvas = M.canvas, gl = canvas.getContext('webgl2') || canvas.getContext('webgl');
    if (!gl) return false;
    const status = {STATUS_JS};
    let last = status(), waiting = false;
    const px = new Uint8Array(4);
    window.__vt = {{input: null, status: null, drawn: null}};
    window.addEventListener('pointerdown', (e) => {{
        if (e.target === canvas) window.__vt = {{input: e.timeStamp, status: null, drawn: null}};
    }}, true);
    window.__vtSend = (origin, direction) => {{
        window.__vt = {{input: performance.now(), status: null, drawn: null}};
        M.sendMessage({{type: 'ScenePointerMessage', event_type: 'click', ray_origin: origin,
                       ray_direction: direction, screen_pos: [[0.5, 0.5]], modifier: null}});
    }};
    new MutationObserver(() => {{
        const now = status();
        if (now === last) return;
        last = now;
        if (window.__vt.input !== null && window.__vt.status === null) {{
            window.__vt.status = performance.now(); waiting = true;
        }}
    }}).observe(document.body, {{subtree: true, childList: true, characterData: true}});
    const after = M.scene.onAfterRender;
    M.scene.onAfterRender = function (...args) {{
        if (after) after.apply(this, args);
        if (!waiting) return;
        waiting = false;
        gl.readPixels(0, 0, 1, 1, gl.RGBA, gl.UNSIGNED_BYTE, px);
        window.__vt.drawn = performance.now();
    }};
    return true;
}}"""


def run(
    twin_dir: Path,
    clicks: int,
    seed: int,
    config: WebConfig,
    gl: Gl = "swiftshader",
    pause: float = 1.0,
    via: str = "pointer",
) -> dict[str, Any]:
    from playwright.sync_api import TimeoutError as PlaywrightTimeout
    from playwright.sync_api import sync_playwright

    from vinetwin.web.server import serve

    port = _free_port()
    app = serve(twin_dir, port=port, config=config)
    server_ms: list[float] = []
    browser_ms: list[float] = []
    idle_ms: list[float] = []
    arrive_ms: list[float] = []  # the click's trip: Playwright's click to the handler's start
    drawn_ms: list[float] = []  # on the page's clock (`PAGE_CLOCK_JS`)
    arrivals: list[float] = []
    rays: list[tuple[list[float], list[float]]] = []  # each click's ray, as the app got it
    click = app.session.click

    def timed_click(origin: Any, direction: Any, *a: Any, **k: Any) -> Any:
        arrivals.append(time.perf_counter())
        rays.append(([float(x) for x in origin], [float(x) for x in direction]))
        return click(origin, direction, *a, **k)

    app.session.click = timed_click  # type: ignore[method-assign]
    missed = 0
    frame_ms = float("nan")
    renderer = ""
    rng = np.random.default_rng(seed)
    try:
        with sync_playwright() as pw, tempfile.TemporaryDirectory() as profile:
            ctx = launch(pw, profile, gl, deadline_s=1800)  # a long run: 30 min
            page = ctx.new_page()
            page.goto(f"http://127.0.0.1:{port}")
            page.wait_for_selector("canvas", timeout=60_000)
            page.wait_for_timeout(5000)  # the scene and the mesh arrive
            # and the server's warm-up is over (a fresh install compiles its kernels first: a
            # click during it waits for it, and its late answer was taken for the next click's)
            if not app.wait_ready():
                raise SystemExit("the web app's warm-up did not finish in 120 s")
            renderer = str(page.evaluate(RENDERER_JS))
            page_clock = bool(page.evaluate(PAGE_CLOCK_JS))
            if via == "message" and not page_clock:
                raise SystemExit("--via message needs viser's test hook (window.__viserMutable)")
            box = page.locator("canvas").first.bounding_box()
            assert box is not None
            cx, cy = box["x"] + box["width"] / 2, box["y"] + box["height"] / 2
            for k in range(clicks + 1):  # the first click is a warm-up (compilation)
                before = _status_text(page)
                latency_before = app.last_latency
                dx, dy = rng.uniform(-2, 2, 2) if k else (0.0, 0.0)
                t0 = time.perf_counter()
                if via == "message" and k:  # the warm-up click's ray, turned by about 0.1 deg
                    origin, direction = rays[0]
                    d = np.asarray(direction) + rng.normal(0.0, 0.002, 3)
                    page.evaluate(
                        "([o, d]) => window.__vtSend(o, d)",
                        [origin, (d / np.linalg.norm(d)).tolist()],
                    )
                else:
                    page.mouse.click(cx + dx, cy + dy)
                seen = False
                deadline = t0 + 10.0
                try:  # polled inside the page at each frame
                    while not seen and time.perf_counter() < deadline:
                        page.wait_for_function(
                            f"(before) => {{ const s = ({STATUS_JS})(); return s && s !== before; }}",
                            arg=before, polling="raf",
                            timeout=max(1.0, 1000 * (deadline - time.perf_counter())),
                        )  # fmt: skip
                        before = _status_text(page)
                        # this click's status names its latency; another change is a late
                        # update of the click before (its autosave's panel): wait on
                        lat = app.last_latency
                        seen = lat is not latency_before and f": {1000 * lat:.0f} ms" in before
                except PlaywrightTimeout:  # the click hit no cane, or nothing came back
                    seen = False
                elapsed = time.perf_counter() - t0
                if seen:  # the page's next frame: after the one that drew the preview
                    page.evaluate("() => new Promise(r => requestAnimationFrame(() => r(0)))")
                idle = time.perf_counter() - t0
                # the person looks at the preview before the next click (the page's frames for
                # this click, its autosave's panel update, are over by then)
                page.wait_for_timeout(1000 * pause)
                if not seen:  # the click hit no cane (or the page did not update in 10 s)
                    missed += int(k > 0)  # the warm-up click is not one of the `clicks`
                    continue
                if k:
                    vt = page.evaluate("() => window.__vt") if page_clock else None
                    if vt and vt["drawn"] is not None and vt["input"] is not None:
                        drawn_ms.append(float(vt["drawn"]) - float(vt["input"]))
                    browser_ms.append(1000 * elapsed)
                    idle_ms.append(1000 * idle)
                    server_ms.append(1000 * app.last_latency)
                    arrive_ms.append(1000 * (arrivals[-1] - t0))
            # how long the page takes to draw a frame (software WebGL in headless Chromium)
            frames = page.evaluate(
                """() => new Promise(done => { const t = []; const f = (now) => { t.push(now);
                   if (t.length < 12) requestAnimationFrame(f); else done(t); };
                   requestAnimationFrame(f); })"""
            )
            frame_ms = float(np.median(np.diff(frames)))
            ctx.close()
    finally:
        app.server.stop()

    def stats(x: list[float]) -> dict[str, float | None]:
        if not x:
            return {"median": None, "p90": None}
        return {"median": statistics.median(x), "p90": float(np.percentile(x, 90))}

    return {
        "shading": config.shading,
        "display_faces": config.display_faces,
        "pause_s": pause,
        "via": via,
        "drawn_faces": app.vine_faces,
        "renderer": renderer,
        "measured": len(browser_ms),
        "missed": missed,
        "arrive_ms": stats(arrive_ms),
        "server_ms": stats(server_ms),
        "browser_ms": stats(browser_ms),
        "idle_ms": stats(idle_ms),
        "drawn_ms": stats(drawn_ms),
        "browser_frame_ms": frame_ms,
        "server_samples_ms": server_ms,
        "browser_samples_ms": browser_ms,
        "idle_samples_ms": idle_ms,
        "drawn_samples_ms": drawn_ms,
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=(__doc__ or "").split("\n")[0])
    ap.add_argument("--twin", type=Path, default=SAMPLE, help="twin folder (a copy is edited)")
    ap.add_argument("--clicks", type=int, default=15, help="timed clicks (after one warm-up)")
    ap.add_argument("--seed", type=int, default=0, help="jitter of the click positions")
    ap.add_argument("--shading", nargs="+", default=["fast", "full"], choices=["fast", "full"],
                    help="WebConfig.shading values to run, one after the other")  # fmt: skip
    ap.add_argument("--gl", default="swiftshader", choices=sorted(GL_ARGS),
                    help="how the page's WebGL is drawn: Chromium's SwiftShader or Mesa's "
                         "llvmpipe through EGL (vinetwin.web.browser.GL_ARGS)")  # fmt: skip
    ap.add_argument("--display-faces", type=int, nargs="+", default=[WebConfig().display_faces],
                    help="WebConfig.display_faces values to run (0: every triangle), each "
                         "with each shading")  # fmt: skip
    ap.add_argument("--pause", type=float, default=1.0,
                    help="seconds between a click's preview and the next click (0: the next "
                         "click comes while the page is still drawing the last one's frames)")  # fmt: skip
    ap.add_argument("--via", default="pointer", choices=["pointer", "message"],
                    help="how a click reaches the app: the mouse, or the click's message sent by "
                         "a script in the page (no pointer events: what viser's page would take "
                         "without the frames it draws for them)")  # fmt: skip
    ap.add_argument("--json", type=Path, help="write the figures here")
    args = ap.parse_args()
    if not CHROMIUM.exists():
        sys.exit(f"{CHROMIUM} is missing: scripts/setup.sh installs Debian's chromium")
    runs = {}
    for faces in args.display_faces:
        for shading in args.shading:
            with tempfile.TemporaryDirectory() as tmp:  # each run edits a fresh copy
                twin_dir = Path(tmp) / args.twin.name
                shutil.copytree(args.twin, twin_dir)
                key = shading if len(args.display_faces) == 1 else f"{shading}/{faces}"
                cfg = WebConfig(shading=shading, display_faces=faces)
                runs[key] = run(
                    twin_dir, args.clicks, args.seed, cfg, args.gl, args.pause, args.via
                )
    print(f"web click to preview, twin {args.twin.name}, {args.clicks} clicks per shading, "
          f"{args.pause:g} s apart, goal {GOAL_MS:.0f} ms; median / p90 ms (missed: clicks "
          f"that hit no cane)")  # fmt: skip
    print(f"WebGL ({args.gl}): {next(iter(runs.values()))['renderer']}; clicks via {args.via}")
    print(f"{'shading':14} {'faces':>7} {'arrive':>12} {'server':>12} {'page':>12} {'idle':>12} "
          f"{'drawn':>12} {'missed':>7}")  # fmt: skip

    def cell(s: dict[str, float | None]) -> str:
        med = "-" if s["median"] is None else f"{s['median']:.0f}"
        p90 = "-" if s["p90"] is None else f"{s['p90']:.0f}"
        return f"{med} / {p90}"

    for shading, out in runs.items():
        print(f"{shading:14} {out['drawn_faces']:>7} {cell(out['arrive_ms']):>12} "
              f"{cell(out['server_ms']):>12} "
              f"{cell(out['browser_ms']):>12} {cell(out['idle_ms']):>12} "
              f"{cell(out['drawn_ms']):>12} {out['missed']:>7}")  # fmt: skip
    write_json(args.json, {"twin": args.twin.name, "clicks": args.clicks, "goal_ms": GOAL_MS,
                           "gl": args.gl, "pause_s": args.pause, "via": args.via,
                           "runs": runs})  # fmt: skip


if __name__ == "__main__":
    main()
