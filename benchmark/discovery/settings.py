"""The ``discover:`` section of ``skidbench discover`` (conf/discover.yaml). :class:`DiscoverOptions` is the
section's schema and defaults (stored in Hydra's ConfigStore, ``pipeline/cli/config_schema.py``); the app
reads it whole, ``OmegaConf.to_object(cfg.discover)``, and hands the search its part
(:meth:`DiscoverOptions.search`: :class:`~skidbench.models.augmented.fit.DiscoverSettings`). Imports nothing
heavy (the schema is registered before every composition)."""

from __future__ import annotations

from dataclasses import dataclass, field, fields
from typing import TYPE_CHECKING, Any

from skidbench.pipeline.core.manifest import SPLITS

if TYPE_CHECKING:
    from skidbench.models.augmented.fit import DiscoverSettings


@dataclass(frozen=True)
class DiscoverOptions:
    """Where discovery writes (``out``: discovery.json, discovery.png, discovery.md), what it reads
    (``splits``: a splits folder instead of preparing the configured source; ``use``: the splits it selects,
    fits and holds out on, Train, never CV/LD), its significance rule and its search."""

    out: str = "${out_root}/${dataset}/discovery"
    splits: str | None = None
    use: list[str] = field(
        default_factory=lambda: ["train"], metadata={"min_len": 1, "item": {"choices": SPLITS}}
    )
    # the significance rule and the search (:class:`~skidbench.models.augmented.fit.DiscoverSettings`): null
    # takes the search's own default, declared there only (what an augmented model's fit uses too)
    horizon_s: float | None = field(default=None, metadata={"gt": 0, "what": "s"})
    folds: int | None = field(default=None, metadata={"lo": 2})  # k-fold over whole sequences
    # fewer Train sequences than this: cut them into contiguous time blocks of at most chunk_s (shorter to
    # reach min_units, never under one horizon)
    min_units: int | None = field(default=None, metadata={"lo": 2})
    chunk_s: float | None = field(default=None, metadata={"gt": 0, "what": "s"})
    alpha: float | None = field(default=None, metadata={"gt": 0, "hi": 1})  # sign-flip test, one-sided
    # held-out log gain per parameter, and the gain left after that penalty
    penalty_per_param: float | None = field(default=None, metadata={"lo": 0})
    min_gain: float | None = field(default=None, metadata={"lo": 0})
    # held-out log-MSE loss allowed on a velocity channel the effect changes
    channel_tolerance: float | None = field(default=None, metadata={"lo": 0})
    # a name cuts the held-out 6 s error that remains by this share of it (one metric) and by at least
    # min_points (RMSRE as a fraction: 0.1 percentage point)
    min_share: float | None = field(default=None, metadata={"lo": 0, "hi": 1})
    min_points: float | None = field(default=None, metadata={"lo": 0})
    # a speed scale is one when its slow and fast halves differ by less than this share of it
    scale_spread: float | None = field(default=None, metadata={"lo": 0})
    # the search again with the commands shifted in time (auto: on recorded data, any source but sim)
    placebo: Any = field(default="auto", metadata={"choices": ("auto", True, False)})
    placebo_shift_s: float = field(default=30.0, metadata={"gt": 0, "what": "s"})  # half a shorter sequence
    max_effects: int | None = field(default=None, metadata={"lo": 0})
    candidates: list[str] | None = None  # None: the whole catalogue; or a list of effect ids
    # also search the term library beyond the catalogue (models/augmented/terms.py)
    open_ended: bool | None = None
    max_terms: int | None = field(default=None, metadata={"lo": 0})  # library terms validated per step
    figure: bool = True

    def search(self, seed: int) -> DiscoverSettings:
        """The search's settings (its rule, folds and units), with the run's ``seed``: the values set here,
        the search's defaults for the others (None)."""
        from skidbench.models.augmented.fit import DiscoverSettings

        names = [f.name for f in fields(DiscoverSettings) if f.name not in ("splits", "seed")]
        given = {n: getattr(self, n) for n in names if getattr(self, n, None) is not None}
        return DiscoverSettings(**given, splits=tuple(self.use), seed=seed)
