"""How often discovery names something that is not there (docs/discovery.md, "How well it works").

    python -m perf.discover_fdr                      # every set, the seeds below (from the repository root)
    python -m perf.discover_fdr --sets clean --seeds 20 --jobs 1 --out outputs/discover_fdr

Generates datasets whose truth is known (``tests/discover_data.py``: the extended differential drive plus
exactly the hidden effects, in physical form) in two worlds, runs the search of ``skidbench discover``
(base ``edd`` with the radius ``calibrate`` finds on the Train tables, default settings, the split
stage's own code between the generator and the search) on each, and counts per set how often the answer
is exact:

* ``clean``: nothing hidden; exact = nothing named. Over seeds, noise levels of the ground truth (VO-like
  drift and jitter at 0.5x, 1x, 2x) and drive styles (the generator's mixed joystick, a gentle one);
* ``clean_sim``: nothing hidden, the built-in simulator's operator (``JoystickDriver`` of
  ``pipeline/simulate/scenarios.py``, aggressive Train style) and its clock (45 Hz commands stamped on
  its 1 ms integrator steps, 50 Hz poses of a motion-capture-like truth); the simulator's force physics
  is not used (it has no effect-free setting: its slip, lag and load transfer are the effects);
* ``clean_blocks``: nothing hidden, one Train sequence of 60 s (held out by time blocks, as on ``mini``);
* ``single``: each catalogue effect alone at its default size; exact = that effect named first and
  nothing after it;
* ``outside``: each effect outside the catalogue alone; exact = no catalogue name and a matching term
  (the test's families), nothing after it;

and the worlds that are not the generator's one world (issue 47), ``seeds`` datasets each (as ``clean``,
``clean_sim`` and ``clean_blocks``; ``single`` has ``seeds / 6`` per effect, ``outside`` ``seeds / 10``):

* ``scale``: the robot drives at 0.96 of the commanded speed (an effective radius 0.96x the spec's) and
  hardly ever straight (the ``curvy`` drive style: few settled straight rows); exact = ``calibrate``'s
  radius within 1 % of the world's and nothing named;
* ``scale_uncal``: the same with no calibration (the spec sheet's radius, as on data ``calibrate`` cannot
  measure); exact = discovery's calibration finding within 1 % and nothing else;
* ``yaw_asym``: a yaw rate proportional to forward speed, the yaw channel only; exact = ``side_asymmetry``
  alone;
* ``clock``: 45 Hz commands, 30 Hz VO-like poses stamped 30 ms late, ``linear_acceleration_slip`` hidden;
  exact = the slip and ``actuator_lag`` (the delay the data hold: without encoders a dead time and a
  clock offset look the same), nothing else;
* ``slow_slip``: a zero-mean gain on both channels with 20 s of memory (s.d. 3 %), nothing else; exact =
  nothing named; ``slow_slip_blocks``: the same on one Train sequence of 90 s, held out by time blocks
  (where the buffer around held-out blocks matters);
* ``heading``: the ground truth's heading 3 deg off its track, drifting 1.5 deg/min; exact = nothing named
  and the ground-truth finding reported;
* ``gt_scale``: the ground truth's distances 15 % per minute longer from each sequence's start (an
  odometry's scale drift); exact = nothing named, the ground-truth finding reported and the wheel radius
  right to 1 % (``calibrate``, which reads the drifting truth, measures it long; discovery's calibration
  finding on the corrected truth may put it right).

Writes ``<out>/cases.jsonl`` (one line per dataset: what was named, each name's held-out gain and
``p_search``) as it goes (a re-run skips the cases already there) and ``<out>/summary.md``.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import subprocess
import sys
import time
from collections import Counter
from collections.abc import Iterable
from multiprocessing import get_context
from pathlib import Path
from typing import Any

import numpy as np

REPO = Path(__file__).resolve().parents[1]

#: the library families that match each outside effect (as tests/test_discover_terms.py checks)
OUTSIDE_MATCH = {
    "command_dead_zone": ("wdz", "rim", "wheels"),
    "payload_change": ("after", "wz_pred", "wz"),
    "yaw_rate_limit": ("sat", "wz_pred", "wz"),
    "one_side_slip": ("slip", None, "wheels"),
    "load_wheel_limit": ("wload", "rim", "wheels"),
}
NOISE = {"low": 0.5, "default": 1.0, "high": 2.0}
#: the worlds of issue 47: set -> (the hidden effect or world property, the generator's sequence options)
WORLDS = {
    "scale": ("speed_scale", {"style": "curvy"}),
    "scale_uncal": ("speed_scale", {"style": "curvy"}),
    "yaw_asym": ("side_asymmetry_yaw", {}),
    "clock": ("linear_acceleration_slip", {"pose_hz": 30.0, "clock_offset": 0.03}),
    "slow_slip": ("slow_slip", {}),
    "slow_slip_blocks": ("slow_slip", {"n_train": 1, "duration": 90.0}),
    "heading": (None, {"heading": (3.0, 1.5)}),
    "gt_scale": (None, {"gt_scale": 0.15}),
}
#: the worlds whose ground truth is inconsistent: exact = nothing named and a ground-truth finding
GT_WORLDS = ("heading", "gt_scale")
SETS = "clean,clean_sim,clean_blocks,single,outside," + ",".join(WORLDS)


def _dd():
    sys.path.insert(0, str(REPO / "tests"))
    import discover_data as dd

    return dd


def cases(sets: Iterable[str], seeds: int) -> list[dict[str, Any]]:
    """Every dataset to run: set, world, effect, seed, noise, style, Train size."""
    dd = _dd()
    out: list[dict[str, Any]] = []
    base = {
        "world": "kinematic",
        "effect": None,
        "noise": "default",
        "style": "mixed",
        "n_train": 8,
        "duration": 36.0,
    }
    for s in sets:
        if s == "clean":
            for i in range(seeds):
                out.append({**base, "set": s, "seed": 1000 + i, "noise": list(NOISE)[i % 3],
                            "style": "gentle" if i % 2 else "mixed"})  # fmt: skip
        elif s == "clean_sim":
            out += [{**base, "set": s, "world": "simclock", "seed": 2000 + i} for i in range(seeds)]
        elif s == "clean_blocks":
            out += [
                {**base, "set": s, "seed": 3000 + i, "n_train": 1, "duration": 60.0} for i in range(seeds)
            ]
        elif s == "single":
            k = max(seeds // 6, 1)
            out += [{**base, "set": s, "effect": e, "seed": 4000 + 10 * j + i}
                    for j, e in enumerate(dd.DEFAULT_SIZES) for i in range(k)]  # fmt: skip
        elif s in WORLDS:
            effect, kw = WORLDS[s]
            first = 6000 + 100 * list(WORLDS).index(s)
            style = {k: kw[k] for k in ("style", "n_train", "duration") if k in kw}
            out += [{**base, "set": s, "world": s, "effect": effect, "seed": first + i, **style}
                    for i in range(seeds)]  # fmt: skip
        elif s == "outside":
            k = max(seeds // 10, 1)
            out += [{**base, "set": s, "effect": e, "seed": 5000 + 10 * j + i}
                    for j, e in enumerate(dd.OUTSIDE) for i in range(k)]  # fmt: skip
        else:
            raise SystemExit(f"unknown set {s!r} ({SETS})")
    return out


def case_id(c: dict[str, Any]) -> str:
    return (
        f"{c['set']}/{c['world']}/{c['effect'] or '-'}/{c['seed']}/{c['noise']}/{c['style']}/{c['n_train']}"
    )


def _sim_sequence(dd, rng: np.random.Generator, effects: dict, duration: float):
    """One sequence with the built-in simulator's operator and clock (module docstring)."""
    from skidbench.pipeline.simulate.scenarios import JoystickDriver

    step = 0.001
    drv = JoystickDriver(rng, "asphalt", aggressive=True, rate=45.0)
    n = int(round(duration / step)) + 1
    period = 1.0 / 45.0 / step
    stamps = [math.ceil(k * period - 1e-9) for k in range(int(duration * 45.0) + 1)]
    stamps = [s for s in stamps if s < n]
    pose = np.zeros(3)
    cv, cw = np.zeros(len(stamps)), np.zeros(len(stamps))
    for k, s in enumerate(stamps):  # the operator steers by the (ideal) pose, as the simulator's does
        cv[k], cw[k] = drv.command(s * step, tuple(pose))
        dt = ((stamps[k + 1] if k + 1 < len(stamps) else n) - s) * step
        pose = pose + dt * np.array([cv[k] * math.cos(pose[2]), cv[k] * math.sin(pose[2]), cw[k]])
    t = np.arange(n) * step
    idx = np.searchsorted(np.asarray(stamps), np.arange(n), side="right") - 1
    v, w = cv[idx], cw[idx]
    ts = np.asarray(stamps) * step
    accel = (np.gradient(np.interp(t, ts, cv), t), np.gradient(np.interp(t, ts, cw), t))
    vx, vy, wz = dd.true_velocity(t, v, w, effects, accel=accel)
    truth = dd.integrate(t, vx, vy, wz)
    tl, loc = dd.vo_poses(rng, t, truth, rate_hz=50.0, drift=0.0, jitter_m=0.001, jitter_rad=0.0017)
    import pandas as pd

    cmd = pd.DataFrame({"t": ts, "v": cv, "w": cw})
    return cmd, pd.DataFrame({"t": tl, "x": loc[:, 0], "y": loc[:, 1], "yaw": loc[:, 2]})


