"""Where batch jobs run: this process, a local process pool (the default), or Ray (a local Ray on
this machine, or a cluster). `vinetwin export`, `validate` and `campaign` hand their jobs here and
get one `Outcome` per job as each finishes, whatever the executor, so outputs, progress,
resumability and per-job failure isolation are the same with all of them.

- A job whose function raises is reported failed (`Outcome.error`), the others go on.
- A job whose worker process dies (killed, out of memory, a crash in native code) is run again
  up to `ExecutorConfig.retries` times, on a fresh worker; then reported failed. Python's pool
  breaks as a whole when a worker dies, taking every job in flight with it, and does not say
  whose worker died: those jobs are run again each in a worker of its own (so only the culprit
  can fail), then a fresh pool goes on. Ray knows the task and retries it itself.
- Jobs are plain picklable objects and the function a module-level one; each worker process
  keeps what is expensive to build (a mesh and its renderer) in `worker_cache`, so a worker
  serving many jobs of one twin loads it once.

Ray is an optional extra (`pip install 'vinetwin[ray]'`). `ExecutorConfig(kind="ray")` starts a
local Ray with `workers` CPUs (all when 0) and shuts it down after; with `address` it joins a
running cluster (`ray start --head` on one machine, `ray start --address HEAD:6379` on the
others), whose nodes must have vinetwin installed and see the twin folders at the same path.
"""

from __future__ import annotations

import atexit
import contextlib
import logging
import os
import signal
import sys
import threading
import time
from collections import OrderedDict
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import FIRST_COMPLETED, Future, ProcessPoolExecutor, wait
from concurrent.futures.process import BrokenProcessPool
from contextlib import contextmanager
from dataclasses import dataclass
from multiprocessing import util as mp_util
from multiprocessing.context import SpawnContext, SpawnProcess
from typing import Any

from vinetwin._config import JsonFields
from vinetwin._faults import FAULT_VAR
from vinetwin.errors import InputError, VinetwinError, raise_if_interrupt

log = logging.getLogger(__name__)

EXECUTORS = ("local", "ray")
#: Environment variables capping a worker's threads (the workers share the cores).
THREAD_VARS = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMBA_NUM_THREADS")
#: Mesa's software OpenGL (llvmpipe, what MuJoCo's EGL renders with on a machine without a GPU)
#: starts this many rasteriser threads per process (default: one per core)
LLVMPIPE_THREADS = "LP_NUM_THREADS"


def _llvmpipe_threads(threads: int) -> str:
    """LP_NUM_THREADS for a worker allowed `threads` threads: 0 (rasterise in the rendering
    thread) for one. With two export workers on two cores, each with llvmpipe's default two
    rasteriser threads, 1000 references took 13.3-14.5 s; with 0, 12.2 s (the sample, MuJoCo)."""
    return "0" if threads <= 1 else str(threads)


@dataclass(frozen=True, kw_only=True)
class ExecutorConfig(JsonFields):
    kind: str = "local"
    """local (a process pool on this machine) or ray."""
    workers: int = 0
    """local: worker processes (0: one per core; 1: run in this process). ray: CPUs of the
    local Ray it starts (0: all); ignored when joining a cluster."""
    address: str = ""
    """ray: the cluster to join ("auto", "HOST:6379" or "ray://HOST:10001"); empty: start a
    local Ray."""
    retries: int = 1
    """Runs again a job whose worker died, this many times."""

    def __post_init__(self) -> None:
        if self.kind not in EXECUTORS:
            raise InputError(
                f"unknown executor '{self.kind}'; choose one of: {', '.join(EXECUTORS)}"
            )
        if self.workers < 0 or self.retries < 0:
            raise InputError("workers and retries must be >= 0")

    @classmethod
    def from_flags(cls, ray: bool, address: str, workers: int) -> ExecutorConfig | None:
        """What `--ray` / `--ray-address` ask for (None: the command's default local pool)."""
        if address:
            return cls(kind="ray", address=address)
        return cls(kind="ray", workers=workers) if ray else None


