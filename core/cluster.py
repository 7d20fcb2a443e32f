"""Running independent, deterministic jobs as Ray tasks: ground-truth chunks, materials to train.

Ray is an optional extra (``pip install 'neumip[cluster]'``), imported only when a cluster is used.
Tasks are pure functions of their arguments; what they return comes back to the driver (ground-truth
chunks are written by the driver alone, exactly as in one process). Two ways to collect results:

- :func:`ordered` yields results in submission order with a bounded number of tasks in flight
  (ground-truth chunks: the data set is written chunk after chunk);
- :func:`as_completed` yields ``(job, result or exception)`` as tasks finish (training a library:
  one failed material does not stop the others).

A worker that dies mid-task (killed, out of memory, node lost) is retried by Ray up to
``max_retries`` times, and a retry returns the same bits (a training task resumes from its last
checkpoint, which replays exactly).
"""

from __future__ import annotations

import argparse
import logging
import os
from contextlib import contextmanager
from dataclasses import dataclass
from typing import Any, Callable, Iterable, Iterator

from neumip.core.errors import NeumipError

log = logging.getLogger(__name__)

INSTALL_HINT = "pip install 'neumip[cluster]'"

AUTH_HINT = (" (a cluster started with `ray start` uses token authentication: set RAY_AUTH_MODE=token and make "
             "its token available, ~/.ray/auth_token or RAY_AUTH_TOKEN)")


class ClusterError(NeumipError, RuntimeError):
    """Ray is missing, the cluster cannot be reached, or a task failed for good."""


@dataclass
class RayConfig:
    """Where tasks run and what each may use."""

    address: str | None = None
    """Cluster to join ("auto", "HOST:6379", "ray://HOST:10001"); None: start a local Ray (or use the
    one this process has already started)."""
    cpus_per_task: int = 1
    """CPUs Ray reserves for each task; the task uses that many threads (drjit or torch)."""
    in_flight: int | None = None
    """Most tasks submitted but not yet collected (bounds memory); None: twice the task slots."""
    local_cpus: int | None = None
    """CPUs of a local Ray started here; None: every core of this machine."""
    dashboard: bool = False
    """Start Ray's dashboard with a local Ray (http://127.0.0.1:8265; needs ray[default])."""
    max_retries: int = 3
    """Times Ray re-runs a task whose worker process died."""

    def __post_init__(self) -> None:
        if self.cpus_per_task < 1:
            raise ValueError(f"cpus_per_task must be >= 1, got {self.cpus_per_task}")
        if self.in_flight is not None and self.in_flight < 1:
            raise ValueError(f"in_flight must be >= 1, got {self.in_flight}")
        if self.max_retries < 0:
            raise ValueError(f"max_retries must be >= 0, got {self.max_retries}")

    @property
    def joining(self) -> bool:
        """Whether this joins a running cluster (else it starts a local Ray)."""
        return self.address not in (None, "", "local")


def add_ray_arguments(p: argparse.ArgumentParser, task: str, per_task: bool = True) -> None:
    """--ray [ADDRESS] and its options on a command that runs one Ray task per `task`."""
    g = p.add_argument_group(f"Ray cluster ({INSTALL_HINT})")
    g.add_argument("--ray", nargs="?", const="", metavar="ADDRESS",
                   help=f"run each {task} as a Ray task: 'auto' or HOST:PORT joins a cluster, no ADDRESS starts "
                   "a local Ray (put --ray last or write --ray=ADDRESS)")
    if per_task:
        g.add_argument("--ray-cpus-per-task", type=int, default=1, metavar="N", help=f"CPUs (threads) of each {task} task (default 1)")
        g.add_argument("--ray-in-flight", type=int, metavar="N", help=f"most {task}s in flight (default: twice the task slots)")
    g.add_argument("--ray-dashboard", action="store_true",
                   help="start Ray's dashboard with a local Ray (needs pip install 'ray[default]')")


def ray_config(args: argparse.Namespace, **fields) -> RayConfig | None:
    """The RayConfig of the --ray options (`fields` override them), or None without --ray.

    Fails at once (ClusterError) when Ray is not installed, before any output is started."""
    if args.ray is None:
        return None
    per_task = {"cpus_per_task": getattr(args, "ray_cpus_per_task", 1), "in_flight": getattr(args, "ray_in_flight", None)}
    config = RayConfig(address=args.ray or None, dashboard=args.ray_dashboard, **{**per_task, **fields})
    check_installed(config)
    return config


def import_ray():
    """The ray module, or ClusterError saying how to install it."""
    try:
        import ray
    except ImportError as exc:
        raise ClusterError(f"Ray is not installed: {INSTALL_HINT}") from exc
    return ray


