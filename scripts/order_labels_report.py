#!/usr/bin/env python
"""What a per-order label costs at albedo 1 (docs/pathtrace.md, "Labels per scattering order").

    python scripts/order_labels_report.py runs/po_all [runs/po_cloud ...]

Per optical-thickness bin of the shards' configurations: shards, mean and largest path length
(vertices), paths cut at the vertex limit, the share of the albedo-1 label carried by albedo
exponents >= 104 and >= 512 (bin edges: clvol/training/labels.py energy_above), and the largest
storage bound of a label in y = log(F / a^4 + 1) (the training loss's units) over the
evaluation albedos.
"""
from __future__ import annotations

import sys

import numpy as np


def main(argv=None) -> int:
    from clvol.training.dataset import load_shards
    from clvol.training.labels import energy_above, label_at, label_bounds
    argv = sys.argv[1:] if argv is None else argv
    if not argv:
        print(__doc__)
        return 2
    shards = [s for d in argv for s in load_shards(d) if s.meta["spec"].get("per_order_labels")]
    if not shards:
        print("error: no per-order shards (clvol dataset make --per-order-labels)", file=sys.stderr)
        return 2
    edges = (1, 10, 30, 100, 300, 1001)
    print("| optical thickness | shards | paths | mean vertices | max vertices | truncated paths "
          "| label share e >= 104 | e >= 512 | storage bound in y (max) |")
    print("|---|---|---|---|---|---|---|---|---|")
    for lo, hi in zip(edges[:-1], edges[1:]):
        sel = [s for s in shards if lo <= s.meta["config"]["optical_thickness"] < hi]
        if not sel:
            continue
        paths = sum(s.meta["spec"]["n_paths"] * s.meta["spec"]["points_per_config"] for s in sel)
        vmean = np.mean([s.meta["vertices_mean"] for s in sel])
        vmax = max(s.meta["vertices_max"] for s in sel)
        trunc = sum(s.meta["paths_truncated"] for s in sel)
        S = np.concatenate([s.arrays["S"] for s in sel]).astype(np.float64)
        M = np.concatenate([s.arrays["M"] for s in sel]).astype(np.float64)
        tot = S.sum()
        share = [float((energy_above(S, e) * S.sum(1)).sum() / max(tot, 1e-300)) for e in (104, 512)]
        ybound = 0.0
        for a in (0.7, 0.9, 0.97, 0.99, 0.995, 0.999, 0.9999, 1.0):
            lo_f, hi_f = label_bounds(S, M, a)
            ybound = max(ybound, float(np.max(np.log((hi_f + a ** 4) / (lo_f + a ** 4)))))
        assert np.allclose(label_at(S, M, 1.0), S.sum(1))
        print(f"| {lo}-{hi - 1 if hi == 1001 else hi} | {len(sel)} | {paths} | {vmean:.0f} | {vmax} | "
              f"{trunc} ({trunc / paths:.2%}) | {share[0]:.3f} | {share[1]:.3f} | {ybound:.1e} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