@dataclass(frozen=True, kw_only=True)
class ClusterConfig:
    """Where a command's batch jobs run (the command line's `--ray`, `--ray-address`)."""

    ray: bool = False
    """Run the jobs on a local Ray started on this machine (pip install 'vinetwin[ray]')."""
    ray_address: str = ""
    """Run the jobs on this Ray cluster (HOST:6379 or auto; same twin paths on every node)."""

    def executor(self, workers: int) -> ExecutorConfig | None:
        """The executor asked for, with `workers` (None: the command's default local pool)."""
        return ExecutorConfig.from_flags(self.ray, self.ray_address, workers)


@dataclass
class Outcome:
    """One job's end: `value` (what the function returned) or `error`."""

    index: int
    value: Any = None
    error: str = ""
    worker_died: bool = False

    @property
    def ok(self) -> bool:
        return not self.error


class ExecutorError(VinetwinError):
    """The executor could not start (Ray missing or its cluster unreachable)."""


# ----------------------------------------------------------------------------- worker side
_CACHE: OrderedDict[Any, Any] = OrderedDict()


def worker_cache(key: Any, build: Callable[[], Any], size: int = 2) -> Any:
    """This worker process's copy of an expensive object (e.g. a twin's renderer), built on
    first use; the least recently used beyond `size` are dropped (closed when they can be)."""
    if key in _CACHE:
        _CACHE.move_to_end(key)
        return _CACHE[key]
    value = build()
    _CACHE[key] = value
    while len(_CACHE) > size:
        _, old = _CACHE.popitem(last=False)
        close = getattr(old, "close", None)
        if callable(close):
            try:
                close()
            except Exception:  # closing a renderer must not fail a job
                pass
    return value


def clear_worker_cache() -> None:
    while _CACHE:
        _, old = _CACHE.popitem()
        close = getattr(old, "close", None)
        if callable(close):
            try:
                close()
            except Exception:
                pass


def worker_threads() -> int:
    """Threads this worker may use (0: all; set by the executor for its workers)."""
    return int(os.environ.get("VINETWIN_WORKER_THREADS", "0") or 0)


def _call(fn: Callable[[Any], Any], job: Any) -> Any:
    return fn(job)


# ----------------------------------------------------------------------------- driver side
def run_unordered(
    fn: Callable[[Any], Any], jobs: Sequence[Any], config: ExecutorConfig | None = None
) -> Iterator[Outcome]:
    """Runs `fn(job)` for every job; yields each job's `Outcome` as it finishes."""
    cfg = config or ExecutorConfig()
    if not jobs:
        return
    if cfg.kind == "ray":
        yield from _run_ray(fn, jobs, cfg)
        return
    workers = cfg.workers if cfg.workers > 0 else (os.cpu_count() or 1)
    workers = max(1, min(workers, len(jobs)))
    if workers == 1:  # in this process, with all its threads
        for i, job in enumerate(jobs):
            try:
                yield Outcome(i, fn(job))
            except Exception as exc:  # one job's failure is reported, the others go on
                raise_if_interrupt(exc)
                yield Outcome(i, error=f"{type(exc).__name__}: {exc}")
        return
    with _worker_env(workers):
        yield from _run_pool(fn, jobs, cfg, workers)


def workers_used(config: ExecutorConfig, n_jobs: int) -> int:
    """How many workers `run_unordered` uses for n jobs (for reports)."""
    if config.kind == "ray":
        try:
            import ray

            if ray.is_initialized():
                return int(ray.cluster_resources().get("CPU", 1))
        except ImportError:
            pass
        return config.workers or (os.cpu_count() or 1)
    workers = config.workers if config.workers > 0 else (os.cpu_count() or 1)
    return max(1, min(workers, n_jobs))


