"""``skidbench discover``: name the physical effect the base model is missing, add it, show the gap shrink.

    skidbench discover source=<any source> [source.root=<dir>] [terrain=<t>] [model=<base>] discover.out=<dir>

Writes ``<out>/discovery.json`` (base model, effects in the order added, one step per effect with its
one-sentence physical explanation, the evidence and the held-out 6 s RMSRE before and after) and
``<out>/discovery.png`` (the gap shrinking step by step, and the residual that revealed each effect).
The workflow: :mod:`skidbench.benchmark.discovery.discover`; its significance rule:
:mod:`skidbench.benchmark.discovery.stats`.
"""

from __future__ import annotations

import logging
import time
from pathlib import Path
from typing import Any

import hydra
import numpy as np
from omegaconf import DictConfig, OmegaConf

from skidbench.benchmark.discovery.checks.placebo import placebo
from skidbench.benchmark.discovery.checks.scale import against_encoders
from skidbench.benchmark.discovery.discover import (
    NO_EFFECT_MESSAGE,
    TerrainDiscovery,
    discover_terrain,
    refused_terrain,
)
from skidbench.benchmark.discovery.pool import load_pool, prepare_pool, too_small
from skidbench.benchmark.discovery.settings import DiscoverOptions
from skidbench.models.augmented.effects import CATALOGUE, EFFECT_IDS
from skidbench.models.augmented.fit import DiscoverError, DiscoverSettings
from skidbench.pipeline.cli.main import stage
from skidbench.pipeline.core.io import atomic_path, write_json_atomic, write_text_atomic
from skidbench.pipeline.core.layout import CommonSettings, Layout, layout_from_cfg, root_from_cfg
from skidbench.pipeline.core.manifest import Manifest
from skidbench.pipeline.core.protocol import check_protocol
from skidbench.pipeline.core.robot import robot_from_hydra

log = logging.getLogger("skidbench.discover")


def _splits_root(cfg: DictConfig, opts: DiscoverOptions) -> Path:
    if opts.splits:
        root = Path(opts.splits).expanduser()
        if not root.is_dir():
            raise DiscoverError(f"{root}: splits folder not found (discover.splits)")
        return root
    from skidbench.pipeline.cli.api import prepare_calibration, prepare_splits

    root = Path(prepare_splits(cfg))
    prepare_calibration(cfg)  # one command from a raw source: the calibrate stage's step too, as split's
    return root


def _dataset_of(root: Path) -> tuple[Layout, Manifest] | None:
    """The dataset whose ``splits`` folder ``root`` is, with its current manifest (None for a bare folder)."""
    layout = Layout(root.parent.parent, root.parent.name)
    if root.resolve() != layout.splits.resolve() or not layout.manifest.is_file():
        return None
    return layout, Manifest.read(layout.manifest)


def _files_of(dataset: tuple[Layout, Manifest] | None):
    """``(terrain, split) -> split files``: the manifest's sequences, each required to be split."""
    if dataset is None:
        return None
    layout, manifest = dataset

    def files(terrain: str, split: str) -> list[Path]:
        return layout.require_split_files(manifest, terrain, split, DiscoverError)

    return files


def _terrains(root: Path, cfg: DictConfig, use: tuple[str, ...], dataset=None) -> list[str]:
    if cfg.get("terrain"):
        return [str(cfg.terrain)]
    if dataset is not None:  # the current manifest's terrains, never the folders that happen to exist
        layout, manifest = dataset
        found = sorted({s.terrain for s in manifest.sequences if s.category in use})
        if not found:
            raise DiscoverError(f"{layout.manifest}: no {'/'.join(use)} sequences")
        return found
    found = sorted(  # a bare splits folder named by discover.splits: what it holds is the dataset
        p.name for p in root.iterdir() if p.is_dir() and any((p / s).glob("*.parquet") for s in use)
    )
    if not found:
        raise DiscoverError(f"{root}: no terrain folder holds {'/'.join(use)} split files")
    return found


def _model_name(cfg: DictConfig) -> str:
    m = cfg.get("model")
    if m is None:
        return "edd"
    return str(m) if isinstance(m, str) else str(m.get("name"))


