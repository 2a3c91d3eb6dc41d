"""Results keyed by what made them (benchmark/evaluate/reuse.py): the one-line reason an evaluate gives for
running a model again names what changed since its recorded run (its code with both digests, the scoring
code, the data, the settings that differ, a damaged output), and nothing when nothing changed."""

from __future__ import annotations

import pytest

from skidbench.benchmark.evaluate import reuse
from skidbench.pipeline.core.cache import Stamp

MADE = {
    "fit": "fitkey",
    "code": {"distribution": "skidbench-tame", "version": "0.1", "digest": "a" * 32},
    "scoring": "s" * 32,
    "data": "d" * 32,
    "settings": {"horizons": [6.0], "min_distance_m": 0.5},
}


def _recorded(tmp_path):
    """A stamp of a finished run made of MADE, with its per-window table as output."""
    out = tmp_path / "tile.windows.parquet"
    out.write_bytes(b"windows")
    stamp = Stamp(tmp_path / "stamps" / "tile.json", "evaluate")
    rk = reuse.ResultKey("tame", "tile", stamp.key([], MADE), stamp)
    reuse.record(rk, [out], "1a2b3c4d" * 4, "p" * 32, type("T", (), {"uri": "u", "experiment_name": "e"}))
    return out


def _now(tmp_path, **changes):
    stamp = Stamp(tmp_path / "stamps" / "tile.json", "evaluate")
    return reuse.ResultKey("tame", "tile", stamp.key([], {**MADE, **changes}), stamp)


@pytest.mark.parametrize(
    "changes, said",
    [
        ({}, None),
        (
            {"code": {**MADE["code"], "digest": "b" * 32}},
            f"its code changed (digest {'a' * 12} -> {'b' * 12})",
        ),
        ({"code": {**MADE["code"], "version": "0.2"}}, "its version changed (0.1 -> 0.2)"),
        ({"scoring": "t" * 32}, f"the scoring code changed (digest {'s' * 12} -> {'t' * 12})"),
        ({"data": "e" * 32}, "its split files changed"),
        (
            {"settings": {"horizons": [6.0], "min_distance_m": 2.0}},
            "the evaluate's settings changed (min_distance_m)",
        ),
    ],
)
def test_the_reason_to_run_again_names_what_changed_since_the_recorded_run(tmp_path, changes, said):
    _recorded(tmp_path)
    why = reuse.why_again(_now(tmp_path, **changes))
    assert why == (None if said is None else f"{said} since run 1a2b3c4d")


def test_a_damaged_output_is_a_reason_to_run_again_and_a_first_run_is_none(tmp_path):
    out = _recorded(tmp_path)
    out.write_bytes(b"truncated")
    assert reuse.why_again(_now(tmp_path)).endswith("fails its fingerprint (corrupted?) since run 1a2b3c4d")
    assert reuse.why_again(_now(tmp_path / "elsewhere")) is None  # never ran there: nothing to say
