"""The toy algorithm's class: cmat's MAPPO, renamed, with its own reference settings."""

from __future__ import annotations

from typing import Any, ClassVar

from cmat.algorithms.mappo import MAPPO


class ToyMAPPO(MAPPO):
    name: ClassVar[str] = "toy_mappo"
    reference_defaults: ClassVar[dict[str, Any]] = {
        **MAPPO.reference_defaults, "ppo": {**MAPPO.reference_defaults["ppo"], "lr": 1e-3},
    }
    task_reference_defaults: ClassVar[dict[str, dict[str, Any]]] = {}
