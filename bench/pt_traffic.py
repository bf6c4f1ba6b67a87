#!/usr/bin/env python3
"""Global-memory traffic of the path tracer per sample, and the bandwidth bound it implies.

    python bench/pt_traffic.py [--replay 2000] [--label-paths 256] [--measured JSON]

Runs bench/device_suite.py's path tracer scene (pathtrace_setup: the 128^3 cloud,
256^2 x 4 spp, seed 0, samples 4..7, the first timed launch; and its point queries,
4,096 points x 256 paths, seed 5) and prints the counts per path (vertices, tentative
collisions, majorant reads), the bytes per sample of ``traffic_bytes`` and the bound on
samples/s that memory bandwidth sets, for the H200 and the H100 SXM.

The counts come from the rows the kernel writes (ROW_STEPS, ROW_VERTICES). They do not
depend on the device: a path's draws depend only on (seed, stream, sample), so any OpenCL
device gives the same paths up to float rounding (a rounding difference can turn one
tentative collision's decision and so one path; the means move by far less than their
statistical error). The kernel does not count its majorant reads, so ``majorant_replay``
counts them on a sample of the same paths, replayed by the float64 twin
(reference/pathtrace.py) with the kernel's majorant grid and DDA (reference/majorant.py):
an estimate, printed with the twin's steps beside the kernel's for the same paths.

The bound is an UPPER bound on samples/s only if every byte came from DRAM: it ignores
caches. The 128^3 float32 density is 8 MiB and its 16^3 majorant 16 KiB, far smaller than
an H100's 50 MB L2 (NVIDIA's Hopper figure, seen quoted, not read at the source; the H200
is the same GH100 die, its L2 size not checked), so the DRAM traffic can be much lower and
the kernel is not bound to stay under it; read a measured rate that is a small fraction of
it as "memory bandwidth does not explain the rate".
"""
from __future__ import annotations

import argparse
import math
import os
import sys
import time

import numpy as np

from _common import ROOT  # (puts the checkout first)
from clvol.kernels.pathtrace import PT_OUT  # noqa: E402

# --------------------------------------------------------------------------- the model
# Bytes of global memory per event, read off cl/pathtrace.cl:
#   - a tentative collision (a tracking step, flight or shadow ray: pt_collide_v, counted in
#     the row's steps word) looks up sigma_t once: pt_sigma_lanes, trilinear between voxel
#     centres, 8 float32 voxels (VGATHER of 4 x-pairs) -> 32 B;
#   - a majorant read: pt_run's DDA loop (maj_dda_track inlined) gathers one float32 of
#     m->maj per lane still in `todo`, once per pass of the inner loop: the lane's current
#     cell at every tentative collision's outer iteration and every cell it then enters
#     -> 4 B each (not counted by the kernel: see majorant_replay);
#   - per path: pt_take_paths' atomic_inc on the launch's counter (4 B read + 4 B written),
#     pt_on_finish's row (PT_OUT = 12 float32 -> 48 B), and for a point query the point
#     and omega (two vload3 -> 24 B).
# Not counted: lanes outside a mask still gather voxel 0 / majorant cell 0 (the same few
# bytes every time: cached), the Philox streams (computed, never stored), and the lanes'
# private state (pt_lanes, 56 words x PT_LANES), which a GPU compiler may spill to off-chip
# local memory: that traffic cannot be read off the source.
DENSITY_BYTES_PER_STEP = 8 * 4
MAJORANT_BYTES_PER_READ = 4
# The same in 32-byte sectors (the unit an NVIDIA GPU's L2 moves to and from DRAM), for
# scattered reads that no cache serves twice: a trilinear lookup's 4 x-pairs lie in 4
# (y, z) rows, a pair in one sector unless x0 is a sector's last float (1 in 8; rows of a
# 128-wide grid start on a sector) -> 4 x 9/8 sectors = 144 B; a majorant read: 1 sector.
SECTOR_DENSITY_BYTES_PER_STEP = 4 * 9 / 8 * 32
SECTOR_MAJORANT_BYTES_PER_READ = 32
COUNTER_BYTES_PER_PATH = 4 + 4
ROW_BYTES_PER_PATH = PT_OUT * 4
QUERY_INPUT_BYTES_PER_PATH = 2 * 3 * 4

# Memory bandwidth (NVIDIA's data sheets: H200 SXM 4.8 TB/s, H100 SXM 3.35 TB/s).
BANDWIDTH = {"H200": 4.8e12, "H100 SXM": 3.35e12}


