"""`make reproduce` runs its two evaluates side by side (pipeline/runner/side_by_side.py): they must run at
the same
time, print as if they had run in turn, and fail `make` as the first failing one would have."""

from __future__ import annotations

import sys
import time

from skidbench.pipeline.runner.side_by_side import run, split_commands


def py(code: str) -> list[str]:
    return [sys.executable, "-c", code]


def test_commands_are_cut_at_the_separator():
    assert split_commands(["a", "x=1", "::", "b", "::", "::", "c", "y"]) == [["a", "x=1"], ["b"], ["c", "y"]]
    assert split_commands([]) == []


def test_outputs_come_in_command_order_while_the_commands_overlap(capfd, tmp_path):
    # the second command finishes first and the first waits for it: one after the other they would hang
    # (the timeout), side by side both end; the output still reads first, then second (stderr included)
    flag = tmp_path / "second-ran"
    first = py(
        "import pathlib, sys, time\n"
        f"p = pathlib.Path({str(flag)!r})\n"
        "t = time.monotonic()\n"
        "while not p.exists() and time.monotonic() - t < 30: time.sleep(0.01)\n"
        "print('first', p.exists())"
    )
    second = py(
        f"import pathlib, sys; pathlib.Path({str(flag)!r}).touch(); print('second out'); "
        "print('second err', file=sys.stderr)"
    )
    started = time.monotonic()
    assert run([first, second]) == 0
    assert time.monotonic() - started < 30
    out = capfd.readouterr().out
    assert out.splitlines() == ["first True", "second out", "second err"]


def test_the_first_failure_in_command_order_is_the_status(capfd):
    assert run([py("print('a')"), py("import sys; print('b'); sys.exit(3)"), py("raise SystemExit(2)")]) == 3
    assert capfd.readouterr().out.splitlines() == ["a", "b"]
    assert run([py("raise SystemExit(4)"), py("print('still printed')")]) == 4
    assert "still printed" in capfd.readouterr().out


def test_each_command_gets_its_share_of_the_cores_for_blas_threads(monkeypatch):
    """n commands at once: each numerical library's thread count at cores // n (at least one), unless the
    user set it."""
    from skidbench.pipeline.runner import side_by_side as sbs

    monkeypatch.setattr(sbs, "cores", lambda: 8)
    env = sbs.shared_env(2, {"PATH": "/bin", "OMP_NUM_THREADS": "3"})
    assert env["OPENBLAS_NUM_THREADS"] == "4" and env["MKL_NUM_THREADS"] == "4"
    assert env["OMP_NUM_THREADS"] == "3" and env["PATH"] == "/bin"  # the user's setting is kept
    monkeypatch.setattr(sbs, "cores", lambda: 2)
    assert sbs.shared_env(3, {})["OPENBLAS_NUM_THREADS"] == "1"


def test_the_commands_run_with_the_shared_thread_counts(capfd, monkeypatch):
    from skidbench.pipeline.runner import side_by_side as sbs

    monkeypatch.delenv("OPENBLAS_NUM_THREADS", raising=False)
    monkeypatch.setattr(sbs, "cores", lambda: 4)
    show = [sys.executable, "-c", "import os; print(os.environ['OPENBLAS_NUM_THREADS'])"]
    assert sbs.run([show, show]) == 0
    assert capfd.readouterr().out.split() == ["2", "2"]
