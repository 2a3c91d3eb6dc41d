"""``skidbench simulate``: the built-in default dataset (simulated Jackal bags, manifest, dataset card).

    skidbench simulate                         # scale=mini, ROS1 bags under outputs/sim-mini/raw/
    skidbench simulate scale=full seed=3       # Table I durations
    skidbench simulate format=ros2             # ROS2 bags (sqlite3); format=mcap for mcap storage

A sequence whose bag is up to date (same config, seed and simulator code; bag intact) is skipped, so a
killed run resumes where it stopped; ``force=true`` re-simulates everything.
"""

from __future__ import annotations

import contextlib
import dataclasses
import logging
import multiprocessing
import os
import shutil
import tempfile
import time
from collections.abc import Iterator
from concurrent.futures import ProcessPoolExecutor, as_completed
from pathlib import Path
from typing import Any

import cv2
import hydra
from omegaconf import DictConfig, OmegaConf
from threadpoolctl import threadpool_limits
from tqdm import tqdm

from skidbench.pipeline.cli.main import stage
from skidbench.pipeline.core.cache import Stamp
from skidbench.pipeline.core.errors import SimulateError
from skidbench.pipeline.core.io import atomic_path, fingerprint_file, write_text_atomic
from skidbench.pipeline.core.layout import layout_from_cfg, root_from_cfg
from skidbench.pipeline.core.manifest import Manifest, Sequence
from skidbench.pipeline.core.robot import Robot, robot_from_hydra
from skidbench.pipeline.simulate.bag import BagSink, bag_path
from skidbench.pipeline.simulate.card import build_rows, render_card, sequence_moments
from skidbench.pipeline.simulate.physics import load_physics
from skidbench.pipeline.simulate.scenarios import SequenceSpec, plan_sequences
from skidbench.pipeline.simulate.sequence import RunSettings, simulate_sequence
from skidbench.pipeline.simulate.settings import SimulateOptions

log = logging.getLogger("skidbench.simulate")

_CODE_FILES = ("physics.py", "scenarios.py", "sequence.py", "bag.py", "render.py", "textures.py")


def code_fingerprint() -> dict[str, str]:
    """Fingerprints of the simulator's source: a changed model re-simulates."""
    here = Path(__file__).parent
    return {f: fingerprint_file(here / f) for f in _CODE_FILES if (here / f).is_file()}


def make_renderer(robot: Robot, opts: SimulateOptions, seed: int):
    """The stereo renderer (pipeline/simulate/render.py), or None when ``images=false``."""
    if not opts.images:
        return None
    try:
        from skidbench.pipeline.simulate.render import StereoRenderer
    except ImportError as exc:
        raise SimulateError(
            f"pipeline/simulate/render.py: stereo renderer unavailable ({exc}); set images=false"
        ) from exc
    camera = robot.extra.get("camera")
    if not camera:
        raise SimulateError(f"robot {robot.name}: no camera section in the robot config; set images=false")
    try:
        return StereoRenderer(dict(camera), seed, **opts.render)
    except (ValueError, KeyError) as exc:
        raise SimulateError(f"simulate.render: {exc}") from exc


def _write_bag(final: Path, fmt: str, fill) -> None:
    """Write a bag atomically: ROS1 to a temp file renamed over ``final``; ROS2 (a folder whose storage
    file is named after it) in a temp folder, then the inner folder renamed to ``final``."""
    if fmt == "ros1":
        with atomic_path(final, suffix=".bag") as tmp:
            with BagSink(tmp, fmt) as sink:
                fill(sink)
        return
    final.parent.mkdir(parents=True, exist_ok=True)
    tmpdir = Path(tempfile.mkdtemp(prefix=".tmp-" + final.name + ".", dir=final.parent))
    try:
        inner = tmpdir / final.name
        with BagSink(inner, fmt) as sink:
            fill(sink)
        if final.is_dir():
            shutil.rmtree(final)
        elif final.exists():
            final.unlink()
        os.replace(inner, final)
    finally:
        shutil.rmtree(tmpdir, ignore_errors=True)


# what a worker needs, set by the parent before it forks (so the renderer's world is built once)
_CONTEXT: dict[str, Any] = {}


def _planned_seconds(spec: SequenceSpec) -> float:
    """Simulated seconds a sequence is expected to take (loops: their target + lining up at the mark)."""
    return spec.options["target"] + 4.0 if spec.category == "loop" else spec.duration


def _simulate_one(index: int, spec: SequenceSpec, final: Path, tick=None) -> dict[str, float]:
    """Simulate one sequence into its bag (atomically); returns its card moments."""
    c = _CONTEXT
    holder: dict[str, Any] = {}

    def fill(sink: BagSink) -> None:
        holder["truth"] = simulate_sequence(
            spec,
            index,
            c["robot"],
            c["terrains"][spec.terrain],
            c["drive"],
            c["tyre"],
            c["run"],
            c["seed"],
            sink,
            c["renderer"],
            tick,
        )

    _write_bag(final, c["fmt"], fill)
    truth = holder["truth"]
    robot = c["robot"]
    return {**sequence_moments(truth, robot.track_width, robot.wheel_radius), "_duration": float(truth.t[-1])}


