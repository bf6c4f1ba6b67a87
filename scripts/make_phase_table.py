#!/usr/bin/env python
"""Rebuild the packaged volume-phase table clvol/data/phase_lobes.npz (clvol/features/phasetable.py):
exact cone-averaged HG lobe tables at the packed g nodes, log-quantised to uint16.

    python scripts/make_phase_table.py [--out clvol/data/phase_lobes.npz]

Needed only when the table grid in clvol/features/phasetable.py changes (the loader refuses a file made
for another grid and falls back to the exact, slow computation).
"""
from __future__ import annotations

import argparse
import sys
import time

import numpy as np


def main(argv=None) -> int:
    from clvol.features import phasetable as P
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--out", default=str(P._packed_path()))
    args = ap.parse_args(argv)
    t0 = time.perf_counter()
    tables = []
    for u in P.PACKED_U:
        g = -np.expm1(-u)
        tables.append(P.lobe_table_exact(float(g)) if g > 0 else
                      np.full((P.N_BETA, P.N_THETA), P.INV_4PI))
        print(f"g = {g:.6f}  ({time.perf_counter() - t0:.1f} s)", flush=True)
    info = P.write_packed_table(args.out, np.stack(tables))
    print(f"wrote {args.out}: {len(tables)} g nodes x {P.N_BETA} x {P.N_THETA}, "
          f"quantisation error <= {info['max_quantisation_error']:.2e} relative, "
          f"{time.perf_counter() - t0:.1f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
