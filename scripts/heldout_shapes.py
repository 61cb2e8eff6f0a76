"""Write the held-out shapes (tactile_slam.sim.heldout) as PLY meshes in metres.

    .venv/bin/python scripts/heldout_shapes.py OUT [--resolution-mm 0.08] [--seed 0]

then, for example, ``tactile-slam bench tracking --objects OUT/torus.ply ...`` (docs/benchmarks.md).
"""

import argparse

from tactile_slam.sim.heldout import SHAPES, write_heldout

if __name__ == "__main__":
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("out")
    p.add_argument("--shapes", nargs="+", choices=SHAPES, default=list(SHAPES))
    p.add_argument("--resolution-mm", type=float, default=0.08)
    p.add_argument("--seed", type=int, default=0)
    a = p.parse_args()
    for path in write_heldout(a.out, tuple(a.shapes), a.resolution_mm, a.seed):
        print(path)
