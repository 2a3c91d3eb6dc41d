"""The README's (and docs/*.md's) commands are tests: every fenced block carries a marker, an HTML comment
on the line before it, that says what the block is and how it is tested:

    <!-- doc-test: run [slow] [shared] [lines=1,2] [cwd=<dir>] [root=quickstart]
                       [<placeholder>[@line]=<value> ...] [sub:<word>=<value> ...] -->
        its commands are executed (bash, in order; the selected lines only), on the tiny simulated dataset
        (``SCALE=tiny`` for make, ``SKIDBENCH_OUT``/``OUT`` a temporary root; the quick start in its own,
        once per session, shared with tests/test_e2e.py);
        ``root=quickstart``: with ``SKIDBENCH_OUT``/``OUT`` the quick start's root, evaluated (the block
        only reads it: what it writes goes under ``$TMP``, a fresh folder, its default ``cwd``);
        ``sub:<word>=<value>``: a literal word replaced (``sub:sim-mini=sim-tiny``);
        ``shared``: skipped when ../shared/data/real is absent; ``slow``: marked slow
    <!-- doc-test: check [lines=...] [<placeholder>=<value> ...] -->
        each ``skidbench <stage> ...`` command (and each stage that ``make reproduce|discover`` runs, with
        its SOURCE, DATA and ARGS) has its overrides and values checked as the CLI checks them before a
        stage starts (unknown keys, group options, the declared schema), without running it: for
        commands that need a cluster, a server or data we do not have
    <!-- doc-test: output -->           printed output, not commands
    <!-- doc-test: skip <reason> -->    not runnable in a test (the reason is required)

An unmarked block fails the test, so a new documented command is a decision, not an accident. In the
values, ``$OUT`` (the temporary output root), ``$REPO`` (this checkout) and ``$SHARED``
(../shared/data/real) are expanded by bash. A placeholder ``<dir>`` not given a value is replaced by a
dummy word in ``check`` blocks."""

from __future__ import annotations

import re
import shlex
from pathlib import Path

import pytest
from conftest import SHARED_REAL
from doc_blocks import BLOCKS, MODES, REPO, commands, doc_env, parse_blocks, publishing, quickstart, run_block

from skidbench.pipeline.cli.overrides import check_overrides, validate

MAKE_STAGES = {  # what the Makefile's targets run (make reproduce / make discover)
    "reproduce": ("extract", "groundtruth", "split", "calibrate", "evaluate", "compare"),
    "discover": ("extract", "groundtruth", "split", "calibrate", "discover", "evaluate", "compare"),
}


def test_every_block_is_marked():
    bad = [f"{b.id} ({b.text[0][:60] if b.text else ''})" for b in BLOCKS if b.mode not in MODES]
    assert not bad, f"mark each fenced block with <!-- doc-test: run|check|output|skip ... -->: {bad}"
    skips = [b.id for b in BLOCKS if b.mode == "skip" and not b.args]
    assert not skips, f"a skipped block says why: {skips}"


def test_the_markers_cover_the_documented_recipes():
    """The README's own-data recipes are at least checked; the quick start runs."""
    modes = {b.text[0].split("#")[0].strip(): b.mode for b in BLOCKS if b.text}
    assert modes.get("make reproduce") == "run"
    assert sum(b.mode in ("run", "check") for b in BLOCKS) >= 8


# -- check: the overrides of every command, as the CLI checks them before a stage starts --------------
def _stage_lines(cmd: str) -> list[tuple[str, list[str]]]:
    """(stage, overrides) of a ``skidbench`` or ``make reproduce|discover`` command line."""
    cmd = re.sub(r"<[^<>]*>", "x", cmd.split(" #")[0])  # placeholders left: a dummy word
    words = shlex.split(cmd)
    env = {}
    while words and re.match(r"^[A-Z_]+=", words[0]):  # VAR=value before the command
        k, v = words.pop(0).split("=", 1)
        env[k] = v
    if words[:1] == ["skidbench"] and len(words) > 1:
        return [(words[1], _positional(words[1], words[2:]))]
    if words[:1] == ["make"] and len(words) > 1 and words[1] in MAKE_STAGES:
        make = dict(env, **dict(w.split("=", 1) for w in words[2:] if "=" in w))
        source = make.get("SOURCE", "sim")
        base = (
            [f"scale={make.get('SCALE', 'mini')}", f"seed={make.get('SEED', '0')}"]
            if source == "sim"
            else [f"source={source}", f"source.root={make.get('DATA', 'x')}"]
        )
        args = shlex.split(make.get("ARGS", ""))
        return [(stage, [*base, *args]) for stage in MAKE_STAGES[words[1]]]
    return []