def _response(calib: Any, terrain: str, pool, inputs: str, own_splits: bool):
    """The wheel response of ``terrain`` under ``inputs=response``: the calibration's on the dataset's own
    splits; on another splits folder identified here, with the same implementation, from the pool's
    encoders (its Train sequences, plus CV/LD when the pool had to add them). ``calib``: the dataset's
    :class:`~skidbench.pipeline.calibrate.calibration.Calibrations`."""
    if inputs != "response":
        return None
    from skidbench.pipeline.calibrate.calibration import response_for, wheel_response_doc, wheel_response_of

    if own_splits:
        resp = response_for(calib, terrain)
    else:
        resp = wheel_response_of(wheel_response_doc(pool.table.assign(sequence=pool.groups)))
    if resp is None:
        raise DiscoverError(f"inputs=response: no wheel response identified for terrain {terrain} (no wheel "
                            "encoders in its Train split; `skidbench calibrate` says why)")  # fmt: skip
    return resp


def _radius_method(calib: Any, terrain: str) -> str:
    """How ``calibrate`` measured the terrain's wheel radius (its record's ``method``; "" when it did not).
    ``calib``: the dataset's :class:`~skidbench.pipeline.calibrate.calibration.Calibrations`."""
    from skidbench.pipeline.calibrate.calibration import load_calibration

    rec = (load_calibration(calib, terrain) or {}).get("wheel_radius") or {}
    return str(rec.get("method", "")) if rec.get("identified") else ""


def _placebo_on(cfg: DictConfig, p: Any) -> bool:
    """``discover.placebo`` (``p``): auto runs it on recorded data (any source but the simulator)."""
    if p == "auto":
        return str(OmegaConf.select(cfg, "source.name", default="sim")) != "sim"
    return bool(p)


def run(cfg: DictConfig) -> dict[str, Any]:
    """Run discovery for the configured source; returns what was written to discovery.json."""
    from skidbench.models.fitting.fit import ModelConfigs, build_model

    t0 = time.perf_counter()
    opts: DiscoverOptions = OmegaConf.to_object(cfg.discover)
    common = root_from_cfg(cfg, CommonSettings)
    settings, inputs = opts.search(common.seed), check_protocol(common.inputs)
    robot = robot_from_hydra(cfg.robot)
    base_name = _model_name(cfg)
    configs = ModelConfigs.from_cfg(cfg)
    build_model(configs, base_name, robot)  # fail early, with the model's one-line error
    root = _splits_root(cfg, opts)
    out = Path(opts.out).expanduser()
    cands = tuple(opts.candidates) if opts.candidates else EFFECT_IDS
    unknown = [c for c in cands if c not in CATALOGUE]
    if unknown:
        raise DiscoverError(
            f"discover.candidates: unknown effect(s) {unknown} (catalogue: {list(EFFECT_IDS)})"
        )
    print(f"skidbench discover: base model {base_name}; inputs={inputs}; splits {root}")
    print("significance rule: " + settings.rule())
    results: list[TerrainDiscovery] = []
    dataset = _dataset_of(root)
    files_of = _files_of(dataset)
    from skidbench.models.base import calibrated_constants
    from skidbench.models.registry.specs import get_model_class
    from skidbench.pipeline.calibrate.calibration import Calibrations, robot_for_model

    layout = layout_from_cfg(cfg)
    calib = Calibrations(layout, robot, cfg.calibrate.use)  # the dataset's, read on its own splits only
    own_splits = root.resolve() == layout.splits.resolve()
    for terrain in _terrains(root, cfg, settings.splits, dataset):
        pool = load_pool(root, terrain, settings, files_of)
        reason = too_small(pool, settings)
        if reason is not None:
            print(f"[{terrain}] refused: {reason}", flush=True)
            results.append(refused_terrain(pool, settings, terrain, base_name, reason))
            continue
        # the dataset's own splits: the base model takes the calibrated constants, as in evaluate
        constants = calibrated_constants(get_model_class(base_name))
        robot_t = robot_for_model(calib, constants, terrain)[0] if own_splits else robot
        response = _response(calib, terrain, pool, inputs, own_splits)
        pool = prepare_pool(pool, inputs, robot, response)
        factory = lambda r=robot_t: build_model(configs, base_name, r)  # noqa: E731
        res = discover_terrain(pool, factory, robot_t, settings, terrain, base_name, candidates=cands,
                               progress=lambda m: print(m, flush=True))  # fmt: skip
        if own_splits and res.calibration:  # a radius calibrate measured against encoders is not the scale
            against_encoders(res, _radius_method(calib, terrain))
            print(f"[{terrain}] calibration: {res.calibration['text']}", flush=True)
        if _placebo_on(cfg, opts.placebo):
            res.placebo = placebo(pool, factory, robot_t, settings, terrain, base_name, cands,
                                  opts.placebo_shift_s)  # fmt: skip
            print(f"[{terrain}] {res.placebo['text']}", flush=True)
        results.append(res)
    if all(r.refused for r in results):
        raise DiscoverError(f"{root}: every terrain refused; {results[0].terrain}: {results[0].refused}")
    doc = to_document(results, base_name, settings, root, time.perf_counter() - t0)
    doc["inputs"] = inputs  # the input protocol every fit of the search was driven by
    out.mkdir(parents=True, exist_ok=True)
    write_json_atomic(out / "discovery.json", doc)
    write_text_atomic(out / "discovery.md", summary_text(doc))
    if opts.figure:
        figure(results, out / "discovery.png")
    print(summary_text(doc))
    print(f"written: {out / 'discovery.json'}")
    return doc


