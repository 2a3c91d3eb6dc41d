"""How much of the friction model's 6 s error is the wheels' response? Score a saved friction fit on every
CV and LD sequence of a dataset twice, with the same parameters: driven by its identified wheel response
(what `skidbench evaluate` scores: a function of the commands only) and driven by the measured encoder
rates (what the model would score if it knew the wheels exactly). Needs splits with encoders (DRIVE).

    python examples/friction_from_encoders.py outputs/drive-husky_windows-3b1ec9 husky

Prints, per terrain and split, the translational and rotational RMSRE (%) of both and the wheel response's
RMS error against the encoders (rad/s). The README's "What limits the error that remains" table is its
output on the DRIVE Husky and Warthog.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from skidbench.benchmark.evaluate import TestSequence, score_split, summarise
from skidbench.benchmark.horizon import HorizonConfig
from skidbench.benchmark.tracking import metric_key
from skidbench.models.friction import FrictionBased
from skidbench.pipeline.robot import load_robot
from skidbench.pipeline.schema import list_split_files, read_split


def encoder_inputs(table):
    """(wl, wr, dwl, dwr) from the measured wheel rates (derivatives by central differences)."""
    t = table["t"].to_numpy(float)
    wl, wr = table["enc_wl"].to_numpy(float), table["enc_wr"].to_numpy(float)
    return wl, wr, np.gradient(wl, t), np.gradient(wr, t)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("dataset", type=Path, help="a dataset folder (outputs/<dataset>) after evaluate")
    ap.add_argument("robot", help="the robot config name the dataset was evaluated with")
    args = ap.parse_args()
    robot = load_robot(args.robot)
    for fit_file in sorted((args.dataset / "fits" / "friction").glob("*.json")):
        terrain = fit_file.stem
        model = FrictionBased.from_json(robot, json.loads(fit_file.read_text()))
        for split in ("cv", "ld"):
            seqs = [
                TestSequence(f.stem, f, *read_split(f))
                for f in list_split_files(args.dataset / "splits", terrain, split)
            ]
            row = {}
            for name, inputs in (("response", model.inputs), ("encoders", encoder_inputs)):
                vel = [model.velocities(inputs(s.table))[0] for s in seqs]
                res = summarise(score_split(seqs, vel, [6.0], HorizonConfig()), split, [6.0])
                row[name] = " / ".join(
                    f"{res[metric_key(k, split, 6.0)]:.2f}" for k in ("translational", "rotational")
                )
            err = np.concatenate(
                [
                    np.column_stack(model.inputs(s.table)[:2]) - s.table[["enc_wl", "enc_wr"]].to_numpy(float)
                    for s in seqs
                ]
            )
            print(
                f"{terrain} {split}: trans / rot RMSRE % driven by the wheel response {row['response']}, "
                f"by the encoders {row['encoders']}; wheel RMSE {np.sqrt(np.nanmean(err**2)):.3f} rad/s"
            )


if __name__ == "__main__":
    main()
