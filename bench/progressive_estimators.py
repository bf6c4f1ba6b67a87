"""The progressive source's estimators compared on the same gathered paths (issue 38;
docs/accuracy.md, "The estimator, decided by measurement").

    python bench/progressive_estimators.py [--scenes cloud_a1_side cloud_a1_back oof_sphcu_back]
        [--size 64] [--ref-spp 1024] [--rounds 1 4 16 64 128]
        [--estimators network shrink cv cv_smooth] [--reference-file NAME=FILE.npz ...]
        [--time SECONDS ...]

Per scene: ``--ms progressive`` with seeds 21 and 22, one round per render (the first render
is the network-only first frame); at each checkpoint the table is recomputed from the same
gathered sums with each estimator (clvol/render/ms/progressive.py ``estimate``) and marched.
Scores are bench/neural_quality.py's ``scores`` against its two-half references (cached in
its cache, made when missing; ``--reference-file`` takes an existing cache file instead):
"single" is one seed's image with the reference's noise removed (what a user sees), "bias"
the two seeds' mean with both noises removed. The first line per scene is the stochastic
source with 64 samples per block (the network's converged table). ``--time``: instead, whole
``--ms progressive --time T`` renders (as clvol render makes them), scored the same way.
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

from _common import machine  # noqa: E402  (bench/ is on sys.path; puts the checkout first)
import neural_quality as nq  # noqa: E402
from clvol.render.ms import progressive as pg  # noqa: E402
from clvol.render.renderer import Renderer  # noqa: E402

SEEDS = (21, 22)


def references(name, scene, grid, spp, files):
    if name in files:
        with np.load(files[name]) as z:
            meta = json.loads(str(z["meta"]))
            print(f"  reference {name}: {files[name]} ({2 * meta['spp_half']} spp, made "
                  f"{meta.get('made')})")
            return z["h1"], z["h2"]
    h1, h2, _ = nq.reference(name, scene, grid, spp // 2,
                             Path.home() / ".cache" / "clvol" / "neural_quality")
    return h1, h2


def run_scene(name, size, spp, rounds, estimators, files):
    scene = nq.bench_scene(nq.SCENES[name], size)
    grid = scene.volume.load()
    h1, h2 = references(name, scene, grid, spp, files)
    net = [Renderer(scene, "raymarch", grid=grid, ms="stochastic", seed=s, view_samples=64,
                    domain_fallback=False).render().layers["total"] for s in SEEDS]
    sc = nq.scores(0.5 * (net[0] + net[1]), h1, h2, with_flip=False, test_halves=net)
    print(f"{name}: stochastic 64 samples (network): bias {sc['rmse100']:.3f}, reference "
          f"floor {sc['ref_floor_rmse100']:.3f}", flush=True)
    imgs, paths = {}, {}
    t0 = time.perf_counter()
    for seed in SEEDS:
        r = Renderer(scene, "raymarch", grid=grid, ms="progressive", seed=seed,
                     domain_fallback=False)
        src = r.source
        r.render()                                        # the first frame
        done = 0
        for cp in rounds:
            while done < cp:
                r.render()
                done += 1
            paths[cp] = src._paths_per_block()
            for est in estimators:
                src.estimator = est
                src.table = r.rt.upload(src.table_now()[0])
                plan = r.plan()
                layers, _ = r._marcher.march(plan.camera, scene.light, plan, src)
                imgs.setdefault((cp, est), []).append(layers["total"])
            src.estimator = "cv_smooth"
    for cp in rounds:
        for est in estimators:
            a, b = imgs[(cp, est)]
            one = nq.scores(a, h1, h2, with_flip=False)
            both = nq.scores(0.5 * (a + b), h1, h2, with_flip=False, test_halves=(a, b))
            print(f"{name:16s} rounds {cp:4d} ({paths[cp]:6.1f} paths/block) {est:10s} "
                  f"single {one['rmse100']:.3f}   bias {both['rmse100']:.3f}", flush=True)
    print(f"{name}: {time.perf_counter() - t0:.1f} s for both seeds", flush=True)


def run_timed(name, size, spp, budgets, files):
    """--time mode: per budget, ``clvol render --ms progressive --time T`` (a fresh Renderer,
    one render: the first frame and the rounds that fit) with each seed; noise-corrected
    scores of one seed's image and of the bias (both seeds)."""
    scene = nq.bench_scene(nq.SCENES[name], size)
    grid = scene.volume.load()
    h1, h2 = references(name, scene, grid, spp, files)
    net = [Renderer(scene, "raymarch", grid=grid, ms="stochastic", seed=s, view_samples=64,
                    domain_fallback=False).render().layers["total"] for s in SEEDS]
    sc = nq.scores(net[0], h1, h2, with_flip=False)
    print(f"{name}: stochastic 64 samples (network): single {sc['rmse100']:.3f}, reference "
          f"floor {sc['ref_floor_rmse100']:.3f}", flush=True)
    Renderer(scene, "raymarch", grid=grid, ms="progressive", progressive_rounds=1,
             domain_fallback=False).render()                      # build kernels
    for t in budgets:
        imgs, heads = [], []
        for seed in SEEDS:
            t0 = time.perf_counter()
            res = Renderer(scene, "raymarch", grid=grid, ms="progressive", seed=seed, time=t,
                           domain_fallback=False).render()
            heads.append((time.perf_counter() - t0, res.header))
            imgs.append(res.layers["total"])
        one = nq.scores(imgs[0], h1, h2, with_flip=False)
        both = nq.scores(0.5 * (imgs[0] + imgs[1]), h1, h2, with_flip=False, test_halves=imgs)
        wall, h = heads[0]
        print(f"{name:16s} --time {t:g}: {wall:.2f} s wall, {h['raymarch.progressive_rounds']} "
              f"rounds, paths/block {h['raymarch.progressive_paths_per_block']}: single "
              f"{one['rmse100']:.3f}   bias {both['rmse100']:.3f}", flush=True)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--scenes", nargs="+",
                    default=["cloud_a1_side", "cloud_a1_back", "oof_sphcu_back"])
    ap.add_argument("--size", type=int, default=64)
    ap.add_argument("--ref-spp", type=int, default=1024)
    ap.add_argument("--rounds", type=int, nargs="+", default=[1, 4, 16, 64, 128])
    ap.add_argument("--estimators", nargs="+", default=["network", "shrink", "cv", "cv_smooth"],
                    choices=list(pg.ESTIMATORS))
    ap.add_argument("--reference-file", nargs="*", default=[], metavar="NAME=FILE.npz")
    ap.add_argument("--time", type=float, nargs="*", default=None, metavar="SECONDS",
                    help="instead: one --time render per budget and seed (the whole source, "
                         "the default estimator)")
    args = ap.parse_args(argv)
    files = dict(x.split("=", 1) for x in args.reference_file)
    print(machine())
    print(f"size {args.size}, rounds {args.rounds}, seeds {SEEDS}, paths per query "
          f"{pg.PATHS_PER_QUERY}, round fraction {pg.ROUND_FRACTION}")
    for name in args.scenes:
        if args.time:
            run_timed(name, args.size, args.ref_spp, args.time, files)
        else:
            run_scene(name, args.size, args.ref_spp, sorted(args.rounds), args.estimators, files)
    print(machine())                                     # the load after the run
    return 0


if __name__ == "__main__":
    sys.exit(main())
