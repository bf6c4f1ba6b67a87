#!/usr/bin/env python
"""Make (or finish) a training data set for the network: procedural volumes, random
configurations, path-traced F_>=2 labels, train-mode gather features (clvol/dataset.py).
The same as `clvol dataset make` (docs/dataset.md):

    python scripts/make_dataset.py runs/data [--seed 0] [--volumes 10] [--solids 2]
        [--configs 12] [--points 256] [--paths 384] [--resolution 32] [--base 64]
        [--address auto|HOST:PORT|ray://HOST:PORT] [--workers N] [--serial]

Runs on a local Ray using all cores (or on a cluster with --address) if Ray is installed
(pip install 'clvol[scale]'), else serially. Resumable: rerun the same command after an
interruption; finished shards are skipped, a half-written one is redone. The folder's
spec.json must match the options (else an error).
Long runs: `nohup python scripts/make_dataset.py runs/data > runs/data.log 2>&1 &`.
"""
from __future__ import annotations

import sys

from clvol.cli import main

if __name__ == "__main__":
    sys.exit(main(["dataset", "make", *sys.argv[1:]]))