def tables(c: dict[str, Any]) -> list[tuple[Any, dict]]:
    """The split tables (and their metadata) of a case's Train sequences."""
    dd = _dd()
    rng = np.random.default_rng(c["seed"])
    effects = {} if not c["effect"] else dd.hidden([c["effect"]])
    if c["world"] == "simclock":
        raw = [_sim_sequence(dd, rng, effects, c["duration"]) for _ in range(c["n_train"])]
    else:
        k = NOISE[c["noise"]]
        orig = dd.vo_poses

        def vo(rng, t, pose, rate_hz=20.0, drift=0.004, jitter_m=0.003, jitter_rad=0.0035):
            return orig(rng, t, pose, rate_hz, drift * k, jitter_m * k, jitter_rad * k)

        dd.vo_poses = vo
        kw = {k: v for k, v in WORLDS.get(c["world"], (None, {}))[1].items()
              if k not in ("style", "n_train", "duration")}  # fmt: skip
        try:
            raw = [
                dd.sequence(rng, effects, c["duration"], style=c["style"], **kw) for _ in range(c["n_train"])
            ]
        finally:
            dd.vo_poses = orig
    out = []
    for i, (cmd, loc) in enumerate(raw):
        df = dd.to_split(cmd, loc)
        out.append((df, dd.split_meta(df, f"train_{i:02d}")))
    return out