def _physics(cfg: DictConfig) -> tuple[Robot, dict, Any, Any, list[SequenceSpec]]:
    """(robot, physics per terrain, drive, tyre, every sequence of the scale), checked."""
    robot = robot_from_hydra(cfg.robot)
    if not robot.left_joints or not robot.right_joints:
        raise SimulateError(f"robot {robot.name}: left_joints/right_joints are empty in the robot config")
    terrains, drive, tyre = load_physics(OmegaConf.to_container(cfg.sim, resolve=True))
    specs = plan_sequences(OmegaConf.to_container(cfg.scale.simulate, resolve=True))
    missing = sorted({s.terrain for s in specs} - set(terrains))
    if missing:
        raise SimulateError(
            f"sim config: no physics for terrain(s) {', '.join(missing)}; add them under sim.terrains"
        )
    return robot, terrains, drive, tyre, specs


def _run_settings(opts: SimulateOptions, robot: Robot) -> RunSettings:
    """The integrator step, sensor rates (the camera's from the robot's camera, 15 fps without one) and
    sensor models of every sequence."""
    rates = dict(opts.rates)
    camera = robot.extra.get("camera") or {}
    rates["camera"] = float(camera.get("fps", 15.0))
    return RunSettings(dt=opts.dt, rates=rates, sensors=dict(opts.sensors))


def _selected(
    only: list[str] | None, scale: str, specs: list[SequenceSpec]
) -> list[tuple[int, SequenceSpec]]:
    """The sequences ``only`` names (all without it), each with its plan index: a subset keeps each
    sequence's plan index, hence its random streams and its bytes."""
    only = set(only or ())
    unknown = sorted(only - {s.name for s in specs})
    if unknown:
        raise SimulateError(f"only={unknown}: no such sequence at scale {scale}")
    return [(i, s) for i, s in enumerate(specs) if not only or s.name in only]


def _stamp_key(
    stamp: Stamp, index: int, spec: SequenceSpec, seed: int, opts: SimulateOptions, physics, run, robot, code
):
    """The key of one sequence's bag: everything its bytes depend on."""
    return stamp.key(
        [],
        {
            "spec": spec.__dict__,
            "index": index,
            "seed": seed,
            "format": opts.format,
            "images": opts.images,
            "render": opts.render,
            "run": dataclasses.asdict(run),
            "robot": robot.to_dict(),
            "physics": physics,
            "code": code,
        },
    )


@contextlib.contextmanager
def _one_thread_per_worker(forking: bool) -> Iterator[None]:
    """When the sequences run in forked workers (``forking``): OpenCV, BLAS and OpenMP single-threaded in
    them, set here before the renderer is built and the workers fork (changing OpenCV's inside a forked
    child hangs on the parent's thread pool), and restored after. The workers already fill the cores, and
    idle pool threads spin, taking CPU time from the other workers: `make bench BENCH=render`, 8.2 CPU-ms a
    stereo pair with one OpenCV thread, 18.4 with two; `skidbench simulate scale=tiny` (2026-11-27), 18.2 s
    wall and 31.4 CPU-s with OpenBLAS's two threads a worker, 15.5 s and 25.6 with one, the same bags."""
    if not forking:
        yield
        return
    cv2_threads = cv2.getNumThreads()
    cv2.setNumThreads(1)
    try:
        with threadpool_limits(limits=1):
            yield
    finally:
        cv2.setNumThreads(cv2_threads)


def _simulate_all(todo: list, jobs: int, desc: str, finish) -> None:
    """Simulate the sequences ``todo`` (in ``jobs`` forked workers when more than one), with a progress
    bar in simulated seconds; ``finish(item, moments)`` after each. ``_CONTEXT`` is set."""
    total = sum(_planned_seconds(t[1]) for t in todo)
    with tqdm(total=total, unit="s", desc=desc, dynamic_ncols=True, mininterval=1.0) as bar:
        if jobs == 1:
            for item in todo:
                bar.set_postfix_str(item[1].name)
                before = bar.n
                result = _simulate_one(item[0], item[1], item[2], bar.update)
                bar.update(max(0.0, _planned_seconds(item[1]) - (bar.n - before)))
                finish(item, result)
            return
        # sequences are independent (own random streams), so any order gives the same bytes; fork shares
        # the parent's renderer world instead of rebuilding it per worker; longest first, so that no
        # worker is left alone with a long sequence at the end
        ctx = multiprocessing.get_context("fork")
        longest_first = sorted(todo, key=lambda t: -_planned_seconds(t[1]))
        with ProcessPoolExecutor(max_workers=min(jobs, len(todo)), mp_context=ctx) as pool:
            futures = {pool.submit(_simulate_one, t[0], t[1], t[2]): t for t in longest_first}
            for fut in as_completed(futures):
                item = futures[fut]
                finish(item, fut.result())
                bar.set_postfix_str(item[1].name)
                bar.update(_planned_seconds(item[1]))


