"""Ray task helpers: results in job order with a bounded window, failures as ClusterError, a clear
error without Ray."""

from __future__ import annotations

import sys
import time

import pytest

from neumip.core import cluster
from neumip.core.cluster import ClusterError, RayConfig


def test_missing_ray_says_how_to_install(monkeypatch):
    monkeypatch.setitem(sys.modules, "ray", None)
    with pytest.raises(ClusterError, match=r"pip install 'neumip\[cluster\]'"):
        cluster.import_ray()


@pytest.mark.parametrize("field", [{"cpus_per_task": 0}, {"in_flight": 0}, {"max_retries": -1}])
def test_config_is_validated(field):
    with pytest.raises(ValueError):
        RayConfig(**field)


def later_first(index: int) -> tuple[int, float]:
    """Earlier jobs finish later; returns the job and when it finished."""
    time.sleep(0.05 * (4 - index % 4))
    return index, time.time()


def test_ordered_yields_in_job_order_within_the_window(local_ray):
    taken = []
    for index, finished in cluster.ordered(later_first, [(i,) for i in range(8)], RayConfig(in_flight=3)):
        taken.append((index, finished, time.time()))
    assert [index for index, _, _ in taken] == list(range(8))
    # with a window of 3, job k + 3 is submitted only after job k was taken, so it finishes after
    assert all(taken[k + 3][1] > taken[k][2] for k in range(5))


def fails_on(bad: int, index: int) -> int:
    if index == bad:
        raise ValueError(f"job {index} is bad")
    return index


def test_failures_are_cluster_errors(local_ray):
    with pytest.raises(ClusterError, match="job 2 is bad"):
        list(cluster.ordered(fails_on, [(i,) for i in range(4)], RayConfig(), shared=(2,)))
    results = dict(cluster.as_completed(fails_on, [(1, i) for i in range(3)], RayConfig()))
    assert results[(1, 0)] == 0 and results[(1, 2)] == 2  # the others finish
    assert isinstance(results[(1, 1)], ClusterError) and "job 1 is bad" in str(results[(1, 1)])


@pytest.mark.parametrize("command", [["generate", "flat", "--queries", "10"], ["train-many", "DATA"]])
def test_commands_without_ray_fail_at_once(command, monkeypatch, tmp_path, capsys):
    from neumip.client.cli import main

    monkeypatch.setitem(sys.modules, "ray", None)
    assert main([*command, "-o", str(tmp_path / "out"), "--ray"]) == 2
    assert "Ray is not installed: pip install 'neumip[cluster]'" in capsys.readouterr().err
    assert not (tmp_path / "out").exists()  # nothing started