def calibrated(spec, train: list[tuple[Any, dict]]):
    """The robot ``calibrate`` makes of these Train tables for ``edd`` (its effective radius; the split's
    commands on settled straight rows, as for data without encoders), as ``skidbench discover`` on a
    dataset's own splits gives it to the base model."""
    from skidbench.models.base import calibrated_constants
    from skidbench.models.registry.specs import get_model_class
    from skidbench.pipeline.calibrate.calibration import calibrate_table, calibrated_robot
    from skidbench.pipeline.calibrate.settings import CalibrationSettings
    from skidbench.pipeline.core.schema import concat_sequences

    doc = calibrate_table(concat_sequences(train), spec, CalibrationSettings())
    return calibrated_robot(spec, doc, calibrated_constants(get_model_class("edd")))


def _names_the_slip_side_asymmetry(c: dict[str, Any], step: dict[str, Any]) -> bool:
    """Whether a step answers one side's slip with ``side_asymmetry`` turning the way the slip does, that
    side's slip term listed as its equivalent: on a base model whose radius ``calibrate`` measured on the
    same data, a slip ratio s on one side is exactly a left/right radius difference e = (s / 2) / (1 - s /
    2) on a radius smaller by s / 2 (tests/test_discover_terms.py checks it), the reparametrisation that
    the naming rule reports under the catalogue's id (docs/discovery.md); on a base whose radius took the
    forward part, the family's yaw-only member (a yaw rate proportional to speed) says the same."""
    side = _dd().OUTSIDE["one_side_slip"][0] if c["effect"] == "one_side_slip" else None
    if not side or step["name"] != "side_asymmetry":
        return False
    params = step.get("params", {})  # either member of the family: the radius difference or the yaw-only one
    k = params.get("side_asymmetry", params.get("side_asymmetry_yaw", {})).get("k", 0.0)
    turns_its_way = k > 0 if side == "l" else k < 0  # the slower side is the inside of the turn
    return turns_its_way and f"slip.{side}.wheels" in step["equivalent_terms"]


