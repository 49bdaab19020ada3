"""The servo loop, the same for the simulation and the hardware: frame -> perception -> ICP from
the kinematic guess -> PBVS -> guarded command, one cycle per camera frame, every cycle logged.

    with open_source("realsense") as cam, FrankaRobot(FrankyTransport(ip), T_fc) as robot:
        summary = run_loop(servo, cam, robot, LoopConfig(), log=CycleLog("run.jsonl"))

Safety, beyond `Servo.step`'s refusals (which already give exactly zero twist):
- no frame within `frame_timeout`: the robot is stopped at once; after `camera_lost` s without
  a frame the run ends ("camera stopped");
- a cycle that took longer than `max_cycle` (frame stamp to command) sends zero instead of its
  stale twist ("overrun");
- the robot's own watchdog (`robot.CommandLimits.watchdog`) stops it if the loop itself hangs;
- an arm that does not follow its commands (its camera, as its kinematics report it, moved less
  than `follow_fraction` of the motion sent over `follow_window` s: a joint limit, a
  singularity, a collision, a reflex) ends the run ("the arm does not follow");
- `dry_run` computes and logs every twist and sends none (the robot is only read);
- an exception anywhere stops the robot before it propagates, as does Ctrl-C.

The log (`CycleLog`) is JSON Lines: a header, then one record per cycle (stamps, ICP result,
twist asked and sent, robot pose, timings, reason), then a footer with the summary.
`log_as_campaign` turns it into the campaign report's structure, so its plots draw a hardware
run the way they draw a simulated one (`vinetwin servo-plot`).
"""

from __future__ import annotations

import contextlib
import json
import math
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Any

import numpy as np

from vinetwin._config import json_default
from vinetwin.capture.sources import CameraFrame, CameraSource
from vinetwin.errors import InputError, OutputError, raise_if_interrupt
from vinetwin.files import parse_json
from vinetwin.frames import Array, invert, pose_error
from vinetwin.servo.config import LoopConfig
from vinetwin.servo.robot import Robot
from vinetwin.servo.step import Servo, StepResult

LOG_FORMAT = "vinetwin-servo-log"
LOG_VERSION = 1


@dataclass
class Cycle:
    """One frame's record."""

    frame: CameraFrame
    result: StepResult
    T_base_camera: Array | None
    sent: Array
    overrun: bool
    cycle_s: float
    """Processing time, from the frame's delivery to the command (s)."""
    latency_s: float
    """From the frame's capture (stamp) to the command (s), on the source's clock."""


@dataclass
class LoopSummary:
    frames: int = 0
    trusted: int = 0
    sent: int = 0
    ended: str = ""
    """Why the loop ended: at goal, duration, frames, end of recording, camera stopped, stopped
    (callback), lost the vine (see `lost`), the arm does not follow (see `stalled`), interrupted,
    or the error."""
    lost: str = ""
    """The servo's "lost the vine" reason when it ended the run (`SafetyConfig.lost_after`)."""
    stalled: str = ""
    """Why the arm was judged not to follow its commands, when that ended the run
    (`LoopConfig.follow_window`)."""
    reacquisitions: int = 0
    """Frames the wide search trusted after a streak of refusals."""
    at_goal: bool = False
    final_error: list[float] | None = None
    """(translation m, rotation rad) of the last trusted estimate."""
    reasons: dict[str, int] = field(default_factory=dict)
    """Refusals by reason."""
    overruns: int = 0
    camera_timeouts: int = 0
    median_cycle_ms: float = math.nan
    loop_rate_hz: float = math.nan

    def describe(self) -> str:
        """The summary as `vinetwin servo` prints it."""
        lines = [
            f"{self.frames} frames, {self.trusted} trusted, {self.sent} commands sent; "
            f"ended: {self.ended}; at goal: {self.at_goal}"
        ]
        if self.final_error is not None:
            t, r = self.final_error
            lines.append(f"last estimated error: {1000 * t:.2f} mm, {r:.4f} rad")
        if self.reasons:
            lines.append("refused: " + ", ".join(f"{k} x{v}" for k, v in self.reasons.items()))
        if self.reacquisitions:
            lines.append(f"re-acquired by the wide search {self.reacquisitions} times")
        if self.lost or self.stalled:
            lines.append(f"STOPPED: {self.lost or self.stalled}")
        lines.append(
            f"median cycle {self.median_cycle_ms:.1f} ms, {self.loop_rate_hz:.1f} Hz; "
            f"overruns {self.overruns}, camera timeouts {self.camera_timeouts}"
        )
        return "\n".join(lines)