def traffic_bytes(steps: float, majorant_reads: float, query: bool = False,
                  sectors: bool = False) -> float:
    """Bytes of global memory of one path (one sample) of cl/pathtrace.cl with ``steps``
    tentative collisions and ``majorant_reads`` majorant reads (means over paths): the
    float32 words the kernel reads and writes, or with ``sectors`` the 32-byte sectors its
    scattered reads touch."""
    d, m = ((SECTOR_DENSITY_BYTES_PER_STEP, SECTOR_MAJORANT_BYTES_PER_READ) if sectors
            else (DENSITY_BYTES_PER_STEP, MAJORANT_BYTES_PER_READ))
    return (d * steps + m * majorant_reads
            + COUNTER_BYTES_PER_PATH + ROW_BYTES_PER_PATH
            + (QUERY_INPUT_BYTES_PER_PATH if query else 0))


def bounds(bytes_per_path: float) -> dict:
    """Bandwidth / bytes: the samples/s (or paths/s) memory bandwidth alone would allow."""
    return {k: bw / bytes_per_path for k, bw in BANDWIDTH.items()}


def row_counts(rows) -> dict:
    """Means per path of the kernel's counters (rows [..., PT_OUT])."""
    from clvol.kernels.pathtrace import ROW_STEPS, ROW_VERTICES
    r = np.asarray(rows)
    return {"paths": int(np.prod(r.shape[:-1])),
            "vertices": float(r[..., ROW_VERTICES].mean()),
            "steps": float(r[..., ROW_STEPS].mean())}


# --------------------------------------------------------------------------- majorant reads

def majorant_replay(med, block: int, render=None, query=None) -> dict:
    """Majorant reads per tentative collision, counted on paths replayed by the twin with
    the kernel's majorant grid (block ``block``) and DDA. ``render``: (camera, seed, sample,
    pixels); ``query``: (points, omegas, seed, sample). Returns the twin's totals and its
    rows (to set beside the kernel's rows of the same paths)."""
    import reference.pathtrace as rpt
    from reference.majorant import build_majorant, dda_segments
    from clvol.kernels.majorant import majorant_args
    P = rpt.Params(density=med.density, bbox_min=med.bbox_min, bbox_max=med.bbox_max,
                   medium=med.medium, light=med.light,
                   environment=med.environment, max_order=med.max_order or 0)
    maj = build_majorant(med.density, block)
    bsize = np.asarray(majorant_args(med.density.shape, med.bbox_min, med.bbox_max, block)[1],
                       np.float64)[:3]
    tally = {"majorant_reads": 0, "steps": 0}

    def collisions(x, w, rs):
        """pt_run's loop for one lane: (point, sigma_maj) of each tentative collision; the
        consumer draws its own numbers between two, then this draws the next tau."""
        segs = dda_segments(x, w, P.bbox_min, P.bbox_max, bsize, maj)
        if not segs:
            return
        tau = -math.log(1.0 - rs.next())
        i, t = 0, segs[0][0]
        while True:
            _, tb, m = segs[i]
            sm = m * P.density_scale
            tally["majorant_reads"] += 1
            dtau = sm * (tb - t)
            if sm > 0 and dtau >= tau:
                t = min(t + tau / sm, tb)
                tally["steps"] += 1
                yield x + t * w, sm
                tau = -math.log(1.0 - rs.next())
                continue
            tau -= dtau
            t = tb
            i += 1
            if i == len(segs):
                return

    def free_flight(P_, x, w, rs, c):
        for p, sm in collisions(x, w, rs):
            c.steps += 1
            if rs.next() * sm < rpt.sigma(P_, p):
                return p
        return None

    def transmittance(P_, x, w, rs, c):
        T = 1.0
        for p, sm in collisions(x, w, rs):
            c.steps += 1
            T *= max(0.0, 1.0 - rpt.sigma(P_, p) / sm)
            if T < rpt.T_RR:
                if rs.next() * rpt.T_RR >= T:
                    return 0.0
                T = rpt.T_RR
        return T

    saved = rpt.free_flight, rpt.transmittance
    rpt.free_flight, rpt.transmittance = free_flight, transmittance
    try:
        if render is not None:
            cam, seed, sample, pixels = render
            rows = rpt.render_paths(P, cam, seed, [sample], pixels)[0]
        else:
            pts, oms, seed, sample = query
            rows = rpt.query_paths(P, pts, oms, seed, [sample])[0]
    finally:
        rpt.free_flight, rpt.transmittance = saved
    return dict(tally, rows=rows, per_step=tally["majorant_reads"] / max(tally["steps"], 1))


# --------------------------------------------------------------------------- the suite's runs

def label_inputs(settings):
    """bench/device_suite.py t_pathtrace's query points and directions."""
    rs = np.random.default_rng(2)
    pts = rs.uniform(-0.3, 0.3, (settings.label_points, 3))
    om = rs.normal(size=(settings.label_points, 3))
    om /= np.linalg.norm(om, axis=1, keepdims=True)
    return pts, om


