"""An algorithm that is not cmat's: `toy_mappo`, MAPPO under another name with its own
reference settings. Defined outside cmat and found through the `cmat.algorithms` entry point
that tests/test_plugins.py installs; nothing in cmat names it. This entry is JAX-free and
declares everything cmat needs to know about the algorithm; the class (`toy.py`) is imported
when a run is built."""

from cmat.algorithms import AlgorithmEntry, mappo
from cmat.algorithms.mappo.options import MLPOptions

ENTRY = AlgorithmEntry(
    label="Toy MAPPO",
    cls="cmat_toy_algorithm.toy:ToyMAPPO",
    network_fields=mappo.NETWORK_FIELDS,
    options=MLPOptions,
    reference_defaults={
        **mappo.REFERENCE_DEFAULTS, "ppo": {**mappo.REFERENCE_DEFAULTS["ppo"], "lr": 1e-3},
    },
    presets=mappo.PRESETS,
)
"""The toy algorithm: cmat's MAPPO, renamed, with its own reference settings (MAPPO's with
learning rate 1e-3) and none per task."""