class CycleLog:
    """A JSON Lines log of a servo run. `extra` fields are added to the header."""

    def __init__(self, path: str | Path, **header: Any) -> None:
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._f: IO[str] | None = self.path.open("w")
        self.write({"format": LOG_FORMAT, "format_version": LOG_VERSION, **header})

    def write(self, record: dict[str, Any]) -> None:
        """Appends a record; a failed write (a full disk) closes the log and raises
        OutputError naming it, once: the loop stops the robot and ends the run."""
        if self._f is None:
            return
        try:
            self._f.write(json.dumps(record, default=json_default) + "\n")
            self._f.flush()  # a crash keeps every cycle logged so far
        except OSError as exc:
            self.close()
            raise OutputError(
                f"{self.path}: cannot write the servo log: {exc.strerror or exc}"
            ) from None

    def close(self) -> None:
        if self._f is not None:
            f, self._f = self._f, None
            with contextlib.suppress(OSError):  # a write already failed and said so
                f.close()


def cycle_record(c: Cycle, extra: dict[str, Any] | None = None) -> dict[str, Any]:
    r = c.result
    icp = r.icp
    rec: dict[str, Any] = {
        "stamp": c.frame.stamp,
        "number": c.frame.number,
        "trusted": r.trusted,
        "reason": r.reason,
        "at_goal": r.at_goal,
        "tracked": r.tracked,
        "twist": r.twist.tolist(),
        "sent": c.sent.tolist(),
        "overrun": c.overrun,
        "cycle_ms": 1000 * c.cycle_s,
        "latency_ms": 1000 * c.latency_s,
        "timings_ms": {k: 1000 * v for k, v in r.timings.items()},
        "T_ref_cur": None if r.T_ref_cur is None else r.T_ref_cur.tolist(),
        "error": None if r.error is None else r.error.tolist(),
        "T_base_camera": None if c.T_base_camera is None else c.T_base_camera.tolist(),
    }
    if icp is not None:
        rec["icp"] = {
            "converged": icp.converged,
            "fitness": icp.fitness,
            "overlap": icp.overlap,
            "inlier_rmse": icp.inlier_rmse,
            "correspondences": icp.correspondences,
            "iterations": icp.iterations,
            "reason": icp.reason,
        }
    if extra:
        rec.update(extra)
    return rec


class FollowCheck:
    """Does the arm follow its commands? Each cycle adds the motion sent in the previous cycle
    (|v| dt, |omega| dt, held until this frame) and the motion the robot's kinematics report
    over the same interval; over `LoopConfig.follow_window` the reported motion must be at least
    `follow_fraction` of the commanded one (windows with less than `follow_min_translation` /
    `follow_min_rotation` commanded are not judged). `update` returns the named stop's reason,
    or "" while the arm follows."""

    def __init__(self, cfg: LoopConfig) -> None:
        self.cfg = cfg
        self._prev: tuple[float, Array, Array] | None = None
        self._window: deque[tuple[float, float, float, float, float]] = deque()

    def update(self, stamp: float, T_base_camera: Array | None, sent: Array) -> str:
        cfg = self.cfg
        if cfg.follow_window <= 0 or T_base_camera is None:
            return ""
        prev, self._prev = self._prev, (stamp, np.asarray(T_base_camera, float), sent.copy())
        if prev is None or stamp <= prev[0]:
            return ""
        dt = stamp - prev[0]
        moved_t, moved_r = pose_error(prev[1], T_base_camera)
        sent_t = float(np.linalg.norm(prev[2][:3])) * dt
        sent_r = float(np.linalg.norm(prev[2][3:])) * dt
        self._window.append((stamp, sent_t, sent_r, moved_t, moved_r))
        while self._window and stamp - self._window[0][0] >= cfg.follow_window:
            self._window.popleft()
        if not self._window or stamp - self._window[0][0] + dt < cfg.follow_window - 1e-9:
            return ""  # the window is not full yet
        c_t, c_r, m_t, m_r = (sum(w[i] for w in self._window) for i in range(1, 5))
        if c_t >= cfg.follow_min_translation and m_t < cfg.follow_fraction * c_t:
            what = f"{1000 * m_t:.1f} mm of the {1000 * c_t:.1f} mm"
        elif c_r >= cfg.follow_min_rotation and m_r < cfg.follow_fraction * c_r:
            what = f"{m_r:.3f} rad of the {c_r:.3f} rad"
        else:
            return ""
        return (
            f"the arm does not follow: the camera moved {what} commanded in the last "
            f"{cfg.follow_window:g} s (a joint limit, a singularity, a collision or a reflex?)"
        )


