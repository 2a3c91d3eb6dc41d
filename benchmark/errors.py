"""The benchmark's exception: every error of evaluation, scoring, comparison and release derives from it
(and so from :class:`~skidbench.pipeline.core.errors.SkidbenchError`: the CLI prints it in one line)."""

from __future__ import annotations

from skidbench.pipeline.core.errors import SkidbenchError


class EvaluationError(SkidbenchError):
    pass
