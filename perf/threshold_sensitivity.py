"""The board's order at half and double the windows' inclusion thresholds (docs/intervals.md, "The metric's
denominators"): from the per-window tables an evaluate wrote (``<out>/<dataset>/eval/<model>/<terrain>
.windows.parquet``, the commanded protocol), each window's relative errors are recomputed with a minimum
distance of 0.25 / 0.5 / 1.0 m and a minimum rotation of 5 / 10 / 20 deg (one changed at a time), and the
board is ranked as compare ranks it. Prints the table; ``--publish`` also writes it to the generated page
``perf/results/threshold_sensitivity.md``.

    python -m perf.threshold_sensitivity outputs [sim-mini] [--publish]
"""

from __future__ import annotations

import argparse
import shlex
import sys
from pathlib import Path

import numpy as np
import pandas as pd

from skidbench.benchmark.scoring import standings as st
from skidbench.benchmark.scoring.floor import FLOOR

from .pages import dataset_identity, publish

H = 6.0
SETTINGS = [(0.5, 10.0), (0.25, 10.0), (1.0, 10.0), (0.5, 5.0), (0.5, 20.0)]


def read(root: Path) -> dict[tuple[str, str], pd.DataFrame]:
    out = {}
    for path in sorted((root / "eval").glob("*/*.windows.parquet")):
        model, terrain = path.parent.name, path.name.removesuffix(".windows.parquet")
        if "." in terrain or model == FLOOR:  # another protocol's, or the floor (not ranked)
            continue
        w = pd.read_parquet(path)
        if len(w):
            out[(model, terrain)] = w[np.isclose(w["horizon_s"], H)]
    return out


def rethreshold(w: pd.DataFrame, min_m: float, min_deg: float) -> pd.DataFrame:
    w = w.copy()
    with np.errstate(divide="ignore", invalid="ignore"):
        w["rel_trans"] = np.where(w["distance"] >= min_m, w["trans_err"] / w["distance"], np.nan)
        rot = np.deg2rad(min_deg)
        w["rel_rot"] = np.where(w["rotation"] >= rot, np.abs(w["rot_err"]) / w["rotation"], np.nan)
    return w


def table(windows: dict[tuple[str, str], pd.DataFrame]) -> str:
    lines = [
        "| thresholds | order: mean of 4 % (rank); the first's standing | trans / rot windows |",
        "|---|---|---|",
    ]
    for min_m, min_deg in SETTINGS:
        ws = {k: rethreshold(w, min_m, min_deg) for k, w in windows.items()}
        ov = st.build(ws, H).overall.sort_values("estimate")
        order = ", ".join(f"{r.model} {r.estimate:.2f} ({r.rank or '-'})" for r in ov.itertuples())
        some = next(iter(ws.values()))
        n_t, n_r = int(some["rel_trans"].notna().sum()), int(some["rel_rot"].notna().sum())
        lines.append(f"| {min_m:g} m, {min_deg:g} deg | {order}; {ov.iloc[0]['standing']} | {n_t} / {n_r} |")
        print(lines[-1], flush=True)
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(
        prog="python -m perf.threshold_sensitivity", description=__doc__.split("\n")[0]
    )
    ap.add_argument("out_root", type=Path)
    ap.add_argument("dataset", nargs="?", default="sim-mini")
    ap.add_argument("--publish", action="store_true", help="also write perf/results/threshold_sensitivity.md")
    a = ap.parse_args(argv)
    root = a.out_root / a.dataset
    windows = read(root)
    if not windows:
        raise SystemExit(f"{root / 'eval'}: no windows of an evaluate (run skidbench evaluate first)")
    text = table(windows)
    if a.publish:
        command = "python -m perf.threshold_sensitivity " + shlex.join(sys.argv[1:] if argv is None else argv)
        command = command.replace(str(a.out_root), "<out>")  # the page is committed: no machine's path
        models = sorted({m for m, _ in windows})
        about = (
            f"Dataset {dataset_identity(root)}, `commanded`, {H:g} s; the windows of {len(models)} models "
            f"({', '.join(models)}) on {len({t for _, t in windows})} terrains, ranked as compare ranks them "
            "(the mean of the four RMSREs over the terrains)."
        )
        print(publish("threshold_sensitivity", command, about, text))


if __name__ == "__main__":
    main()
