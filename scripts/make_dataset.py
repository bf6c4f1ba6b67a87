#!/usr/bin/env python
"""Make (or finish) a training data set for the network: procedural volumes, random
configurations, path-traced F_>=2 labels, train-mode gather features (clvol/dataset.py).

    python scripts/make_dataset.py runs/data [--seed 0] [--volumes 10] [--solids 2]
        [--configs 12] [--points 256] [--paths 384] [--resolution 32] [--base 64]

Resumable: rerun the same command after an interruption; finished shards are skipped, a
half-written one is redone. The folder's spec.json must match the options (else an error).
Long runs: `nohup python scripts/make_dataset.py runs/data > runs/data.log 2>&1 &`.
"""
from __future__ import annotations

import argparse
import sys
import time

from clvol.dataset import DatasetSpec, make_dataset
from clvol.errors import ClvolError


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("out", help="data set folder (e.g. runs/data; runs/ is ignored by git)")
    d = DatasetSpec()
    ap.add_argument("--seed", type=int, default=d.seed)
    ap.add_argument("--volumes", type=int, default=d.n_volumes)
    ap.add_argument("--solids", type=int, default=d.n_solids)
    ap.add_argument("--configs", type=int, default=d.configs_per_volume)
    ap.add_argument("--points", type=int, default=d.points_per_config)
    ap.add_argument("--paths", type=int, default=d.n_paths)
    ap.add_argument("--resolution", type=int, default=d.resolution)
    ap.add_argument("--base", type=int, default=d.base_resolution)
    args = ap.parse_args(argv)
    try:
        spec = DatasetSpec(seed=args.seed, n_volumes=args.volumes, n_solids=args.solids,
                           configs_per_volume=args.configs, points_per_config=args.points,
                           n_paths=args.paths, resolution=args.resolution,
                           base_resolution=args.base)
        t0 = time.perf_counter()
        r = make_dataset(spec, args.out)
    except ClvolError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    print(f"{args.out}: made {r['made']} shards, skipped {r['skipped']} finished ones, "
          f"{spec.n_shards} in the spec, {time.perf_counter() - t0:.1f} s", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