def run_loop(
    servo: Servo,
    source: CameraSource,
    robot: Robot | None,
    config: LoopConfig | None = None,
    *,
    log: CycleLog | None = None,
    on_cycle: Callable[[Cycle], dict[str, Any] | bool | None] | None = None,
    check_latency: bool = True,
) -> LoopSummary:
    """Runs the servo until the goal is held, the frames end or a limit is reached.

    `robot` None: no robot (replay of frames that carry their recorded pose; nothing is sent).
    `on_cycle(cycle)` may return a dict of extra fields for the cycle's log record (with
    "end_run": True to end the run after this cycle), or True to end it. `check_latency`
    False: no overrun check (the simulation, where the source's time is simulated)."""
    cfg = config or LoopConfig()
    summary = LoopSummary()
    cycles_ms: list[float] = []
    first_stamp: float | None = None
    last_stamp = math.nan
    at_goal_since: float | None = None
    no_frame_since: float | None = None
    send = robot is not None and not cfg.dry_run
    follow = FollowCheck(cfg)
    try:
        while True:
            frame = source.read(timeout=cfg.frame_timeout)
            if frame is None:
                if source.ended:
                    summary.ended = "end of recording"
                    break
                summary.camera_timeouts += 1
                now = time.monotonic()
                no_frame_since = now if no_frame_since is None else no_frame_since
                if send:
                    assert robot is not None
                    robot.stop(f"no frame for {cfg.frame_timeout} s")
                if log:
                    log.write({"event": "no frame", "after_s": now - no_frame_since})
                if now - no_frame_since >= cfg.camera_lost:
                    summary.ended = "camera stopped"
                    break
                continue
            no_frame_since = None
            t_read = time.perf_counter()
            T_base_camera = (
                frame.T_base_camera if robot is None else robot.T_base_camera_at(frame.stamp)
            )
            r = servo.step_depth(frame.depth, frame.stamp, T_base_camera, now=source.now())
            latency = source.now() - frame.stamp  # capture to command
            overrun = check_latency and latency > cfg.max_cycle
            twist = np.zeros(6) if overrun else r.twist
            sent = np.zeros(6)
            if send:
                assert robot is not None
                sent = robot.command(twist)
            cycle_s = time.perf_counter() - t_read
            cycle = Cycle(frame, r, T_base_camera, sent, overrun, cycle_s, latency)
            extra = on_cycle(cycle) if on_cycle else None
            end = extra is True
            if isinstance(extra, dict):
                end = bool(extra.pop("end_run", False))
            if log:
                log.write(cycle_record(cycle, extra if isinstance(extra, dict) else None))

            summary.frames += 1
            summary.trusted += int(r.trusted)
            summary.sent += int(bool(np.any(sent)))
            summary.overruns += int(overrun)
            cycles_ms.append(1000 * cycle_s)
            if not r.trusted:
                key = r.reason.split(":")[0]
                summary.reasons[key] = summary.reasons.get(key, 0) + 1
            elif r.T_ref_cur is not None:
                summary.final_error = list(pose_error(r.T_ref_cur, np.eye(4)))
            first_stamp = frame.stamp if first_stamp is None else first_stamp
            last_stamp = frame.stamp
            if r.trusted:
                summary.at_goal = r.at_goal
                if r.at_goal:
                    at_goal_since = frame.stamp if at_goal_since is None else at_goal_since
                else:
                    at_goal_since = None
            summary.reacquisitions += int(r.reacquired)
            if r.lost:
                summary.ended, summary.lost = "lost the vine", r.reason
                break
            stalled = follow.update(frame.stamp, T_base_camera, sent) if send else ""
            if stalled:
                summary.ended, summary.stalled = "the arm does not follow", stalled
                if log:
                    log.write({"event": "stop", "reason": stalled})
                break
            if end:
                summary.ended = "stopped"
                break
            if cfg.settle > 0 and at_goal_since is not None:
                if frame.stamp - at_goal_since >= cfg.settle:
                    summary.ended = "at goal"
                    break
            if cfg.duration > 0 and frame.stamp - first_stamp >= cfg.duration:
                summary.ended = "duration"
                break
            if cfg.max_frames and summary.frames >= cfg.max_frames:
                summary.ended = "frames"
                break
    except KeyboardInterrupt:
        summary.ended = "interrupted"
    except Exception as exc:
        summary.ended = f"error: {exc}"
        raise_if_interrupt(exc)  # Ctrl-C inside a compiled kernel
        raise
    finally:
        if robot is not None and (send or robot.moving):  # a dry run sends nothing, ever
            robot.stop(f"loop ended: {summary.ended}")
        if cycles_ms:
            summary.median_cycle_ms = float(np.median(cycles_ms))
        if first_stamp is not None and last_stamp > first_stamp:
            summary.loop_rate_hz = (summary.frames - 1) / (last_stamp - first_stamp)
        if log:
            log.write({"event": "end", "summary": summary.__dict__})
    return summary