def _write_manifest_and_card(layout, results: list[dict], robot: Robot, fmt: str, seed: int) -> tuple:
    """The dataset's manifest and card (``raw/card.md``) of the simulated ``results``; returns the card's
    (rows, text)."""
    manifest = Manifest(
        [
            Sequence(
                r["spec"].name, r["spec"].terrain, r["spec"].category, str(r["path"].relative_to(layout.raw))
            )
            for r in results
        ],
        robot=robot.name,
        format=fmt,
        base=layout.raw,
    )
    manifest.write(layout.manifest)
    rows = build_rows(
        [
            {"category": r["spec"].category, "terrain": r["spec"].terrain, "moments": r["moments"]}
            for r in results
        ]
    )
    card = render_card(rows, f"{layout.dataset} (seed {seed})")
    write_text_atomic(layout.raw / "card.md", card)
    return rows, card


def run(cfg: DictConfig) -> dict[str, Any]:
    """Simulate every sequence of the configured scale; returns a summary (paths, card rows, timing)."""
    t_start = time.perf_counter()
    opts: SimulateOptions = root_from_cfg(cfg, SimulateOptions)
    fmt, jobs = opts.format, opts.jobs
    robot, terrains, drive, tyre, specs = _physics(cfg)
    physics = OmegaConf.to_container(cfg.sim, resolve=True)
    run = _run_settings(opts, robot)

    layout = layout_from_cfg(cfg)
    seed = int(cfg.seed)
    bags_dir = layout.raw / "bags"
    code = code_fingerprint()
    moments: dict[str, dict[str, float]] = {}
    todo: list[tuple[int, SequenceSpec, Path, Stamp, str]] = []
    selected = _selected(opts.only, str(cfg.scale.name), specs)
    for index, spec in selected:
        stamp = Stamp(layout.raw / ".stamps" / f"{spec.name}.json", "simulate")
        key = _stamp_key(stamp, index, spec, seed, opts, physics, run, robot, code)
        if not opts.force and stamp.is_fresh(key) and "moments" in stamp.data.get("info", {}):
            moments[spec.name] = stamp.data["info"]["moments"]
        else:
            todo.append((index, spec, bag_path(bags_dir, spec.name, fmt), stamp, key))

    def finish(item, result) -> None:
        index, spec, final, stamp, key = item
        duration = result.pop("_duration")
        stamp.record(key, [final], {"moments": result, "duration": duration})
        moments[spec.name] = result

    if todo:
        with _one_thread_per_worker(jobs > 1 and len(todo) > 1):
            _CONTEXT.update(
                robot=robot, terrains=terrains, drive=drive, tyre=tyre, run=run, seed=seed, fmt=fmt,
                renderer=make_renderer(robot, opts, seed),
            )  # fmt: skip
            try:
                _simulate_all(todo, jobs, f"simulate {layout.dataset}", finish)
            finally:
                _CONTEXT.clear()

    results = [
        {"spec": s, "path": bag_path(bags_dir, s.name, fmt), "moments": moments[s.name]} for _, s in selected
    ]
    rows, card = _write_manifest_and_card(layout, results, robot, fmt, seed)
    return {
        "layout": layout,
        "card": card,
        "rows": rows,
        "sequences": len(results),
        "format": fmt,
        "skipped": len(selected) - len(todo),
        "bytes": sum(_size(r["path"]) for r in results),
        "seconds": time.perf_counter() - t_start,
    }


def _size(path: Path) -> int:
    if path.is_dir():
        return sum(f.stat().st_size for f in path.rglob("*") if f.is_file())
    return path.stat().st_size if path.exists() else 0


@hydra.main(version_base="1.3", config_path="pkg://skidbench.conf", config_name="simulate")
@stage("simulate")
def main(cfg: DictConfig) -> None:
    summary = run(cfg)
    layout = summary["layout"]
    print(summary["card"])
    print(
        f"simulate: {summary['sequences']} sequences ({summary['skipped']} up to date), "
        f"{summary['bytes'] / 1e6:.1f} MB of {summary['format']} bags in {summary['seconds']:.1f} s"
    )
    print(f"simulate: bags     -> {layout.raw / 'bags'}")
    print(f"simulate: manifest -> {layout.manifest}")
    print(f"simulate: card     -> {layout.raw / 'card.md'}")


if __name__ == "__main__":
    main()