def _positional(stage: str, args: list[str]) -> list[str]:
    """A stage's positional arguments (``skidbench export <dataset> <dir>``) as the CLI turns them into
    overrides (``pipeline/cli/main.py`` ``positional_overrides``)."""
    import importlib

    from skidbench.pipeline.cli.main import STAGES, positional_overrides

    if stage not in STAGES:
        return args
    module, func = STAGES[stage][0].split(":")
    return positional_overrides(stage, getattr(importlib.import_module(module), func), args)


CHECKED = [
    pytest.param(b, n, cmd, id=f"{b.id}#{n}")
    for b in BLOCKS
    if b.mode in ("check", "run")
    for n, cmd in commands(b, every=b.mode == "run")
    if _stage_lines(cmd)
]


@pytest.mark.parametrize(("block", "n", "cmd"), CHECKED)
def test_documented_commands_pass_the_config_checks(block, n, cmd, monkeypatch, tmp_path):
    monkeypatch.setenv("SKIDBENCH_OUT", str(tmp_path))
    for var, value in (("$OUT", str(tmp_path)), ("$REPO", str(REPO)), ("$SHARED", str(SHARED_REAL))):
        cmd = cmd.replace(var, value)
    for stage, overrides in _stage_lines(cmd):
        if stage in ("inspect", "models"):
            continue
        try:
            dropped, cfg = check_overrides(stage, overrides)
            if cfg is not None:
                validate(cfg)
        except Exception as exc:  # noqa: BLE001 - the message is the point
            pytest.fail(f"{block.id} command {n}, stage {stage}: {exc}")


# -- run: the blocks a user is told to run, executed -------------------------------------------------
# Every run block runs in a temporary output root, once per session. The quick start (``make reproduce``,
# the longest) runs in its own root through the session fixture ``readme_reproduce`` (tests/conftest.py):
# tests/test_e2e.py asserts on what that same run wrote instead of building its own tiny pipeline.
@pytest.fixture(scope="module")
def doc_out(tmp_path_factory) -> dict[str, str]:
    """One output root for the other run blocks."""
    return doc_env(tmp_path_factory.mktemp("docs_out"))


RUN = [
    pytest.param(b, id=b.id, marks=[pytest.mark.slow] if "slow" in b.opts["flags"] else [])
    for b in BLOCKS
    if b.mode == "run"
]


@pytest.mark.parametrize("block", RUN)
def test_documented_blocks_run_as_written(block, request):
    if "shared" in block.opts["flags"] and not SHARED_REAL.is_dir():
        pytest.skip("../shared/data/real is absent")
    if block.id == quickstart().id:  # executed once per session (run_block), its results read here
        results = request.getfixturevalue("readme_reproduce")["results"]
    elif block.id in {b.id for b in publishing()}:  # once per session too: tests/test_release.py reads them
        walked = request.getfixturevalue("publishing_walkthrough")["results"]
        results = [r for r in walked if r["block"] == block.id]
    elif block.opts["root"] == "quickstart":  # on the quick start's evaluated root, writing under $TMP only
        tmp = request.getfixturevalue("tmp_path")
        env = {**doc_env(Path(request.getfixturevalue("readme_reproduce")["root"])), "TMP": str(tmp)}
        block.opts["cwd"] = block.opts["cwd"] or "$TMP"
        results = run_block(block, env)
    else:
        results = run_block(block, request.getfixturevalue("doc_out"))
    for r in results:
        assert r["returncode"] == 0, f"{block.id} command {r['n']}: {r['cmd']}\n{r['stderr'][-3000:]}"
    expected = [n for n, cmd in commands(block) if "$SHARED" not in cmd or SHARED_REAL.is_dir()]
    assert [r["n"] for r in results] == expected


def test_the_check_refuses_a_misspelt_documented_command(tmp_path):
    doc = tmp_path / "doc.md"
    doc.write_text('<!-- doc-test: check -->\n```\nmake reproduce ARGS="groundtruth.methd=vo"\n```\n')
    (block,) = parse_blocks(doc)
    ((_, cmd),) = commands(block)
    stage, overrides = _stage_lines(cmd)[0]
    with pytest.raises(Exception, match="groundtruth.methd"):
        check_overrides(stage, overrides)
