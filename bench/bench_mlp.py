"""Throughput of the network's fused OpenCL forward pass (cl/mlp.cl) against torch.

    python bench/bench_mlp.py            # batches 4,096 and 262,144
    python bench/bench_mlp.py --quick    # batches 4,096 and 32,768
    python bench/bench_mlp.py --sizes A.npz,B.npz,...   # OpenCL cost of several weight files'
                                                        # networks, side by side (model-size sweep)

Evaluations/s = queries x channels evaluated per second. OpenCL is timed on device buffers
(the render path: the gather's buffers in, a device buffer out; no host copies), torch
(clvol.training.model.Model, the training model) on the same inputs as CPU tensors in inference mode with
2 threads, and also with 1 thread: on a loaded 2-core machine torch's OpenMP pool often runs
slower with 2 threads than with 1, and the ratio is taken against the faster of the two. The
runs alternate within each repeat and medians are reported, with the load average before and
after: the cores are shared, so other processes' load lowers every figure. The last two
columns divide by the process's CPU time instead of wall time (evaluations per CPU-second, for
OpenCL and 1-thread torch): less sensitive to the load; 2 idle cores give at most twice that.
Target: >= 5x torch.
"""
from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import numpy as np

from _common import cpu_seconds, machine  # bench/ is on sys.path; puts the checkout (reference/) first
from clvol.kernels.mlp import MlpKernel  # noqa: E402
from clvol.features.weights import Architecture, MlpWeights, default_params, feature_contract  # noqa: E402
from clvol.runtime import get_runtime  # noqa: E402
from reference import mlp as ref  # noqa: E402

TARGET_RATIO = 5.0



