"""Killing a Ray worker process mid-task, from outside (as the OOM killer or a lost node would)."""

from __future__ import annotations

import os
import signal
import threading
import time
from contextlib import contextmanager
from pathlib import Path
from typing import Callable, Iterator


def parent_pid() -> int:
    return os.getppid()


def busy_workers(raylet: int, function: str) -> list[int]:
    """PIDs of the raylet's workers running `function` now (Ray titles a busy worker ray::FUNCTION)."""
    pids = []
    for proc in Path("/proc").iterdir():
        try:
            if (proc.name.isdigit() and (proc / "cmdline").read_bytes().startswith(f"ray::{function}".encode())
                    and int((proc / "stat").read_text().rsplit(")", 1)[1].split()[1]) == raylet):
                pids.append(int(proc.name))
        except (OSError, ValueError, IndexError):
            continue
    return pids


@contextmanager
def killing_the_first_busy_worker(
    ray, function: str, when: Callable[[], bool] = lambda: True
) -> Iterator[list[int]]:
    """While inside, SIGKILL the first worker of this Ray seen running `function` once `when()` is
    true; yields the list that receives its PID."""
    raylet = ray.get(ray.remote(parent_pid).remote())  # the workers' parent
    killed: list[int] = []
    stop = threading.Event()

    def watch() -> None:
        while not (stop.is_set() or killed):
            if when():
                for pid in busy_workers(raylet, function)[:1]:
                    os.kill(pid, signal.SIGKILL)
                    killed.append(pid)
            time.sleep(0.002)

    watcher = threading.Thread(target=watch)
    watcher.start()
    try:
        yield killed
    finally:
        stop.set()
        watcher.join()