@contextmanager
def _worker_env(workers: int) -> Iterator[None]:
    """Caps the threads of the workers spawned meanwhile: set in this process's environment,
    which spawned workers inherit before they import numpy, numba or Open3D (an initializer
    would run too late for the libraries that read it at load)."""
    threads = str(max(1, (os.cpu_count() or 1) // workers))
    values = {k: threads for k in (*THREAD_VARS, "VINETWIN_WORKER_THREADS")}
    values[LLVMPIPE_THREADS] = _llvmpipe_threads(int(threads))
    saved = {k: os.environ.get(k) for k in values}
    os.environ.update(values)
    try:
        yield
    finally:
        for k, v in saved.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v


class _QuickExitProcess(SpawnProcess):
    """A pool worker that leaves without the interpreter's teardown once the pool's loop has
    ended normally (its shutdown sentinel): the exit handlers run (logging's flush among them),
    the standard streams are flushed, then the process ends. The teardown it skips (freeing
    every module's objects: numba's compiled code, MuJoCo, the EGL renderer) took 0.3-0.4 s of
    CPU per worker at the end of every export, validation and campaign; the system frees all
    of it at exit anyway. A worker that fails or is interrupted exits the usual way."""

    def run(self) -> None:
        super().run()
        with contextlib.suppress(Exception):
            atexit._run_exitfuncs()  # logging's flush, weakref finalizers, ...
        with contextlib.suppress(Exception):
            mp_util._exit_function()  # pyright: ignore[reportAttributeAccessIssue]
        for stream in (sys.stdout, sys.stderr):  # what a normal exit flushes last
            with contextlib.suppress(Exception):
                stream.flush()
        os._exit(0)


class _QuickExitContext(SpawnContext):
    Process = _QuickExitProcess


def _new_pool(workers: int) -> ProcessPoolExecutor:
    return ProcessPoolExecutor(
        workers,
        mp_context=_QuickExitContext(),
        initializer=_die_with_parent,
        initargs=(os.getpid(),),
    )


def _die_with_parent(parent: int) -> None:
    """Pool workers end with the process that started them, even when it is killed with
    SIGKILL (no clean-up runs there): the kernel sends them SIGKILL when their parent dies
    (Linux `PR_SET_PDEATHSIG`); elsewhere a watcher thread exits when the parent is gone. A
    worker killed mid-write leaves only a temporary file, which the next run removes."""
    try:
        import ctypes

        libc = ctypes.CDLL(None, use_errno=True)
        if libc.prctl(1, signal.SIGKILL, 0, 0, 0) == 0:  # PR_SET_PDEATHSIG
            if os.getppid() != parent:  # the parent died before the call
                os._exit(1)
            return
    except (OSError, AttributeError):
        pass

    def watch() -> None:
        while os.getppid() == parent:
            time.sleep(0.5)
        os._exit(1)

    threading.Thread(target=watch, daemon=True, name="parent-watch").start()


def _run_pool(
    fn: Callable[[Any], Any], jobs: Sequence[Any], cfg: ExecutorConfig, workers: int
) -> Iterator[Outcome]:
    queue = list(range(len(jobs)))
    pool = _new_pool(workers)
    pending: dict[Future[Any], int] = {}
    try:
        while queue or pending:
            suspects: list[int] = []
            while queue and len(pending) < 2 * workers:  # bounded: honest progress, flat memory
                i = queue.pop(0)
                try:
                    pending[pool.submit(_call, fn, jobs[i])] = i
                except BrokenProcessPool:  # a worker died since the last wait
                    suspects.append(i)
                    break
            done = set()
            if pending and not suspects:
                done, _ = wait(list(pending), return_when=FIRST_COMPLETED)
            for fut in done:
                i = pending.pop(fut)
                try:
                    yield Outcome(i, fut.result())
                except BrokenProcessPool:
                    suspects.append(i)
                except Exception as exc:
                    raise_if_interrupt(exc)
                    yield Outcome(i, error=f"{type(exc).__name__}: {exc}")
            if suspects:
                # a worker died and took the pool with it; which of the jobs in flight killed
                # it is unknown: run each of them alone, then go on with a fresh pool
                suspects += list(pending.values())
                pending.clear()
                pool.shutdown(wait=False, cancel_futures=True)
                log.warning(
                    "a worker died; running the %d jobs in flight one by one", len(suspects)
                )
                yield from _run_alone(fn, jobs, sorted(suspects), cfg)
                pool = _new_pool(workers)
    finally:
        pool.shutdown(wait=True, cancel_futures=True)


def _run_alone(
    fn: Callable[[Any], Any], jobs: Sequence[Any], indices: list[int], cfg: ExecutorConfig
) -> Iterator[Outcome]:
    """Each job in a worker of its own: a death is then its own; it runs again up to
    `cfg.retries` times."""
    for i in indices:
        deaths = 0
        while True:
            pool = _new_pool(1)
            try:
                yield Outcome(i, pool.submit(_call, fn, jobs[i]).result())
                break
            except BrokenProcessPool:
                deaths += 1
                if deaths > cfg.retries:
                    yield Outcome(
                        i, error="worker died (killed or crashed) while running it",
                        worker_died=True,
                    )  # fmt: skip
                    break
                log.warning("job %d: its worker died; running it again", i)
            except Exception as exc:
                raise_if_interrupt(exc)
                yield Outcome(i, error=f"{type(exc).__name__}: {exc}")
                break
            finally:
                pool.shutdown(wait=True, cancel_futures=True)


def _ray() -> Any:
    try:
        import ray
    except ImportError as exc:
        raise ExecutorError(
            f"the Ray executor needs ray: pip install 'vinetwin[ray]' ({exc})"
        ) from exc
    return ray


def _run_ray(
    fn: Callable[[Any], Any], jobs: Sequence[Any], cfg: ExecutorConfig
) -> Iterator[Outcome]:
    ray = _ray()
    started = False
    if not ray.is_initialized():
        env = {k: "1" for k in (*THREAD_VARS, "VINETWIN_WORKER_THREADS")}
        env[LLVMPIPE_THREADS] = _llvmpipe_threads(1)
        for k in (FAULT_VAR, FAULT_VAR + "_ONCE"):
            if k in os.environ:
                env[k] = os.environ[k]
        env.setdefault("PYOPENGL_PLATFORM", "egl")
        env.setdefault("MUJOCO_GL", "egl")
        kwargs: dict[str, Any] = {
            "include_dashboard": False,
            "log_to_driver": False,
            "configure_logging": False,
            "runtime_env": {"env_vars": env},
        }
        if cfg.address:
            kwargs["address"] = cfg.address
        else:
            kwargs["num_cpus"] = cfg.workers or (os.cpu_count() or 1)
        try:
            ray.init(**kwargs)
        except Exception as exc:
            where = cfg.address or "a local Ray"
            raise ExecutorError(f"cannot start or join {where}: {exc}") from exc
        started = True
    try:
        remote = ray.remote(num_cpus=1, max_retries=cfg.retries, retry_exceptions=False)(_call)
        cpus = max(1, int(ray.cluster_resources().get("CPU", 1)))
        fn_ref = ray.put(fn)
        queue = list(range(len(jobs)))
        pending: dict[Any, int] = {}
        while queue or pending:
            while queue and len(pending) < 2 * cpus:
                i = queue.pop(0)
                pending[remote.remote(fn_ref, jobs[i])] = i
            ready, _ = ray.wait(list(pending), num_returns=1)
            for ref in ready:
                i = pending.pop(ref)
                try:
                    yield Outcome(i, ray.get(ref))
                except ray.exceptions.RayTaskError as exc:  # the function raised
                    cause = exc.cause if getattr(exc, "cause", None) is not None else exc
                    yield Outcome(i, error=f"{type(cause).__name__}: {cause}")
                except (ray.exceptions.WorkerCrashedError, ray.exceptions.RayError) as exc:
                    yield Outcome(
                        i,
                        error=f"worker died (killed or crashed) while running it: {type(exc).__name__}",
                        worker_died=True,
                    )
    finally:
        if started:
            ray.shutdown()