def make_inputs(n: int, rng) -> tuple[np.ndarray, np.ndarray]:
    """n queries: a random block of up to 8,192 (realistic ranges, reference.mlp) tiled."""
    block = min(n, 8192)
    f, c = ref.random_inputs(block, rng, lobes=[(0.8, 0.7), (-0.3, 0.3)])
    reps = -(-n // block)
    return (np.ascontiguousarray(np.tile(f, (reps, 1, 1))[:n]),
            np.ascontiguousarray(np.tile(c, (reps, 1))[:n]))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--quick", action="store_true", help="batches 4,096 and 32,768")
    ap.add_argument("--repeats", type=int, default=None,
                    help="repeats per batch (default: 3, more for small batches: at least "
                         "~2 s of OpenCL time, at most 25)")
    ap.add_argument("--device", default=None)
    ap.add_argument("--sizes", default=None, metavar="W1.npz,W2.npz,...",
                    help="only time the OpenCL forward of these weight files' networks, "
                         "alternating within each repeat (a 32^3 lattice, grey and RGB)")
    args = ap.parse_args(argv)
    if args.sizes:
        return compare_sizes(args.sizes.split(","), args.device, args.repeats or 15)
    batches = (4096, 32768) if args.quick else (4096, 262144)

    import torch
    from clvol.training.model import Model
    torch.set_num_threads(2)

    arch = Architecture()
    weights = MlpWeights(arch, default_params(arch, np.random.default_rng(0)), feature_contract())
    rt = get_runtime(args.device)
    net = MlpKernel(weights, runtime=rt)
    model = Model(arch)
    model.load_numpy_params(weights.params)
    model.eval()

    print("bench_mlp: fused OpenCL forward (cl/mlp.cl) vs torch")
    print(f"machine : {machine(rt)}")
    print(f"torch   : {torch.__version__}, 2 threads and 1 thread, inference_mode")
    macs = arch.n_macs()
    print(f"network : {arch.n_params()} parameters, {macs['total']} multiply-adds per evaluation "
          f"({macs['dense']} in dense layers)")
    print(f"protocol: 3-25 repeats per row (n), OpenCL and torch (2, 1 threads) alternating, medians; "
          f"load average before {os.getloadavg()[0]:.2f}")
    print()
    header = (f"{'batch':>8} {'mode':>5} {'OpenCL evals/s':>15} {'torch-2t evals/s':>17} "
              f"{'torch-1t evals/s':>17} {'ratio':>7} {'target':>7}  {'CL ms':>7} {'torch ms':>9} {'n':>3}"
              f" {'CL /cpu-s':>10} {'t1 /cpu-s':>10}")
    print(header)
    rows = []
    rng = np.random.default_rng(1)
    for n in batches:
        f, c = make_inputs(n, rng)
        fb, cb = rt.upload(f), rt.upload(c)
        ft, ct = torch.from_numpy(f), torch.from_numpy(c)
        for mode, alb in (("grey", None), ("rgb", (0.92, 0.99, 0.94))):
            ch = 1 if alb is None else 3
            out = rt.alloc((n, ch))
            cfgs = [ct] if alb is None else [torch.from_numpy(ref.with_albedo(c, a)) for a in alb]
            net.enqueue(fb, cb, n, out, alb).wait()            # build + warm-up
            with torch.inference_mode():
                model(ft[:256], ct[:256])
            t0 = time.perf_counter()
            net.enqueue(fb, cb, n, out, alb).wait()
            once = time.perf_counter() - t0
            repeats = args.repeats or int(np.clip(2.0 / max(once, 1e-3), 3, 25))
            t_cl, t_th, c_cl, c_th = [], {2: [], 1: []}, [], []
            for _ in range(repeats):
                c0, t0 = cpu_seconds(), time.perf_counter()
                net.enqueue(fb, cb, n, out, alb).wait()
                t_cl.append(time.perf_counter() - t0)
                c_cl.append(cpu_seconds() - c0)
                for threads in (2, 1):
                    torch.set_num_threads(threads)
                    c0, t0 = cpu_seconds(), time.perf_counter()
                    with torch.inference_mode():
                        for cc in cfgs:
                            model(ft, cc)
                    t_th[threads].append(time.perf_counter() - t0)
                    if threads == 1:
                        c_th.append(cpu_seconds() - c0)
            cl_rate = n * ch / np.median(t_cl)
            th2, th1 = (n * ch / np.median(t_th[k]) for k in (2, 1))
            ratio = cl_rate / max(th2, th1)
            rows.append((n, mode, cl_rate, th2, th1, ratio))
            print(f"{n:>8} {mode:>5} {cl_rate:>15,.0f} {th2:>17,.0f} {th1:>17,.0f} {ratio:>6.1f}x "
                  f"{TARGET_RATIO:>6.1f}x  {np.median(t_cl) * 1e3:>7.1f} "
                  f"{min(np.median(t_th[2]), np.median(t_th[1])) * 1e3:>9.1f} {repeats:>3}"
                  f" {n * ch / np.median(c_cl):>10,.0f} {n * ch / np.median(c_th):>10,.0f}")
        del f, c, fb, cb, ft, ct
    print()
    print(f"load average after {os.getloadavg()[0]:.2f} (2 cores; figures measured under that load)")
    worst = min(r[5] for r in rows)
    print(f"lowest ratio (vs the faster torch) {worst:.1f}x, target {TARGET_RATIO:.0f}x: "
          f"{'met' if worst >= TARGET_RATIO else 'NOT met'}")
    return 0


def compare_sizes(paths, device, repeats: int) -> int:
    """Median OpenCL forward time of each weight file's network on one 32^3 lattice of inputs
    (what one --ms network lattice fill evaluates), the files alternating within each repeat."""
    from clvol.features.weights import load_weights
    rt = get_runtime(device)
    nets = [(p, load_weights(p)) for p in paths]
    n = 32 ** 3
    f, c = make_inputs(n, np.random.default_rng(1))
    fb, cb = rt.upload(f), rt.upload(c)
    print("bench_mlp --sizes: OpenCL forward of a 32^3 lattice (32,768 queries), medians")
    print(f"machine : {machine(rt)}")
    print(f"protocol: {repeats} repeats, files alternating; load average before {os.getloadavg()[0]:.2f}")
    print(f"{'weights':40s} {'params':>8} {'MACs/eval':>10} {'grey ms':>8} {'rgb ms':>8} {'grey evals/cpu-s':>17}")
    kernels = [(p, w, MlpKernel(w, runtime=rt)) for p, w in nets]
    times = {(p, m): [] for p, _ in nets for m in ("grey", "rgb")}
    cpu = {p: [] for p, _ in nets}
    outs = {1: rt.alloc((n, 1)), 3: rt.alloc((n, 3))}
    for _, _, k in kernels:                                  # build + warm-up
        k.enqueue(fb, cb, n, outs[1], None).wait()
        k.enqueue(fb, cb, n, outs[3], (0.92, 0.99, 0.94)).wait()
    for _ in range(repeats):
        for p, _, k in kernels:
            for mode, alb, ch in (("grey", None, 1), ("rgb", (0.92, 0.99, 0.94), 3)):
                c0, t0 = cpu_seconds(), time.perf_counter()
                k.enqueue(fb, cb, n, outs[ch], alb).wait()
                times[(p, mode)].append(time.perf_counter() - t0)
                if mode == "grey":
                    cpu[p].append(cpu_seconds() - c0)
    for p, w in nets:
        print(f"{Path(p).name[-40:]:40s} {w.arch.n_params():>8} {w.arch.n_macs()['total']:>10} "
              f"{np.median(times[(p, 'grey')]) * 1e3:>8.1f} {np.median(times[(p, 'rgb')]) * 1e3:>8.1f} "
              f"{n / max(np.median(cpu[p]), 1e-9):>17,.0f}")
    print(f"load average after {os.getloadavg()[0]:.2f} (2 cores; figures measured under that load)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