WORLD_TRUTH = {"yaw_asym": ["side_asymmetry"], "clock": ["actuator_lag", "linear_acceleration_slip"]}


def _radius_right(r: dict[str, Any]) -> bool:
    """The world's effective radius found to 1 %: by ``calibrate`` (``scale``) or by discovery's
    calibration finding (``scale_uncal``), and not the other way round."""
    want = _dd().WORLD["speed_scale"] * _dd().R_WHEEL
    if r["set"] == "scale_uncal":
        return r.get("calibration") is not None and abs(r["calibration"] / want - 1) <= 0.01
    return r.get("calibration") is None and abs(r["radius"] / want - 1) <= 0.01


def exact(r: dict[str, Any]) -> bool:
    """Whether the answer is the truth (module docstring) and nothing else: no ground-truth finding but on
    the worlds whose ground truth is wrong, no calibration finding but where the radius is not the
    calibrated one; ``r``: the case's row (what was named, the radius the base model was given, the
    calibration and ground-truth findings)."""
    effects, terms, steps = r["effects"], r["terms"], [st for st in r["steps"] if st["kind"] != "calibration"]
    if r.get("ground_truth") and r["set"] not in GT_WORLDS:
        return False  # a ground-truth finding where the ground truth is right: a false "check it"
    if r["set"] in WORLDS:
        if r["set"].startswith("scale") and not _radius_right(r):
            return False
        if r["set"] in GT_WORLDS and not r.get("ground_truth"):
            return False
        if r["set"] == "gt_scale":  # calibrate read the drifting truth: discovery may correct its radius
            radius = r["calibration"] if r.get("calibration") is not None else r["radius"]
            if abs(radius / _dd().R_WHEEL - 1) > 0.01:
                return False
        elif r["set"] != "scale_uncal" and r.get("calibration") is not None:
            return False
        return sorted(effects) == WORLD_TRUTH.get(r["set"], []) and not terms
    if r.get("calibration") is not None:
        return False  # the radius was calibrated on these worlds: a calibration finding is a false one
    if r["set"].startswith("clean"):
        return not effects and not terms
    if r["set"] == "single":
        return effects == [r["effect"]] and not terms
    if len(steps) == 1 and _names_the_slip_side_asymmetry(r, steps[0]):
        return True
    fam, sig, ch = OUTSIDE_MATCH[r["effect"]]
    if effects or len(terms) != 1:
        return False
    f, s_, chan = terms[0].split("@")[0].split(".")
    return f == fam and (sig is None or s_ == sig) and chan == ch


def false_catalogue_names(c: dict[str, Any], steps: list[dict[str, Any]]) -> list[str]:
    """The catalogue effects named that are not in the data (for an effect outside the catalogue: every
    catalogue name, but ``side_asymmetry`` naming one side's slip, its reparametrisation)."""
    truth = {c["effect"]} if c["set"] == "single" else set(WORLD_TRUTH.get(c["set"], []))
    return [
        st["name"]
        for st in steps
        if st["kind"] == "catalogue"
        and not st.get("dropped")
        and st["name"] not in truth
        and not _names_the_slip_side_asymmetry(c, st)
    ]


