"""A model from outside skidbench, scored from a file: the ideal differential drive, written without
skidbench (numpy and pandas only), as another lab would run its own model (C++, PyTorch, ...).

    python examples/predict_ideal.py <bundle> <predictions.parquet|.csv> [protocol]

Reads the public half of a bundle (``skidbench export``'s ``<dir>/public``): ``bundle.json`` (the robot),
``calibration/<terrain>.json`` (its identified wheel radius and track width) and the model-input tables
``inputs/<protocol>/<terrain>/<cv|ld>/*.parquet`` (columns ``t sequence cmd_v cmd_w cmd_wl cmd_wr cmd_dwl
cmd_dwr``), predicts the body velocities ``vx = r (wl + wr) / 2``, ``vy = 0``, ``wz = r (wr - wl) / B`` (the
paper's eq. 1 with chi = 1) and writes one row per input row: ``sequence, t, vx, vy, wz``. Then ``skidbench
score <dataset> --predictions <file> inputs=<protocol> score.check=true`` checks it.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
import pandas as pd


def constants(bundle: Path, terrain: str) -> tuple[float, float]:
    """(wheel radius, track width): the calibrated value where calibrate identified it, else the robot's."""
    spec = json.loads((bundle / "bundle.json").read_text())["robot"]["spec"]
    calib = json.loads((bundle / "calibration" / f"{terrain}.json").read_text())
    r, b = (
        float(calib[c]["value"]) if (calib.get(c) or {}).get("identified") else float(spec[c])
        for c in ("wheel_radius", "track_width")
    )
    return r, b


def main(bundle: str, out: str, protocol: str = "commanded") -> None:
    bundle_dir = Path(bundle)
    frames = []
    for path in sorted((bundle_dir / "inputs" / protocol).glob("*/*/*.parquet")):
        terrain, split = path.parent.parent.name, path.parent.name
        if split not in ("cv", "ld"):
            continue
        r, b = constants(bundle_dir, terrain)
        x = pd.read_parquet(path)
        wl, wr = x["cmd_wl"].to_numpy(float), x["cmd_wr"].to_numpy(float)
        vx = r * (wl + wr) / 2.0
        frames.append(pd.DataFrame({"sequence": x["sequence"], "t": x["t"], "vx": vx, "vy": np.zeros_like(vx),
                                    "wz": r * (wr - wl) / b}))  # fmt: skip
    if not frames:
        sys.exit(f"{bundle_dir / 'inputs' / protocol}: no input tables (export with inputs={protocol})")
    table = pd.concat(frames, ignore_index=True)
    if out.endswith(".csv"):
        table.to_csv(out, index=False, float_format="%.17g")
    else:
        table.to_parquet(out, index=False)
    print(f"{out}: {len(table)} rows, {table['sequence'].nunique()} sequences")


if __name__ == "__main__":
    main(*sys.argv[1:])
