"""An algorithm that is not cmat's: `toy_mappo`, MAPPO under another name with its own
reference settings. Defined outside cmat and found through the `cmat.algorithms` entry point
that tests/test_plugins.py installs; nothing in cmat names it. This entry is JAX-free; the
class (`toy.py`) is imported when a run is built."""

from cmat.algorithms import AlgorithmEntry

ENTRY = AlgorithmEntry(label="Toy MAPPO", cls="cmat_toy_algorithm.toy:ToyMAPPO")