def query_tracer(p, rt):
    """The PathTracer of device_suite's point_query (unit sun, block 8, the same grid)."""
    from clvol.kernels.pathtrace import PathTracer
    from clvol.render.pathtrace import _medium
    med = _medium(p["scene"], p["grid"], None, (1.0, 1.0, 1.0), None)
    return PathTracer(med, 8, runtime=rt)


def replay_render(pt, cam, seed: int, sample: int, rows, n: int, batches: int = 8) -> dict:
    """Majorant reads per tentative collision of ``n`` of a render launch's paths (pixels
    drawn at random; ``rows``: the kernel's rows of that launch, [spl][pixels][row]), in
    ``batches`` (mean and standard error over them); ``same``: the fraction of replayed
    paths whose steps equal the kernel's."""
    from clvol.kernels.pathtrace import ROW_STEPS
    pix = np.sort(np.random.default_rng(0).choice(cam.width * cam.height, n, replace=False))
    per, same = [], 0
    for chunk in np.array_split(pix, batches):
        r = majorant_replay(pt.med, pt.block, render=(cam, seed, sample, chunk))
        per.append((r["majorant_reads"], r["steps"]))
        same += int(np.sum(r["rows"][:, ROW_STEPS] == rows[0, chunk, ROW_STEPS]))
    return _spread(per, same, n)


def replay_query(qt, rt, pts, om, seed: int, n: int, batches: int = 8) -> dict:
    """As replay_render for point queries: ``n`` of the points, one path each (the twin
    numbers their streams 0..n-1, so the kernel runs those points alone to compare)."""
    from clvol.kernels.pathtrace import ROW_STEPS
    qi = np.sort(np.random.default_rng(1).choice(len(pts), n, replace=False))
    p, w = pts[qi], om[qi]
    per, same = [], 0
    for chunk in np.array_split(np.arange(n), batches):
        # the twin numbers a chunk's streams 0..len(chunk)-1: the kernel runs the chunk alone
        kc = qt.query_batch(rt.to_device(p[chunk].astype(np.float32)),
                            rt.to_device(w[chunk].astype(np.float32)), len(chunk), seed, 0, 1)[0]
        r = majorant_replay(qt.med, qt.block, query=(p[chunk], w[chunk], seed, 0))
        per.append((r["majorant_reads"], r["steps"]))
        same += int(np.sum(r["rows"][:, ROW_STEPS] == kc[:, ROW_STEPS]))
    return _spread(per, same, n)


def _spread(per, same, n) -> dict:
    """Majorant reads per step as a ratio of totals over the batches' (reads, steps), with
    the ratio estimator's standard error from the batches."""
    a = np.asarray(per, np.float64)
    R, S = a[:, 0].sum(), a[:, 1].sum()
    r = R / max(S, 1.0)
    b = len(a)
    e = a[:, 0] - r * a[:, 1]
    se = float(np.sqrt(b / (b - 1) * np.sum(e * e)) / max(S, 1.0)) if b > 1 else float("nan")
    return {"per_step": float(r), "per_step_se": se, "replayed": n,
            "same_steps": same / max(n, 1)}


def summary(counts: dict, replay: dict, query: bool) -> dict:
    """counts (row_counts) and a replay (majorant reads per step) -> bytes per path (float32
    words, and 32-byte sectors) and the bandwidth bounds (M samples/s) of each."""
    reads = replay["per_step"] * counts["steps"]
    words = traffic_bytes(counts["steps"], reads, query)
    sectors = traffic_bytes(counts["steps"], reads, query, sectors=True)
    return dict(counts, majorant_reads=reads, replay=replay, bytes=words, bytes_sectors=sectors,
                bound_M={k: v * 1e-6 for k, v in bounds(words).items()},
                bound_M_sectors={k: v * 1e-6 for k, v in bounds(sectors).items()})


def suite_row(summ: dict, device_label: str = "") -> dict:
    """The columns bench/device_suite.py prints beside a path tracer row."""
    row = {"steps/sample": round(summ["steps"], 2), "vertices/sample": round(summ["vertices"], 2),
           "majorant reads/sample (twin replay)": f"{summ['majorant_reads']:.1f} "
           f"({summ['replay']['replayed']} paths, {summ['replay']['same_steps']:.0%} "
           "with the kernel's steps)",
           "B/sample (words / 32-B sectors)": f"{summ['bytes']:.0f} / {summ['bytes_sectors']:.0f}"}
    for k in BANDWIDTH:
        row[f"BW bound {k} M/s (words / sectors)"] = (
            f"{summ['bound_M'][k]:.0f} / {summ['bound_M_sectors'][k]:.0f}")
    card = card_of(device_label)
    return row, card


