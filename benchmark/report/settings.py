"""The config sections of the reports: compare's ``figures:`` (which figures, at what resolution,
:mod:`skidbench.benchmark.report.compare_figures`) and evaluate's ``report_data:`` (what compare's Figs. 5-7
draw, written next to each per-window table, :mod:`skidbench.benchmark.report.data`). Each dataclass is its
section's schema and defaults (stored in Hydra's ConfigStore, ``pipeline/cli/config_schema.py``); a stage
reads a section whole, ``OmegaConf.to_object(cfg.figures)``."""

from __future__ import annotations

from dataclasses import dataclass, field


@dataclass(frozen=True)
class FigureSettings:
    """The ``figures`` section: whether to draw, the resolution, the terrain of Figs. 5-7 and the wheel
    response (None: the first terrain scored) and the models of Figs. 5 and 6."""

    enabled: bool = True
    dpi: int = field(default=130, metadata={"lo": 20, "hi": 1200})
    fig5_model: str = "full_linear"  # Fig. 5: residual of this model's yaw rate vs angular acceleration
    fig6_model: str = "friction"  # Fig. 6: this model's yaw-rate surfaces
    terrain: str | None = None  # terrain of Figs. 5-7; null: the first one evaluated


@dataclass(frozen=True)
class ReportDataSettings:
    """The ``report_data`` section: Fig. 6's commanded angular accelerations (rad/s^2) of the yaw-rate
    surfaces and its grid points per wheel-rate axis, Fig. 7's sample windows per test split."""

    fig6_accels: list[float] = field(
        default_factory=lambda: [-8.0, 0.0, 8.0], metadata={"min_len": 1, "what": "rad/s^2"}
    )
    fig6_grid: int = field(default=31, metadata={"lo": 2})
    fig7_windows: int = field(default=3, metadata={"lo": 0})