def to_document(
    results: list[TerrainDiscovery], base_name: str, s: DiscoverSettings, root: Path, seconds: float
) -> dict[str, Any]:
    terrains = {}
    for r in results:
        terrains[r.terrain] = {
            "base_model": base_name,
            "effects": r.effects,
            "model_effects": r.final.get("model_effects", r.effects),  # the members as fitted
            "terms": r.terms,
            "calibration": r.calibration,
            "placebo": r.placebo,
            "ground_truth": r.base.get("ground_truth", []),
            "too_small": r.base.get("too_small", []),
            "one_metric": r.base.get("one_metric", []),
            "dropped": r.base.get("dropped", []),
            "message": r.message,
            "unexplained": r.unexplained,
            "steps": r.steps,
            "base": r.base,
            "final": r.final,
            "rejected": r.rejected,
            "seconds": r.seconds,
            "selected_on": r.selected_on,
            **({"refused": r.refused} if r.refused else {}),
        }
    if len(results) == 1:
        r = results[0]
        effects, steps, message = list(r.effects) + list(r.terms), list(r.steps), r.message
    else:
        effects, steps = [], []
        for r in results:
            steps += [{"terrain": r.terrain, **st} for st in r.steps]
            effects += [e for e in r.effects if e not in effects]
        message = "; ".join(f"{r.terrain}: {r.message}" for r in results)
    for st in steps:
        st.setdefault("terrain", results[0].terrain if len(results) == 1 else st.get("terrain"))
    return {
        "schema": 1,
        "base_model": base_name,
        "effects": effects,
        "message": message if effects else NO_EFFECT_MESSAGE,
        "steps": steps,
        "terrains": terrains,
        "significance_rule": s.rule(),
        "settings": {k: (list(v) if isinstance(v, tuple) else v) for k, v in s.__dict__.items()},
        "catalogue": {e.id: {"explanation": e.explanation, "formula": e.formula} for e in CATALOGUE.values()},
        "splits": str(root),
        "seconds": seconds,
    }


