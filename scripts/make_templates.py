#!/usr/bin/env python3
"""Generate the sampling-template tables clvol/data/templates.npz (deterministic).

    python scripts/make_templates.py            # write clvol/data/templates.npz
    python scripts/make_templates.py --check    # regenerate and compare with the committed file
    python scripts/make_templates.py --out X.npz --diffuse 6,8,12,16,24,32,48,48 --highlight 32,16,16,8

The algorithm and units are in clvol/features/templates.py and docs/templates.md. The .npz is written
with fixed zip timestamps, so the same tables give the same bytes (and the same hash, which
weight files record as the contract's template_hash).
"""
from __future__ import annotations

import argparse
import io
import sys
import time
import zipfile
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from clvol.features import templates as T  # noqa: E402


def write_npz(path: Path, arrays: dict) -> None:
    """Like np.savez, but byte-for-byte reproducible (fixed member timestamps and order)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(".tmp")
    with zipfile.ZipFile(tmp, "w", compression=zipfile.ZIP_STORED) as zf:
        for name in sorted(arrays):
            buf = io.BytesIO()
            np.lib.format.write_array(buf, np.asarray(arrays[name]), allow_pickle=False)
            info = zipfile.ZipInfo(name + ".npy", date_time=(1980, 1, 1, 0, 0, 0))
            zf.writestr(info, buf.getvalue())
    tmp.replace(path)


def _counts(text: str) -> tuple[int, ...]:
    try:
        out = tuple(int(c) for c in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected comma-separated counts, got {text!r}")
    if not out or min(out) < 2:
        raise argparse.ArgumentTypeError(f"each layer needs at least 2 points, got {text!r}")
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", type=Path, default=ROOT / "clvol" / "data" / "templates.npz")
    ap.add_argument("--diffuse", type=_counts, default=T.TemplateSpec.diffuse_counts)
    ap.add_argument("--highlight", type=_counts, default=T.TemplateSpec.highlight_counts)
    ap.add_argument("--cone-deg", type=float, default=T.HIGHLIGHT_HALF_ANGLE_DEG,
                    help="half-angle of the highlight cone around the light ray (degrees)")
    ap.add_argument("--check", action="store_true",
                    help="regenerate and compare with --out instead of writing it")
    args = ap.parse_args(argv)
    if not 0 < args.cone_deg < 90:
        ap.error(f"--cone-deg must be in (0, 90), got {args.cone_deg}")
    spec = T.TemplateSpec(diffuse_counts=args.diffuse, highlight_counts=args.highlight,
                          highlight_half_angle_deg=args.cone_deg)
    t0 = time.perf_counter()
    arrays = T.generate(spec, progress=print)
    print(f"generated {len(arrays['points'])} points in {time.perf_counter() - t0:.1f} s")
    if args.check:
        with np.load(args.out) as z:
            # NaN marks "not defined" (diffuse radius of a highlight layer): compare as equal.
            worst = max(float(np.nanmax(np.abs(np.asarray(z[k], float) - np.asarray(v, float)),
                                        initial=0.0))
                        for k, v in arrays.items() if np.asarray(v).dtype.kind in "fi")
        print(f"max difference from {args.out}: {worst:.3g}")
        return 0 if worst < 1e-9 else 1
    write_npz(args.out, arrays)
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
