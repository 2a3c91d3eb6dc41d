"""``skidbench fit model=<name> terrain=<t>``: fit one model on one terrain's Train split.

Writes ``<out_root>/<dataset>/fits/<model>/<terrain>.json``. Sweeps: ``skidbench fit -m model=a,b
terrain=x,y``. The model comes from the config group ``model`` (``conf/model/<name>.yaml``, or a plugin's
config found on the Hydra search path).
"""

from __future__ import annotations

import logging

import hydra
from omegaconf import DictConfig

from skidbench.pipeline.cli import stage

from .base import ModelError

log = logging.getLogger(__name__)


@hydra.main(version_base="1.3", config_path="pkg://skidbench.conf", config_name="fit")
@stage("fit")
def main(cfg: DictConfig) -> None:
    from omegaconf.errors import MissingMandatoryValue

    from .fitting import fit_model

    try:
        terrain = str(cfg.terrain)
    except MissingMandatoryValue:
        raise ModelError(
            "fit: no terrain given; add terrain=<t> (a folder under <dataset>/splits/)"
        ) from None
    name = str(cfg.model.name)
    res = fit_model(cfg, name, terrain, reuse=bool(cfg.get("reuse", False)), split=str(cfg.split))
    msg = (
        f"fit {name} on {terrain}: {res.n_train} rows, loss {res.fit_loss:.6g}, {res.fit_time_s:.2f} s, "
        f"params {res.model.params} -> {res.path}"
    )
    log.info(msg)


if __name__ == "__main__":
    main()