def run_case(c: dict[str, Any]) -> dict[str, Any]:
    from skidbench.benchmark.discovery.discover import discover_terrain
    from skidbench.benchmark.discovery.pool import prepare_pool
    from skidbench.models.augmented.fit import DiscoverError, DiscoverSettings, build_pool
    from skidbench.models.registry.specs import get_model_class
    from skidbench.pipeline.core.robot import load_robot

    started = time.process_time()
    jackal = load_robot("jackal")
    edd = get_model_class("edd")
    s = DiscoverSettings()
    try:
        train = tables(c)
        # as discovery on a dataset's own splits takes its base's radius; scale_uncal: none could be measured
        robot = jackal if c["set"] == "scale_uncal" else calibrated(jackal, train)
        pool = prepare_pool(build_pool(train, s), "commanded", jackal)
        res = discover_terrain(pool, lambda: edd(robot), robot, s, "tile", "edd", progress=lambda m: None)
    except DiscoverError as exc:
        return {**c, "id": case_id(c), "error": str(exc)}
    steps = [
        {
            "name": st["effect"],
            "kind": st["kind"],
            "heldout_gain": st["evidence"]["heldout_gain"],
            "p_search": st["evidence"].get("p_search"),
            "equivalent_terms": [q["term"] for q in st.get("naming", {}).get("equivalent_terms", [])],
            "params": st["params"],
            **({"dropped": st["dropped"]} if st.get("dropped") else {}),
        }
        for st in res.steps
    ]
    row = {
        **c,
        "id": case_id(c),
        "effects": res.effects,
        "terms": res.terms,
        "steps": steps,
        "radius": robot.wheel_radius,
        "calibration": res.calibration["value"] if res.calibration else None,
        "ground_truth": [q["text"] for q in res.base.get("ground_truth", [])],
        "too_small": [q["name"] for q in res.base.get("too_small", [])],
        "one_metric": [q["name"] for q in res.base.get("one_metric", [])],
        "false_catalogue": false_catalogue_names(c, steps),
        "rejected_best": (res.rejected or {}).get("best_candidate"),
        "cpu_s": round(time.process_time() - started, 1),
    }
    return {**row, "exact": exact(row)}


def wilson(k: int, n: int, z: float = 1.96) -> tuple[float, float]:
    """The 95 % Wilson interval of a proportion k / n."""
    if n == 0:
        return (0.0, 1.0)
    p = k / n
    d = 1 + z * z / n
    c = (p + z * z / (2 * n)) / d
    h = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / d
    return (max(0.0, c - h), min(1.0, c + h))