# ----------------------------------------------------------------------------- reading logs
def read_log(path: str | Path) -> tuple[dict[str, Any], list[dict[str, Any]], dict[str, Any]]:
    """(header, cycle records, summary or {}) of a servo log; a log cut short by a crash reads
    up to its last whole line."""
    path = Path(path)
    if not path.exists():
        raise InputError(f"{path}: no such log")
    header: dict[str, Any] | None = None
    cycles, summary = [], {}
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(f"{path}: cannot read it as a servo log (JSON Lines): {exc}") from None
    for n, line in enumerate(text.splitlines()):
        try:
            rec = parse_json(line)
        except ValueError:
            if n == 0:  # not a partial last line: the first line is no JSON at all
                raise InputError(f"{path}: not a vinetwin servo log (its first line is no "
                                 "JSON)") from None  # fmt: skip
            break  # a partial last line
        if not isinstance(rec, dict):
            if n == 0:
                raise InputError(f"{path}: not a vinetwin servo log")
            continue
        if n == 0:
            version = rec.get("format_version", 0)
            if rec.get("format") != LOG_FORMAT or not isinstance(version, int):
                raise InputError(f"{path}: not a vinetwin servo log")
            if version > LOG_VERSION:
                raise InputError(
                    f"{path}: log version {rec['format_version']} is newer than this vinetwin "
                    f"reads ({LOG_VERSION})"
                )
            header = rec
        elif rec.get("event") == "end":
            summary = rec.get("summary", {})
        elif "stamp" in rec:
            cycles.append(rec)
    if header is None:
        raise InputError(f"{path}: empty log")
    return header, cycles, summary


def log_as_campaign(paths: list[str | Path]) -> dict[str, Any]:
    """Servo logs as the campaign report's structure (one 'grid' run per log, each its own
    start column), for `report.plot_errors` / `plot_trajectories`. The error is the true one
    where the log has it (simulation), else the servo's estimate; the goal is where the last
    trusted estimate puts the reference camera."""
    runs, starts, twins = [], [], set()
    for i, p in enumerate(paths):
        try:
            run, start, twin = _log_run(i, p)
        except InputError:
            raise
        except (KeyError, TypeError, ValueError, IndexError, AttributeError) as exc:
            raise InputError(f"{p}: malformed servo log: {type(exc).__name__}: {exc}") from None
        runs.append(run)
        starts.append(start)
        twins.add(twin)
    return {"twin": ", ".join(sorted(twins)), "starts": starts, "runs": runs}


def _log_run(i: int, p: str | Path) -> tuple[dict[str, Any], tuple[float, float], str]:
    """One log as a campaign run (`log_as_campaign`), its start error and its twin."""
    header, cycles, summary = read_log(p)
    t0 = cycles[0]["stamp"] if cycles else 0.0
    series: dict[str, list[Any]] = {
        "t": [], "error_t": [], "error_r": [], "trusted": [], "position": []
    }  # fmt: skip
    goal = np.eye(4)
    est: Array | None = None
    for c in cycles:
        if c.get("true_error") is not None:
            et, er = c["true_error"]
        elif c.get("T_ref_cur") is not None:
            et, er = pose_error(np.asarray(c["T_ref_cur"]), np.eye(4))
        else:
            continue
        series["t"].append(c["stamp"] - t0)
        series["error_t"].append(et)
        series["error_r"].append(er)
        series["trusted"].append(c["trusted"])
        base = c.get("T_base_camera")
        series["position"].append((np.asarray(base)[:3, 3] if base else np.zeros(3)).tolist())
        if c["trusted"] and base is not None and c.get("T_ref_cur") is not None:
            est = np.asarray(base) @ invert(np.asarray(c["T_ref_cur"]))
    if est is not None:
        goal = est
    start = (series["error_t"][0], series["error_r"][0]) if series["t"] else (0.0, 0.0)
    run = {
        "key": f"log/{Path(p).stem}",
        "group": "grid",
        "start_index": i,
        "goal": goal.tolist(),
        "summary": {"variant": header.get("variant", "?"), **summary},
        "series": series,
    }
    return run, start, str(header.get("twin", ""))
