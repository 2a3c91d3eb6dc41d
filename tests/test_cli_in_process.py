"""The tests' in-process runner of ``skidbench`` (tests/reliability_data.py ``in_process``: the console
script's ``main`` in the test's process, for runs whose process is not what is tested) gives what the
console script's process gives: the exit status, stdout and stderr, the refusal's one line included; and
the environment and folder it ran in do not leak into the test's process. What a stage's forked workers
print is kept too: tests/test_reliability_faults.py's truncated-Parquet case reads extract's worker's
"fails its fingerprint" from it."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest
from reliability_data import in_process

SKIDBENCH = str(Path(sys.executable).with_name("skidbench"))


@pytest.mark.parametrize(
    "argv", [["nosuchstage"], ["split", "scale=tiny", "nonsense=1"]], ids=["unknown stage", "refused key"]
)
def test_in_process_gives_the_console_scripts_status_and_output(argv, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    env = {**os.environ, "SKIDBENCH_OUT": str(tmp_path / "out"), "SKIDBENCH_IN_PROCESS_PROBE": "1"}
    proc = subprocess.run([SKIDBENCH, *argv], env=env, capture_output=True, text=True, timeout=300)
    here = in_process(argv, env, cwd=tmp_path / "..")
    assert proc.returncode == 2 and proc.stderr.startswith("skidbench")  # a refusal, not a crash
    assert (here.returncode, here.stdout, here.stderr) == (proc.returncode, proc.stdout, proc.stderr)
    assert "SKIDBENCH_IN_PROCESS_PROBE" not in os.environ and Path.cwd() == tmp_path
