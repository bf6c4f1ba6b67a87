#!/usr/bin/env python
"""Make (or finish) a training data set for the network: procedural volumes, random
configurations, path-traced F_>=2 labels, train-mode gather features (clvol/dataset.py).

    python scripts/make_dataset.py runs/data [--seed 0] [--volumes 30] [--heldout 10]
        [--configs 8] [--points 128] [--paths 128] [--resolution 32,128] [--base 64]
        [--optical-thickness 1,1000] [--albedo 0.3,0.999] [--g -0.9,0.99] [--max-lobes 3]
        [--families cumulus,flat_cumulus,...]

--volumes counts every volume; the last --heldout of them come from a separate random stream
(held out of training by construction). Volumes cycle through the families.

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


def pair(r) -> str:
    return ",".join(str(x) for x in r)


def parse_pair(name: str, text: str, kind=float) -> tuple:
    try:
        lo, hi = (kind(x) for x in text.split(","))
    except ValueError:
        raise ClvolError(f"{name} {text!r}: expected two numbers low,high") from None
    return (lo, hi)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("out", help="data set folder (e.g. runs/data; runs/ is ignored by git)")
    d = DatasetSpec()
    ap.add_argument("--seed", type=int, default=d.seed)
    ap.add_argument("--volumes", type=int, default=d.n_volumes)
    ap.add_argument("--heldout", type=int, default=d.n_heldout_volumes)
    ap.add_argument("--configs", type=int, default=d.configs_per_volume)
    ap.add_argument("--points", type=int, default=d.points_per_config)
    ap.add_argument("--paths", type=int, default=d.n_paths)
    ap.add_argument("--resolution", default=pair(d.resolution), help="low,high voxels per side")
    ap.add_argument("--base", type=int, default=d.base_resolution)
    ap.add_argument("--optical-thickness", default=pair(d.optical_thickness), help="low,high")
    ap.add_argument("--albedo", default=pair(d.albedo), help="low,high per channel")
    ap.add_argument("--g", default=pair(d.g), help="low,high HG g of every lobe")
    ap.add_argument("--max-lobes", type=int, default=d.max_lobes)
    ap.add_argument("--families", default=",".join(d.families))
    args = ap.parse_args(argv)
    try:
        spec = DatasetSpec(seed=args.seed, n_volumes=args.volumes, n_heldout_volumes=args.heldout,
                           configs_per_volume=args.configs, points_per_config=args.points,
                           n_paths=args.paths, resolution=parse_pair("--resolution", args.resolution, int),
                           base_resolution=args.base,
                           optical_thickness=parse_pair("--optical-thickness", args.optical_thickness),
                           albedo=parse_pair("--albedo", args.albedo), g=parse_pair("--g", args.g),
                           max_lobes=args.max_lobes,
                           families=tuple(f for f in args.families.split(",") if f))
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