def summary(rows: list[dict[str, Any]], command: str, asked: dict[str, int] | None = None) -> str:
    """The page: per set, the datasets run (of those the options ask for, ``asked``), the exact answers
    with their Wilson interval and the wrong ones, then every answer that was not exact and every name."""
    lines = [
        f"discovery false-discovery measurement ({time.strftime('%Y-%m-%d')}): `{command}`",
        "",
        "| set | datasets run | exact | exact % (95 % interval) | not exact (a name missing or false) "
        "| false catalogue name |",
        "|---|---:|---:|---|---:|---:|",
    ]
    for s in dict.fromkeys(
        [*(s for s in asked or {} if any(r["set"] == s for r in rows)), *(r["set"] for r in rows)]
    ):
        rs = [r for r in rows if r["set"] == s and "error" not in r]
        k = sum(r["exact"] for r in rs)
        lo, hi = wilson(k, len(rs))
        false = sum(1 for r in rs if not r["exact"])
        false_cat = sum(1 for r in rs if false_catalogue_names(r, r["steps"]))
        of = f" of {asked[s]}" if asked and asked.get(s, 0) > len(rs) else ""
        lines.append(
            f"| {s} | {len(rs)}{of} | {k} | {100 * k / max(len(rs), 1):.0f} ({100 * lo:.0f}-{100 * hi:.0f}) "
            f"| {false} | {false_cat} |"
        )
    lines += ["", "Not exact:"]
    for r in rows:
        if "error" in r:
            lines.append(f"- {r['id']}: error {r['error']}")
        elif not r["exact"]:
            named = ", ".join(
                f"{st['name']} (gain {st['heldout_gain']:.3f}, p_search {st['p_search']:.3g})"
                for st in r["steps"]
            )
            small = (
                f"; detected, too small to act on: {', '.join(r['too_small'])}" if r.get("too_small") else ""
            ) + (
                f"; detected, does not help both metrics: {', '.join(r['one_metric'])}"
                if r.get("one_metric")
                else ""
            )
            lines.append(f"- {r['id']}: {named or 'nothing named'}{small}")
    named = [st for r in rows for st in r.get("steps", [])]
    if named:
        lines += [
            "",
            "Every name given: held-out gain and p_search (the share of sign flips whose best candidate "
            "gains as much)",
        ]
        for r in rows:
            for st in r.get("steps", []):
                eq = f" (equivalent: {', '.join(st['equivalent_terms'])})" if st["equivalent_terms"] else ""
                lines.append(
                    f"- {r['id']}: {st['name']}{eq} gain {st['heldout_gain']:.3f} "
                    f"p_search {st['p_search']:.3g}"
                )
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(prog="python -m perf.discover_fdr", description=__doc__.split("\n\n")[0])
    ap.add_argument("--sets", default=SETS)
    ap.add_argument("--seeds", type=int, default=20, help="clean datasets (the other sets scale from it)")
    ap.add_argument("--jobs", type=int, default=1, help="processes (the machine's cores are shared)")
    ap.add_argument("--out", default="outputs/discover_fdr")
    ap.add_argument("--effects", default="", help="only the cases of these hidden effects (comma-separated)")
    ap.add_argument("--publish", action="store_true", help="also write perf/results/discover_fdr.md")
    ap.add_argument("--summarize-only", action="store_true", help="run no dataset: summarise those in --out")
    a = ap.parse_args(argv)
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    path = out / "cases.jsonl"
    done = {}
    if path.is_file():
        for line in path.read_text().splitlines():
            r = json.loads(line)
            done[r["id"]] = r
    only = set(filter(None, a.effects.split(",")))
    wanted_cases = [c for c in cases(a.sets.split(","), a.seeds) if not only or c["effect"] in only]
    todo = [] if a.summarize_only else [c for c in wanted_cases if case_id(c) not in done]
    print(f"{len(todo)} datasets to run ({len(done)} done) -> {path}", flush=True)
    with path.open("a") as fh:
        workers = get_context("fork").Pool(a.jobs) if a.jobs > 1 and todo else None
        runs = map(run_case, todo) if workers is None else workers.imap_unordered(run_case, todo)
        for r in runs:
            fh.write(json.dumps(r) + "\n")
            fh.flush()
            done[r["id"]] = r
            verdict = "exact" if r.get("exact") else "NOT exact"
            print(f"{r['id']}: {verdict} {r.get('effects')} {r.get('terms')} "
                  f"{r.get('cpu_s')} CPU-s", flush=True)  # fmt: skip
        if workers is not None:
            workers.close()
            workers.join()
    wanted = {case_id(c) for c in wanted_cases}
    # the verdicts from the recorded answers by the current definition of exact
    rows = [r if "error" in r else {**r, "exact": exact(r)} for k, r in done.items() if k in wanted]
    command = "python -m perf.discover_fdr " + " ".join(sys.argv[1:] if argv is None else argv)
    text = summary(rows, command.strip(), Counter(c["set"] for c in wanted_cases))
    if len(rows) < len(wanted):
        text = f"{len(rows)} of the {len(wanted)} datasets these options ask for were run.\n\n" + text
    (out / "summary.md").write_text(text)
    if a.publish:  # the generated results page docs/discovery.md points to
        from skidbench.pipeline.core.io import write_text_atomic

        commit = subprocess.run(["git", "-C", str(REPO), "rev-parse", "--short", "HEAD"], capture_output=True,
                                text=True).stdout.strip()  # fmt: skip
        head = (
            f"Generated by `{command.strip()}` at commit {commit or 'unknown'} ({os.cpu_count()} CPUs).\n\n"
        )
        write_text_atomic(REPO / "perf" / "results" / "discover_fdr.md", head + text)
    print(text)


if __name__ == "__main__":
    main()
