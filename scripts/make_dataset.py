#!/usr/bin/env python
"""Make (or finish) a training data set for the network: procedural volumes, random
configurations, path-traced F_>=2 labels, train-mode gather features (clvol/training/dataset.py).
The same as `clvol dataset make` (docs/dataset.md):

    python scripts/make_dataset.py runs/data [--seed 0] [--volumes 30] [--heldout 10]
        [--configs 8] [--points 128] [--paths 128] [--resolution 32,128] [--base 64]
        [--optical-thickness 1,1000] [--albedo 0.3,0.999] [--g -0.9,0.99] [--max-lobes 3]
        [--families cumulus,flat_cumulus,...]
        [--address auto|HOST:PORT|ray://HOST:PORT] [--workers N] [--serial]

--volumes counts every volume; the last --heldout of them come from a separate random stream
(held out of training by construction). Volumes cycle through the families.

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
