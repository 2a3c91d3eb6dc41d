"""The fenced blocks of README.md and docs/*.md with their ``doc-test`` markers (the syntax is described in
tests/test_docs_commands.py), and how a ``run`` block is executed: shared by that test and by the session
fixtures that run the README's quick start and docs/publishing.md's walkthrough once (tests/conftest.py
``readme_reproduce``, ``publishing_walkthrough``)."""

from __future__ import annotations

import os
import re
import shlex
import subprocess
import sys
from dataclasses import dataclass, field
from pathlib import Path

from conftest import SHARED_REAL

REPO = Path(__file__).resolve().parents[1]
DOCS = [REPO / "README.md", *sorted((REPO / "docs").glob("*.md"))]
MARKER = re.compile(r"^<!--\s*doc-test:\s*(\w+)\s*(.*?)\s*-->\s*$")
MODES = ("run", "check", "output", "skip")


@dataclass
class Block:
    doc: Path
    line: int  # of the opening fence, 1-based
    text: list[str]
    mode: str | None
    args: str = ""
    opts: dict = field(default_factory=dict)

    @property
    def id(self) -> str:
        return f"{self.doc.name}:{self.line}"


def parse_blocks(path: Path) -> list[Block]:
    """Every fenced block of a Markdown file with its marker (None when unmarked)."""
    lines = path.read_text().splitlines()
    blocks, i = [], 0
    while i < len(lines):
        if lines[i].startswith("```"):
            j = i + 1
            while j < len(lines) and not lines[j].startswith("```"):
                j += 1
            m = MARKER.match(lines[i - 1].strip()) if i else None
            b = Block(path, i + 1, lines[i + 1 : j], m.group(1) if m else None, m.group(2) if m else "")
            b.opts = _options(b.args)
            blocks.append(b)
            i = j + 1
        else:
            i += 1
    return blocks


def _options(args: str) -> dict:
    opts: dict = {"flags": set(), "subs": [], "lines": None, "cwd": None, "root": None}
    for tok in shlex.split(args):
        if tok in ("slow", "shared"):
            opts["flags"].add(tok)
        elif tok.startswith("lines="):
            opts["lines"] = {int(n) for n in tok[6:].split(",")}
        elif tok.startswith("cwd="):
            opts["cwd"] = tok[4:]
        elif tok.startswith("root="):
            opts["root"] = tok[5:]
        elif tok.startswith("sub:") and "=" in tok:  # a literal word replaced (sub:sim-mini=sim-tiny)
            name, value = tok[4:].split("=", 1)
            opts["subs"].append((name, None, value))
        elif tok.startswith("<") and "=" in tok:
            name, value = tok.split("=", 1)
            name, _, at = name.partition("@")
            opts["subs"].append((name, int(at) if at else None, value))
    return opts


def commands(block: Block, every: bool = False) -> list[tuple[int, str]]:
    """(command number, command) of a block: continuation lines joined, comments and blank lines out; in
    a block that shows a prompt (``$ ``), only the prompted lines. The marker's ``lines`` only, unless
    ``every`` (a run block's other lines are still checked)."""
    prompted = any(ln.startswith("$ ") for ln in block.text)
    cmds, buf = [], ""
    for ln in block.text:
        if prompted:
            if not ln.startswith("$ "):
                continue
            ln = ln[2:]
        s = ln.rstrip()
        if not buf and (not s.strip() or s.lstrip().startswith("#")):
            continue
        if s.endswith("\\"):
            buf += s[:-1] + " "
            continue
        cmds.append(buf + s)
        buf = ""
    out = []
    for n, cmd in enumerate(cmds, 1):
        for name, at, value in block.opts["subs"]:
            if at in (None, n):
                cmd = cmd.replace(name, value)
        if every or block.opts["lines"] is None or n in block.opts["lines"]:
            out.append((n, cmd))
    return out


BLOCKS = [b for doc in DOCS for b in parse_blocks(doc)]


def quickstart() -> Block:
    """The README's quick-start block: the ``run`` block whose first line is ``make reproduce``."""
    (block,) = [b for b in BLOCKS if b.doc.name == "README.md" and b.text and b.text[0].split("#")[0].strip()
                == "make reproduce"]  # fmt: skip
    return block


def publishing() -> list[Block]:
    """docs/publishing.md's walkthroughs, its ``run`` blocks in order, on the quick start's root and one
    folder: the maintainer releases (export), a lab submits (import the public half, predict, check), the
    maintainer scores and publishes (import with the answers, score, compare, publish)."""
    return [b for b in BLOCKS if b.doc.name == "publishing.md" and b.mode == "run"]


def doc_env(out: Path) -> dict[str, str]:
    """The environment of a ``run`` block: the tiny simulated dataset (``SCALE=tiny``), ``out`` as the output
    root (``SKIDBENCH_OUT`` and make's ``OUT``), this interpreter's scripts first on PATH, no inherited
    MLflow store; ``$REPO`` and ``$SHARED`` for the commands."""
    env = {k: v for k, v in os.environ.items() if k != "MLFLOW_TRACKING_URI"}
    bin_dir = str(Path(sys.executable).parent)
    env.update(
        PATH=f"{bin_dir}{os.pathsep}{env.get('PATH', '')}",
        SKIDBENCH_OUT=str(out),
        OUT=str(out),
        SCALE="tiny",
        REPO=str(REPO),
        SHARED=str(SHARED_REAL),
    )
    return env


def run_block(block: Block, env: dict[str, str]) -> list[dict]:
    """Execute a ``run`` block's commands in order (bash, ``set -euo pipefail``) in its ``cwd`` (default this
    checkout), up to the first that fails; a command naming ``$SHARED`` is left out when ../shared is
    absent. Returns per command executed: ``n``, ``cmd``, ``returncode``, ``stdout``, ``stderr``."""
    cwd = block.opts["cwd"] or str(REPO)
    cwd = cwd.replace("$SHARED", str(SHARED_REAL)).replace("$REPO", str(REPO)).replace("$OUT", env["OUT"])
    cwd = cwd.replace("$TMP", env.get("TMP", ""))
    results = []
    for n, cmd in commands(block):
        if "$SHARED" in cmd and not SHARED_REAL.is_dir():
            continue
        proc = subprocess.run(
            ["bash", "-c", f"set -euo pipefail; {cmd}"],
            cwd=cwd, env=env, capture_output=True, text=True, timeout=1800,
        )  # fmt: skip
        results.append(
            {"n": n, "cmd": cmd, "returncode": proc.returncode, "stdout": proc.stdout, "stderr": proc.stderr}
        )
        if proc.returncode != 0:
            break
    return results
