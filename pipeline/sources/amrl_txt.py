"""``source=amrl_txt``: the public AMRL skid-steer release as distributed (SPEC.md, "extract").

Layout ``<root>/{Asphalt,Grass,Tile}/{ConstantVel,Train,LongDistance}/{cmd,loc}/N.txt``, no headers,
comma or whitespace separated:
- ``cmd/N.txt`` rows ``v_x, v_y, v_z, w_x, w_y, w_z, time_s`` (Twist commands) -> table ``cmd_vel``;
- ``loc/N.txt`` rows ``time_s, x, y, heading_rad`` (ground-truth poses from visual odometry) -> ``gt_pose``.

Sequences are named ``<terrain>_<category>_<NN>`` (terrain lower-case; ConstantVel -> cv, Train -> train,
LongDistance -> ld). Checks and documented repairs (logged):
- a row with the wrong number of values, a non-numeric value, an empty file, a cmd file without its loc
  file, time that goes backwards: a one-line SourceError naming the file;
- duplicated cmd stamps: the later command is kept (it is the one the controller acted on);
- a loc file that covers less time than its cmd file: kept; the split stage uses only the overlap (the
  uncovered command time has no ground truth), and the shortfall is logged.
"""

from __future__ import annotations

import io
import logging
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from skidbench.pipeline.core.errors import SourceError
from skidbench.pipeline.core.manifest import Sequence
from skidbench.pipeline.sources.contract import (
    TWIST_COLUMNS,
    SourceContext,
    SourceData,
    SourceSequence,
    Tables,
    TableSource,
    stamped,
)

log = logging.getLogger(__name__)

CATEGORY_DIRS = {"Train": "train", "ConstantVel": "cv", "LongDistance": "ld"}
TERRAIN_DIRS = ("Asphalt", "Grass", "Tile")


def read_rows(path: Path, ncols: int) -> np.ndarray:
    """A headerless numeric text file with ``ncols`` values a row (comma and/or whitespace separated)."""
    try:
        text = path.read_text()
    except OSError as exc:
        raise SourceError(f"{path}: cannot read ({exc.strerror})") from exc
    lines = [ln for ln in text.splitlines() if ln.strip() and not ln.lstrip().startswith("#")]
    if not lines:
        raise SourceError(f"{path}: empty sequence (no rows)")
    sep = re.compile(r"[,\s]+")
    counts = np.array([len(sep.split(ln.strip())) for ln in lines])
    bad = np.flatnonzero(counts != ncols)
    if len(bad):
        i = int(bad[0])
        raise SourceError(f"{path}:{i + 1}: expected {ncols} values a row, found {counts[i]}")
    try:
        return np.loadtxt(io.StringIO("\n".join(sep.sub(" ", ln.strip()) for ln in lines)), ndmin=2)
    except ValueError as exc:
        raise SourceError(f"{path}: non-numeric value ({exc})") from exc


def _stamps(t_s: np.ndarray, path: Path) -> np.ndarray:
    if not np.isfinite(t_s).all():
        raise SourceError(f"{path}: time column holds NaN/inf")
    back = np.flatnonzero(np.diff(t_s) < 0)
    if len(back):
        i = int(back[0]) + 1
        raise SourceError(f"{path}:{i + 1}: non-monotonic time ({t_s[i]} s after {t_s[i - 1]} s)")
    return np.round(t_s * 1e9).astype(np.int64)


def discover(root: Path) -> list[tuple[Sequence, Path, Path]]:
    """Every (sequence, cmd file, loc file) under ``root``."""
    root = Path(root)
    if not root.is_dir():
        raise SourceError(f"{root}: no such folder; set source.root to the AMRL release")
    out = []
    for terrain in sorted(p for p in root.iterdir() if p.is_dir() and p.name in TERRAIN_DIRS):
        for cat_dir in sorted(p for p in terrain.iterdir() if p.is_dir() and p.name in CATEGORY_DIRS):
            cmds = sorted((cat_dir / "cmd").glob("*.txt"), key=lambda p: (len(p.stem), p.stem))
            for cmd in cmds:
                loc = cat_dir / "loc" / cmd.name
                if not loc.is_file():
                    raise SourceError(f"{cmd}: no matching loc file {loc}")
                cat = CATEGORY_DIRS[cat_dir.name]
                name = f"{terrain.name.lower()}_{cat}_{int(cmd.stem) if cmd.stem.isdigit() else cmd.stem:02}"
                rel = str(cmd)  # absolute: the manifest lives under out_root, not here
                out.append((Sequence(name, terrain.name.lower(), cat, rel), cmd, loc))
    if not out:
        raise SourceError(
            f"{root}: no AMRL sequences (expected {{Asphalt,Grass,Tile}}/{{ConstantVel,Train,LongDistance}}"
            "/{cmd,loc}/N.txt); set source.root"
        )
    return out


def read_sequence(cmd: Path, loc: Path) -> Tables:
    """The extracted tables of one sequence (``cmd_vel``, ``gt_pose``)."""
    c = read_rows(cmd, 7)
    cmd_ns = _stamps(c[:, 6], cmd)
    dup = np.concatenate([np.diff(cmd_ns) == 0, [False]])
    if dup.any():
        log.warning("%s: %d duplicated stamp(s); kept the later command", cmd, int(dup.sum()))
        c, cmd_ns = c[~dup], cmd_ns[~dup]
    g = read_rows(loc, 4)
    loc_ns = _stamps(g[:, 0], loc)
    short = max(loc_ns[0] - cmd_ns[0], 0) + max(cmd_ns[-1] - loc_ns[-1], 0)
    if short > 1e9:
        log.warning(
            "%s is shorter than %s by %.2f s: only the overlap %.2f..%.2f s has ground truth",
            loc, cmd, short * 1e-9, max(loc_ns[0], cmd_ns[0]) * 1e-9, min(loc_ns[-1], cmd_ns[-1]) * 1e-9,
        )  # fmt: skip
    if loc_ns[-1] <= cmd_ns[0] or loc_ns[0] >= cmd_ns[-1]:
        raise SourceError(
            f"{loc}: no time overlap with {cmd} (loc {loc_ns[0] * 1e-9:.2f}..{loc_ns[-1] * 1e-9:.2f} s)"
        )
    cmd_vel = stamped(cmd_ns, **{k: c[:, i] for i, k in enumerate(TWIST_COLUMNS)})
    gt = stamped(loc_ns, x=g[:, 1], y=g[:, 2], yaw=g[:, 3])
    return Tables(cmd_vel=cmd_vel, gt_pose=gt)


@dataclass(frozen=True)
class AmrlSettings:
    """``source.*`` of ``source=amrl_txt``: the release's folder."""

    root: str


class AmrlText(TableSource):
    """The AMRL release (module docstring): one sequence per cmd/loc pair under ``root``."""

    kind = "amrl_txt"
    version = 1
    Settings = AmrlSettings

    def inputs(self, settings: AmrlSettings) -> list[Path]:
        return [p for _, cmd, loc in discover(_root(settings)) for p in (cmd, loc)]

    def read(self, settings: AmrlSettings, ctx: SourceContext) -> SourceData:
        seqs = []
        for seq, cmd, loc in discover(_root(settings)):
            tables = read_sequence(cmd, loc)
            seqs.append(SourceSequence(seq.name, seq.terrain, seq.category, tables, (cmd, loc)))
        return SourceData(tuple(seqs), format="amrl_txt")


def _root(settings: AmrlSettings) -> Path:
    return Path(str(settings.root)).expanduser().absolute()