def summary_text(doc: dict[str, Any]) -> str:
    lines = [f"discovery from base model {doc['base_model']}"]
    for terrain, r in doc["terrains"].items():
        if r.get("selected_on"):
            lines.append(f"[{terrain}] selected on {r['selected_on']['text']}")
        if r.get("refused"):
            lines.append(f"[{terrain}] refused: {r['refused']}")
            continue
        b = r["base"]["heldout_rmsre"]
        lines.append(
            f"[{terrain}] base held-out RMSRE: translational {b['translational']:.4f}, "
            f"rotational {b['rotational']:.4f}"
        )
        for i, st in enumerate(r["steps"], 1):
            a = st["heldout_rmsre_after"]
            ev = st["evidence"]
            lines.append(
                f"[{terrain}] {i}. {st['effect']}: translational -> {a['translational']:.4f}, rotational -> "
                f"{a['rotational']:.4f} (held-out gain {ev['heldout_gain']:+.3f}, "
                f"{ev['units_improved']}/{ev['n_heldout_units']} held-out units better; p_search = "
                f"{ev.get('p_search', float('nan')):.2g}: the chance that a dataset with nothing missing "
                f"gives the best of the {ev.get('n_candidates_tested', '?')} candidates tried a gain as "
                "consistent)"
            )
            lines.append(f"      {st['explanation']}")
            eq = [q["term"] for q in (st.get("naming") or {}).get("equivalent_terms") or []]
            if eq:
                lines.append(f"      equivalent terms (the same residual in other forms): {', '.join(eq)}")
        for q in (r.get("too_small") or []) + (r.get("one_metric") or []):
            lines.append(f"[{terrain}] {q['text']}")
        for q in r.get("dropped") or []:
            lines.append(f"[{terrain}] {q['name']} dropped after step {q['after_step']}: {q['why']}")
        lines.append(f"[{terrain}] {r['message']}")
        for q in r.get("ground_truth") or []:
            lines.append(f"[{terrain}] {q['text']}")
        if r.get("placebo"):
            lines.append(f"[{terrain}] {r['placebo']['text']}")
        if r.get("unexplained"):
            lines.append(f"[{terrain}] {r['unexplained']['text']}")
    return "\n".join(lines)


def figure(results: list[TerrainDiscovery], path: Path) -> None:
    """Per terrain: held-out RMSRE after each step; then, per step, the held-out residual of the effect's
    channel against the quantity that revealed it (binned means +- s.e.) and the correction added."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    ncol = 1 + max(1, max(len(r.figure_data) for r in results))
    fig, axes = plt.subplots(len(results), ncol, figsize=(4.2 * ncol, 3.6 * len(results)), squeeze=False)
    for row, r in zip(axes, results, strict=True):
        ax = row[0]
        labels = ["base"] + [s["effect"] for s in r.steps]
        trans = [r.base["heldout_rmsre"]["translational"]] + [
            s["heldout_rmsre_after"]["translational"] for s in r.steps
        ]
        rot = [r.base["heldout_rmsre"]["rotational"]] + [
            s["heldout_rmsre_after"]["rotational"] for s in r.steps
        ]
        x = np.arange(len(labels))
        ax.plot(x, trans, "o-", label="translational")
        ax.plot(x, rot, "s-", label="rotational")
        ax.set_xticks(x)
        ax.set_xticklabels(["base"] + [f"+{e}" for e in labels[1:]], rotation=25, ha="right", fontsize=7)
        ax.set_ylabel("held-out 6 s RMSRE")
        ax.set_ylim(bottom=0)
        status = "refused: too little Train data" if r.refused else NO_EFFECT_MESSAGE
        ax.set_title(f"{r.terrain}: {r.base_model}" + ("" if r.steps else f" ({status})"), fontsize=9)
        ax.legend(fontsize=7)
        for j, ax in enumerate(row[1:]):
            if j >= len(r.figure_data) or "bin_x" not in r.figure_data[j]:
                ax.axis("off")
                continue
            d = r.figure_data[j]
            ax.errorbar(d["bin_x"], d["bin_y"], yerr=d["bin_se"], fmt="o", ms=3, label="held-out residual")
            if "bin_fit" in d:
                ax.plot(d["bin_x"], d["bin_fit"], "-", color="C3", label="added effect")
            ax.axhline(0, color="0.6", lw=0.8)
            ax.set_xlabel(d["feature"], fontsize=8)
            ax.set_ylabel(f"{d['channel']} residual (true - model)", fontsize=8)
            verdict = "added" if d.get("accepted") else "best candidate, rejected"
            title = f"step {j + 1}: {d['effect']} ({verdict})"
            if d.get("unexplained"):
                title = f"unexplained {d['channel']} residual and its strongest correlate"
            ax.set_title(title, fontsize=9)
            ax.legend(fontsize=7)
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=110, format="png")
    plt.close(fig)


@hydra.main(version_base="1.3", config_path="pkg://skidbench.conf", config_name="discover")
@stage("discover")
def main(cfg: DictConfig) -> None:
    logging.getLogger("skidbench").setLevel(logging.INFO)
    log.debug(OmegaConf.to_yaml(cfg))
    run(cfg)


if __name__ == "__main__":
    main()
