from __future__ import annotations

from cmat.algorithms.mappo.algorithm import MAPPO


class ToyMAPPO(MAPPO):
    """cmat's MAPPO under another class; its settings are its entry's (`ENTRY`)."""
