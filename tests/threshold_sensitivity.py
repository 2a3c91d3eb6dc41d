"""The board's order at half and double the windows' inclusion thresholds (docs/intervals.md, "The metric's
denominators"): from the per-window tables an evaluate wrote (``<out>/<dataset>/eval/<model>/<terrain>
.windows.parquet``, the commanded protocol), each window's relative errors are recomputed with a minimum
distance of 0.25 / 0.5 / 1.0 m and a minimum rotation of 5 / 10 / 20 deg (one changed at a time), and the
board is ranked as compare ranks it. Not a test: it prints the table the doc quotes.

    .venv/bin/python tests/threshold_sensitivity.py outputs [sim-mini]
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pandas as pd

from skidbench.benchmark.scoring import standings as st
from skidbench.benchmark.scoring.floor import FLOOR

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


def main() -> None:
    out = Path(sys.argv[1])
    root = out / (sys.argv[2] if len(sys.argv) > 2 else "sim-mini")
    windows = read(root)
    print("| thresholds | order: mean of 4 % (rank); the first's standing | trans / rot windows |")
    print("|---|---|---|")
    for min_m, min_deg in SETTINGS:
        ws = {k: rethreshold(w, min_m, min_deg) for k, w in windows.items()}
        ov = st.build(ws, H).overall.sort_values("estimate")
        order = ", ".join(f"{r.model} {r.estimate:.2f} ({r.rank or '-'})" for r in ov.itertuples())
        some = next(iter(ws.values()))
        n_t, n_r = int(some["rel_trans"].notna().sum()), int(some["rel_rot"].notna().sum())
        print(
            f"| {min_m:g} m, {min_deg:g} deg | {order}; {ov.iloc[0]['standing']} | {n_t} / {n_r} |",
            flush=True,
        )


if __name__ == "__main__":
    main()