def card_of(device_label: str):
    """The BANDWIDTH entry a device label names (an H100 PCIe has other figures: None)."""
    if "PCIe" in device_label:
        return None
    return next((k for k in BANDWIDTH if k.split()[0] in device_label), None)


def fraction(measured_M: float, summ: dict, card: str) -> str:
    """measured M/s as a percentage of the card's bounds (words / sectors)."""
    return (f"{100 * measured_M / summ['bound_M'][card]:.3g}% / "
            f"{100 * measured_M / summ['bound_M_sectors'][card]:.3g}%")


def main(argv=None) -> int:
    import json
    import device_suite as ds
    from clvol.runtime import get_runtime
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--replay", type=int, default=2000,
                    help="paths of each kind replayed by the twin for the majorant reads")
    ap.add_argument("--label-paths", type=int, default=256,
                    help="paths per point counted (the suite's 256; fewer: a subset of them)")
    ap.add_argument("--measured", default=str(ROOT / "docs" / "device" / "h200_2026-11-27.json"),
                    help="a device_suite.json whose path tracer rows to set against the bounds")
    args = ap.parse_args(argv)
    rt = get_runtime()
    s = ds.FULL
    t0 = time.perf_counter()
    p = ds.pathtrace_setup({"settings": s, "rt": rt}, ("render",))
    pt, cam = p["pt"], p["scene"].camera
    print(f"device: {rt.entry.label}; the suite's scene: cloud {s.pt_volume}^3, "
          f"{cam.width}^2 x {s.pt_spl} spp (seed 0, samples {s.pt_spl}..{2 * s.pt_spl - 1}); "
          f"labels {s.label_points} points x {args.label_paths} paths (seed 5); "
          f"defines {sorted(pt.defines)}")
    rows = pt.render_batch(cam, 0, s.pt_spl, s.pt_spl)   # the suite's first timed launch
    rep = replay_render(pt, cam, 0, s.pt_spl, rows, args.replay)
    out = {"render": summary(row_counts(rows), rep, False)}
    pts, om = label_inputs(s)
    qt = query_tracer(p, rt)
    qrows = qt.query_batch(rt.to_device(pts.astype(np.float32)),
                           rt.to_device(om.astype(np.float32)), len(pts), 5, 0, args.label_paths)
    qrep = replay_query(qt, rt, pts, om, 5, min(args.replay, len(pts)))
    out["labels"] = summary(row_counts(qrows), qrep, True)
    measured = {}
    try:
        rep_json = json.loads(open(args.measured).read())
        label = rep_json["machine"]["device"]["label"]
        for r in rep_json["timings"].get("path tracer", []):
            if "M samples/s" in r:
                measured["render"] = r["M samples/s"]
            if "M paths/s" in r:
                measured["labels"] = r["M paths/s"]
    except (OSError, KeyError, ValueError) as e:
        label = ""
        print(f"(no measured rows: {e})")
    for k, v in out.items():
        r = v["replay"]
        extra = QUERY_INPUT_BYTES_PER_PATH if k == "labels" else 0
        print(f"{k}: {v['paths']} paths (kernel rows): {v['vertices']:.3f} vertices, "
              f"{v['steps']:.3f} tentative collisions per path; majorant reads "
              f"{r['per_step']:.3f} +- {r['per_step_se']:.3f} per collision (twin replay of "
              f"{r['replayed']} paths, {r['same_steps']:.1%} with the kernel's step count) "
              f"-> {v['majorant_reads']:.2f} per path")
        print(f"  bytes per path, float32 words: {DENSITY_BYTES_PER_STEP} x {v['steps']:.2f} + "
              f"{MAJORANT_BYTES_PER_READ} x {v['majorant_reads']:.2f} + "
              f"{COUNTER_BYTES_PER_PATH + ROW_BYTES_PER_PATH + extra} = {v['bytes']:.0f} B; "
              f"32-B sectors: {SECTOR_DENSITY_BYTES_PER_STEP:g} x {v['steps']:.2f} + "
              f"{SECTOR_MAJORANT_BYTES_PER_READ} x {v['majorant_reads']:.2f} + "
              f"{COUNTER_BYTES_PER_PATH + ROW_BYTES_PER_PATH + extra} = {v['bytes_sectors']:.0f} B")
        for card, bw in BANDWIDTH.items():
            print(f"  bandwidth bound (no caches), {card} {bw / 1e12:g} TB/s: "
                  f"{v['bound_M'][card]:,.0f} M/s (words), {v['bound_M_sectors'][card]:,.0f} M/s "
                  f"(sectors)")
        card = card_of(label)
        if k in measured and card:
            print(f"  measured on {label} ({os.path.relpath(args.measured, ROOT)}): {measured[k]} M/s = "
                  f"{fraction(measured[k], v, card)} of its bound (words / sectors)")
    print(f"({time.perf_counter() - t0:.1f} s)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
