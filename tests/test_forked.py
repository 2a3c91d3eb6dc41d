"""Stages map their independent items in forked workers (pipeline/runner/forked.py): the results must be those
of the plain loop, in call order, and a failing item must fail the stage as it would alone."""

from __future__ import annotations

import os

import pytest

from skidbench.pipeline.core.errors import ExtractError
from skidbench.pipeline.runner import forked


def _square_and_pid(x: int) -> tuple[int, int]:
    return x * x, os.getpid()


def _fails_on_three(x: int) -> int:
    if x == 3:
        raise ExtractError(f"bag {x}: truncated")
    return x


def test_results_in_call_order_from_other_processes(monkeypatch):
    monkeypatch.setattr(forked, "cores", lambda: 2)
    seen = []
    out = forked.map_forked(_square_and_pid, [(x,) for x in range(7)], lambda i, r: seen.append(i))
    assert [r[0] for r in out] == [x * x for x in range(7)]
    assert sorted(seen) == list(range(7))
    assert os.getpid() not in {r[1] for r in out}  # forked workers did the work


def test_one_core_or_one_call_runs_here(monkeypatch):
    monkeypatch.setattr(forked, "cores", lambda: 1)
    assert {r[1] for r in forked.map_forked(_square_and_pid, [(1,), (2,)])} == {os.getpid()}
    monkeypatch.setattr(forked, "cores", lambda: 2)
    assert forked.map_forked(_square_and_pid, [(4,)])[0] == (16, os.getpid())


def test_an_item_error_reaches_the_stage_as_itself(monkeypatch):
    monkeypatch.setattr(forked, "cores", lambda: 2)
    with pytest.raises(ExtractError, match="bag 3: truncated"):
        forked.map_forked(_fails_on_three, [(x,) for x in range(6)])


def _blas_threads(_: int) -> int:
    from threadpoolctl import threadpool_info

    return max((i["num_threads"] for i in threadpool_info() if i["user_api"] == "blas"), default=1)


def test_each_worker_gets_its_share_of_the_cores_for_blas(monkeypatch):
    """Two workers on two cores: one BLAS thread each (a forked worker would inherit the parent's two); this
    process's own pool is left as it was."""
    from threadpoolctl import threadpool_limits

    monkeypatch.setattr(forked, "cores", lambda: 2)
    with threadpool_limits(limits=2, user_api="blas"):  # as a 2-core machine starts it
        assert _blas_threads(0) == 2
        assert forked.map_forked(_blas_threads, [(0,), (1,)]) == [1, 1]
        assert _blas_threads(0) == 2