def check_installed(config: RayConfig):
    """The ray module, after checking it has what `config` asks for (the dashboard needs ray[default])."""
    ray = import_ray()
    if config.dashboard and not config.joining:
        missing = ray._private.utils.get_dashboard_dependency_error()
        if missing:
            raise ClusterError(f"Ray's dashboard needs the full Ray: pip install 'ray[default]=={ray.__version__}' "
                               f"({missing})")
    return ray


@contextmanager
def session(config: RayConfig) -> Iterator[Any]:
    """Connect (or start a local Ray), yield the ray module; shut down only a Ray started here."""
    ray = check_installed(config)
    started = not ray.is_initialized()
    if started:
        local = {} if config.joining else {"num_cpus": config.local_cpus, "include_dashboard": config.dashboard}
        try:
            # "local": a new local Ray even when a `ray start` cluster runs here (that is what `auto` is for)
            ray.init(address=config.address or "local", logging_level=logging.WARNING, **local)
        except (ConnectionError, ValueError, RuntimeError) as exc:
            raise ClusterError(f"cannot start or join Ray at {config.address or 'a local instance'}: {exc}"
                               + (AUTH_HINT if config.joining and "RAY_AUTH_MODE" not in os.environ else "")) from exc
        nodes = sum(1 for node in ray.nodes() if node.get("Alive"))
        log.info("Ray: %g CPUs on %d node(s)", ray.cluster_resources().get("CPU", 0), nodes)
    try:
        yield ray
    finally:
        if started:
            ray.shutdown()


def task_slots(ray, config: RayConfig) -> int:
    """How many tasks of `config.cpus_per_task` CPUs the cluster runs at once (at least 1)."""
    return max(1, int(ray.cluster_resources().get("CPU", 1)) // config.cpus_per_task)


def _remote(ray, fn: Callable, config: RayConfig):
    return ray.remote(fn).options(num_cpus=config.cpus_per_task, max_retries=config.max_retries)


def _drop(refs: list) -> None:
    """Forget tasks whose results are no longer wanted. They are not cancelled: with Ray 2.60,
    ``ray.cancel`` on a task that is finishing (or has just failed) at that moment aborts the whole
    driver process ("Tried to complete task that was not pending"), which was seen in tests here. A local
    Ray started by `session` stops them at shutdown; on a joined cluster they run to completion."""
    if refs:
        log.info("dropping %d Ray task(s) still in flight", len(refs))
    refs.clear()


def _failure(exc: Exception) -> ClusterError:
    cause = getattr(exc, "cause", None)  # a RayTaskError carries the task's own exception
    return ClusterError(f"a Ray task failed: {cause or exc}")


def ordered(fn: Callable, jobs: Iterable[tuple], config: RayConfig, shared: tuple = ()) -> Iterator[Any]:
    """``fn(*shared, *job)`` for every job as Ray tasks, results yielded in job order.

    At most ``in_flight`` jobs are submitted and not yet yielded (finished ones wait for their
    predecessors, so memory stays bounded). ``shared`` values are put in Ray's object store once.
    Closing the generator (an interrupt, an error downstream) stops submitting; the jobs in flight are
    dropped, not cancelled (see `_drop`).
    """
    with session(config) as ray:
        remote = _remote(ray, fn, config)
        shared_refs = [ray.put(value) for value in shared]
        window = config.in_flight or 2 * task_slots(ray, config)
        jobs = iter(jobs)
        queue: list = []  # refs in job order, oldest first
        try:
            while True:
                while len(queue) < window and (job := next(jobs, None)) is not None:
                    queue.append(remote.remote(*shared_refs, *job))
                if not queue:
                    return
                try:
                    result = ray.get(queue[0])
                except ray.exceptions.RayError as exc:
                    raise _failure(exc) from exc
                queue.pop(0)
                yield result
        finally:
            _drop(queue)


def as_completed(
    fn: Callable, jobs: list[tuple], config: RayConfig
) -> Iterator[tuple[tuple, Any | ClusterError]]:
    """``fn(*job)`` for every job as Ray tasks; yields ``(job, result)`` or ``(job, ClusterError)``
    as each finishes. Closing the generator drops the jobs still running (see `_drop`)."""
    with session(config) as ray:
        remote = _remote(ray, fn, config)
        running = {remote.remote(*job): job for job in jobs}
        try:
            while running:
                [ref], _ = ray.wait(list(running), num_returns=1)
                job = running.pop(ref)
                try:
                    yield job, ray.get(ref)
                except ray.exceptions.RayError as exc:
                    yield job, _failure(exc)
        finally:
            _drop(list(running))
