"""The network's image quality against long path-traced references, with a hard target.

    python bench/neural_quality.py [--weights FILE.npz] [--size 128] [--ref-spp 4096]
                                   [--scenes NAME|FILE ...] [--out table.md|table.csv]
                                   [--quick] [--refs-only] [--rebuild-refs] [--cache DIR]

Scenes (none of them in the training set): the four examples (examples/*.toml) and five more in
bench/scenes/ (a back-scattering HG g = -0.9 cloud, a low-albedo 0.4 torus, a strongly chromatic
two-lobe jade box, a 128^3 cumulus, a cumulus lit from behind), each at --size x --size pixels.

Methods, each a whole ``render_raymarch`` / ``render_pathtrace`` call on the loaded volume:
  network     ``--ms network`` at default settings (``--weights``, default the shipped model)
  wrenninge   ``--ms wrenninge`` (analytic octaves), default settings
  single      ``--ms none`` (single scattering only)
  pt_equal    the path tracer given the network's wall time (``time_budget``): the network's
              time is the median of 3 warm renders (kernels built, phase tables made, volume
              loaded; the network's pyramid, gather and lattice fill are inside the time)
  view        ``--ms view`` at default settings: the same network queried at the camera's view
              (blocks of pixels, depths at the quantiles of the in-scattering weight) instead
              of on a world lattice; timed like the network
  pt_view     only with --pt-view N: the view-space table filled by path-traced point queries
              (N paths per point): what the view-space representation itself leaves. Filled
              twice (seeds 11, 12); the row scores their mean with the noise of both fills
              removed like the reference's (``scores(test_halves=...)``), so it is the
              representation's bias, not the queries' noise
  stochastic  only with --stochastic N: ``--ms stochastic`` with N free-flight samples per block
              accumulated on the still view (the viewer's image after N frames); timed like
              the network (the whole N-sample render). Its own sampling noise stays in the
              score: it is what a user sees after N frames
  pt_stochastic  only with --pt-stochastic N and --stochastic: the stochastic table filled
              by path-traced point queries (N paths per point) twice, with different sampling
              and path seeds; the noise of both is removed like pt_view's, so the row is the
              estimator's bias after that many samples (what the representation leaves)
  pt_lattice  only with --pt-lattice N: the network's F_ms lattice filled by the path tracer's
              point queries (N paths per point) instead, then the same march. Not a baseline
              and not timed: it shows what the lattice itself leaves at this resolution

References: the path tracer at --ref-spp samples per pixel as two independent halves (two seeds,
--ref-spp / 2 each); the reference is their mean. They are cached in --cache (default
~/.cache/clvol/neural_quality, shared by all checkouts) under a key that hashes the resolved scene,
the density grid's bytes, the image size, spp, seeds and the path tracer's source files, so a
changed scene, generator or path tracer is rebuilt and never read stale. Each half is written
atomically when it is done (``NAME.half1.npz``), then the scene's file when both are, so an
interrupted --refs-only run loses at most the half it was rendering.

Metrics, per scene and method (``scores``), against the reference R = (H1 + H2) / 2:
  rmse100   RMSE x 100 of tonemapped luminance with the reference's noise removed: MRPNN's
            exposure and luminance (clvol/metrics.py ``mrpnn_metric``) without its 8-bit rounding
  relmse    mean of (t - R)^2 / (R^2 + 0.01) on both images scaled by the same exposure (so 0.01
            means "dark for this image" whatever the light's irradiance), noise removed likewise
  flip      LDR-FLIP after the same exposure (clvol/metrics.py ``flip``); not noise-corrected
  mean      image mean over the reference's (all pixels and channels)
Printed with them: ref_floor_rmse100 (the removed noise) and ref_halves_flip (FLIP of one half
against the other: how much of a FLIP score the reference's noise alone can make).
Target (PASS/FAIL each): worst rmse100 <= 1.0, worst relmse <= 0.01, worst FLIP <= 0.05 (network,
over all scenes), and on every scene the network's rmse100 <= the best of the three baselines.
Results in docs/neural.md.
"""
from __future__ import annotations

import argparse
import csv
import hashlib
import io
import json
import math
import statistics
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from _common import load_average, machine  # noqa: E402  (bench/ is on sys.path)
from clvol.atomic import atomic_open  # noqa: E402
from clvol.errors import ClvolError  # noqa: E402
from clvol.metrics import (LUMA, flip, flip_available, mrpnn_exposure,  # noqa: E402
                           tonemap_srgb)
from clvol.render.ms.network import shipped_weights  # noqa: E402
from clvol.render.pathtrace import DEFAULT_BLOCK, render_pathtrace  # noqa: E402
from clvol.render.renderer import Renderer  # noqa: E402
from clvol.scene import load_scene  # noqa: E402

SCENES = {
    "cloud": ROOT / "examples" / "cloud.toml",
    "jade": ROOT / "examples" / "jade.toml",
    "milk": ROOT / "examples" / "milk.toml",
    "smoke": ROOT / "examples" / "smoke.toml",
    "backscatter": ROOT / "bench" / "scenes" / "backscatter.toml",
    "low_albedo": ROOT / "bench" / "scenes" / "low_albedo.toml",
    "jade_chromatic": ROOT / "bench" / "scenes" / "jade_chromatic.toml",
    "cloud_128": ROOT / "bench" / "scenes" / "cloud_128.toml",
    "cloud_backlit": ROOT / "bench" / "scenes" / "cloud_backlit.toml",
    # issue 21: albedo 1 from three sides, a 128^3 albedo-1 cloud, an albedo-0.99 cloud
    "cloud_a1_side": ROOT / "bench" / "scenes" / "cloud_a1_side.toml",
    "cloud_a1_back": ROOT / "bench" / "scenes" / "cloud_a1_back.toml",
    "cloud_a1_top": ROOT / "bench" / "scenes" / "cloud_a1_top.toml",
    "cloud_a1_128": ROOT / "bench" / "scenes" / "cloud_a1_128.toml",
    "cloud_a099": ROOT / "bench" / "scenes" / "cloud_a099.toml",
    # issue 28: the fire example (frame 6 of its generated sequence): smoke that scatters the
    # sun and glows by blackbody emission; the real-time methods skip scattered emission
    "flame": ROOT / "examples" / "fire" / "fire.toml",
    # issue 24: sky light (targets: <= 2.0 at albedo 0.9-1, <= 2.5 under the HDR map)
    "cloud_sky_only": ROOT / "bench" / "scenes" / "cloud_sky_only.toml",
    "cloud_sun_sky": ROOT / "bench" / "scenes" / "cloud_sun_sky.toml",
    "cloud_sky_map": ROOT / "examples" / "cloud_sky.toml",
    # the network on clouds it has never seen: generators no training set uses
    # (clvol.training.dataset.OUT_OF_FAMILY), optical thickness 37-48
    "oof_nubis_side": ROOT / "bench" / "scenes" / "oof_nubis_side.toml",
    "oof_sphcu_back": ROOT / "bench" / "scenes" / "oof_sphcu_back.toml",
    "oof_nubis_top": ROOT / "bench" / "scenes" / "oof_nubis_top.toml",
    "oof_sphcu_closeup": ROOT / "bench" / "scenes" / "oof_sphcu_closeup.toml",
}
METHODS = ("network", "view", "wrenninge", "single", "pt_equal")
BASELINES = ("wrenninge", "single", "pt_equal")
COLUMNS = ("scene", "family", "method", "rmse100", "relmse", "flip", "mean", "mean_rgb",
           "seconds", "spp", "ref_floor_rmse100", "ref_halves_flip")
# Scenes whose volume comes from a generator no training set uses: their rows are the
# out-of-family ones ("out"); every other scene is in family ("in").
OUT_OF_FAMILY_GENERATORS = ("perlin_worley", "sphere_cumulus")
# Out-of-family targets (docs/neural.md): image means per channel, and the worst rmse100 of the
# stochastic view source (its --stochastic row) or, without one, of the network's row.
OOF_MEAN_RANGE = (0.97, 1.03)
OOF_RMSE100 = 1.5
TARGET = {"rmse100": 1.0, "relmse": 0.01, "flip": 0.05}
REF_SEEDS = (7_000_001, 7_000_002)   # the two halves; test renders use other seeds
PT_EQUAL_SEED = 11
PT_VIEW_SEEDS = (11, 12)             # the two independent fills of the pt_view row
STOCHASTIC_SEED = 5                  # the stochastic row's sampling stream
# Bump when the cache file's layout changes (the key already covers the path tracer's code).
CACHE_FORMAT = 1
PATHTRACER_SOURCES = ("cl/pathtrace.cl", "cl/include/rng.h", "cl/include/grid.h",
                      "cl/include/phase.h", "cl/include/majorant.h",
                      "clvol/kernels/pathtrace.py", "clvol/render/pathtrace.py")


# --------------------------------------------------------------------------- metrics

def scores(test, h1, h2, with_flip: bool = True, test_halves=None) -> dict:
    """Noise-corrected errors of ``test`` against the reference ``R = (h1 + h2) / 2``.

    Why E|h1 - h2|^2 / 4 is the reference's noise: write the halves as h_i = mu + e_i with e_1,
    e_2 independent, zero-mean, of the same variance s^2 per pixel (same spp, other seeds). Then
    R = mu + (e_1 + e_2) / 2 has Var R = s^2 / 2, and h1 - h2 = e_1 - e_2 has E|h1 - h2|^2 = 2 s^2,
    so Var R = E|h1 - h2|^2 / 4. A test image t independent of the reference's noise has
    E|t - R|^2 = |t - mu|^2 + Var R (the cross term has mean 0), so
        |t - mu|^2  ~  mean |t - R|^2 - mean |h1 - h2|^2 / 4,
    unbiased over pixels; noise can make it negative where t ~ mu, so the mean is clamped at 0.
    Through a non-linear map f (the tonemap) the same holds to first order in the noise (f(h_i)
    = f(mu) + J e_i); the sRGB curve's slope changes fast near black (where 4096-spp noise is
    tiny in absolute terms) and is 0 above the clamp. relMSE's numerator is linear, but its
    denominator holds the noisy R: R low goes with (t - R)^2 high when t > mu, a second-order
    bias of relative size ~ 4 Var R / (|t - mu| R) -- small when the reference's noise is small
    against the test's error, as it is for 4096-spp references.

    Returns rmse100 (noise-corrected, tonemapped luminance as ``mrpnn_metric`` sees it but not
    rounded to 8 bits: rounding would add ~0.16 of noise to a 1.0 target), relmse
    (noise-corrected, both images times the exposure k), flip, mean (ratio of image means),
    ref_floor_rmse100 (the reference's own noise on the rmse100 scale) and the uncorrected
    rmse100_raw.

    ``test_halves`` = (t1, t2): a noisy test made twice with independent noise (other seeds),
    ``test`` being their mean. Its own noise is removed the same way (Var t = E|t1 - t2|^2 /
    4, independent of the reference's), so what is left estimates |E t - mu|: the test
    method's bias alone.
    """
    t, a, b = (np.asarray(x, np.float64) for x in (test, h1, h2))
    r = 0.5 * (a + b)
    k = mrpnn_exposure(r)
    yt, yr, y1, y2 = (tonemap_srgb(x, k) @ LUMA for x in (t, r, a, b))
    floor_mse = float(np.mean((y1 - y2) ** 2)) / 4.0
    test_mse, test_rel = 0.0, 0.0
    if test_halves is not None:
        u, v = (np.asarray(x, np.float64) for x in test_halves)
        test_mse = float(np.mean((tonemap_srgb(u, k) @ LUMA - tonemap_srgb(v, k) @ LUMA) ** 2)) / 4.0
        test_rel = (u - v) ** 2 / 4.0
    mse = float(np.mean((yt - yr) ** 2)) - test_mse
    den = (k * r) ** 2 + 0.01
    rel = float(np.mean((k * k) * ((t - r) ** 2 - (a - b) ** 2 / 4.0 - test_rel) / den))
    ref_mean = float(np.mean(r))
    return {
        "rmse100": 100.0 * math.sqrt(max(mse - floor_mse, 0.0)),
        "relmse": max(rel, 0.0),
        "flip": flip(t, r) if with_flip else float("nan"),
        "mean": float(np.mean(t)) / ref_mean if ref_mean > 0 else float("nan"),
        "mean_rgb": tuple(float(np.mean(t[..., c]) / max(np.mean(r[..., c]), 1e-30))
                          for c in range(3)),
        "ref_floor_rmse100": 100.0 * math.sqrt(floor_mse),
        "rmse100_raw": 100.0 * math.sqrt(mse),
    }


# --------------------------------------------------------------------------- references

def ensure_fire_frames() -> None:
    """The flame scene reads examples/fire's generated frames: make them if missing."""
    fire = ROOT / "examples" / "fire"
    if not (fire / "fire_0006.npz").exists():
        sys.path.insert(0, str(fire))
        import make_fire
        make_fire.main([])


def bench_scene(path, size: int):
    if Path(path).parent.name == "fire":
        ensure_fire_frames()
    scene = load_scene(path)
    return replace(scene, camera=replace(scene.camera, width=size, height=size))


def code_hash(root: Path = ROOT) -> str:
    h = hashlib.sha256()
    for rel in PATHTRACER_SOURCES:
        h.update(rel.encode() + b"\0" + (root / rel).read_bytes() + b"\0")
    return h.hexdigest()


def reference_key(scene, grid, spp_half: int, seeds=REF_SEEDS, code: str | None = None) -> str:
    """sha256 over everything the reference image depends on (see the module docstring)."""
    d = scene.to_dict()
    d["volume"].pop("file", None)   # a file's bytes are in the density hash; its path is not
    dens = hashlib.sha256(np.ascontiguousarray(grid.density).tobytes())
    dens.update(np.asarray(grid.bbox_min, np.float64).tobytes())
    dens.update(np.asarray(grid.bbox_max, np.float64).tobytes())
    dens.update(str(grid.density.shape).encode())
    if scene.emission is not None:       # the emission grid (from the same file) and its code
        em = scene.emission.load(scene.volume, grid)
        dens.update(np.ascontiguousarray(em.values).tobytes())
        dens.update(np.asarray([*em.bbox_min, *em.bbox_max, *em.colour], np.float64).tobytes())
        dens.update((ROOT / "clvol" / "emission.py").read_bytes())
    blob = json.dumps({"format": CACHE_FORMAT, "scene": d, "density": dens.hexdigest(),
                       "spp_half": int(spp_half), "seeds": list(seeds), "max_order": None,
                       "majorant_block": DEFAULT_BLOCK,
                       "code": code if code is not None else code_hash()},
                      sort_keys=True)
    return hashlib.sha256(blob.encode()).hexdigest()


def reference_path(cache: Path, name: str, scene, key: str) -> Path:
    return Path(cache) / f"{name}_{scene.camera.width}x{scene.camera.height}_{key[:16]}.npz"


def load_reference(path: Path, key: str, keys=("h1", "h2")):
    """((arrays named ``keys``), meta) from a cache file whose stored key equals ``key``,
    else None."""
    if not path.exists():
        return None
    with np.load(path) as z:
        meta = json.loads(str(z["meta"]))
        if meta.get("key") != key:   # a 16-hex-digit name collision: never use it
            return None
        return tuple(z[k] for k in keys), meta


def _save_npz(path: Path, **arrays) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    buf = io.BytesIO()
    np.savez(buf, **arrays)
    with atomic_open(path) as fh:
        fh.write(buf.getvalue())


def make_reference(scene, grid, spp_half: int, path: Path, key: str, name: str,
                   seeds=REF_SEEDS, progress: bool = True):
    """Render (or take from a finished half file) both halves, write the scene's file, and
    remove the half files. A half file carries the same key, so it is never mixed in stale."""
    halves, seconds = [], []
    for i, seed in enumerate(seeds):
        half_path = path.with_name(f"{path.stem}.half{i + 1}.npz")
        got = load_reference(half_path, key, keys=("h",))
        if got is not None:
            print(f"  reference {name}: half {i + 1}/2 from {half_path.name}", flush=True)
            (img,), meta = got
            halves.append(img)
            seconds.append(meta["seconds"])
            continue
        print(f"  reference {name}: half {i + 1}/2, {spp_half} spp, seed {seed} ...", flush=True)
        res = render_pathtrace(scene, spp=spp_half, seed=seed, grid=grid, progress=progress)
        halves.append(res.layers["total"])
        seconds.append(float(res.header["seconds"]))
        _save_npz(half_path, h=halves[-1],
                  meta=np.array(json.dumps({"key": key, "seed": seed, "seconds": seconds[-1]})))
    meta = {"key": key, "scene": name, "spp_half": spp_half, "seeds": list(seeds),
            "seconds": seconds, "made": time.strftime("%Y-%m-%d %H:%M"),
            "machine": machine()}
    _save_npz(path, h1=halves[0], h2=halves[1], meta=np.array(json.dumps(meta)))
    for i in range(len(seeds)):
        path.with_name(f"{path.stem}.half{i + 1}.npz").unlink(missing_ok=True)
    print(f"  reference {name}: {sum(seconds):.1f} s, written to {path}", flush=True)
    return halves[0], halves[1], meta


def reference(name, scene, grid, spp_half, cache: Path, rebuild: bool = False,
              progress: bool = True):
    key = reference_key(scene, grid, spp_half)
    path = reference_path(cache, name, scene, key)
    if rebuild:
        for old in [path] + [path.with_name(f"{path.stem}.half{i}.npz") for i in (1, 2)]:
            old.unlink(missing_ok=True)
    got = load_reference(path, key)
    if got is not None:
        (h1, h2), meta = got
        print(f"  reference {name}: cached {path.name} (made {meta['made']}, "
              f"{sum(meta['seconds']):.0f} s)", flush=True)
        return h1, h2, meta
    return make_reference(scene, grid, spp_half, path, key, name, progress=progress)


# --------------------------------------------------------------------------- test renders

def render_raymarch(scene, ms: str, grid, **options):
    """One ray-marched frame with ``options`` (None: the renderer's default)."""
    given = {k: v for k, v in options.items() if v is not None}
    return Renderer(scene, "raymarch", grid=grid, ms=ms, **given).render()


def median_time(fn, n: int = 3):
    """(last result, median seconds of n runs): the machine is shared, the median is robust."""
    times, out = [], None
    for _ in range(n):
        t0 = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t0)
    return out, statistics.median(times)


def render_methods(scene, grid, weights, repeats: int = 3, ms_resolution=None,
                   pt_lattice: int = 0, pt_view: int = 0, view_options=None,
                   stochastic: int = 0, pt_stochastic: int = 0, stochastic_block=None) -> dict:
    """{method: (image, seconds, spp or None, halves or None)} for METHODS, each warmed up
    once untimed; ``halves``: the two independent renders a noisy row is the mean of.
    ``ms_resolution``: the network's F_ms lattice (None: the renderer's default);
    ``pt_lattice`` > 0: also "pt_lattice", that lattice filled by point queries;
    ``pt_view`` > 0: also "pt_view", the view-space table filled by point queries;
    ``view_options``: Renderer options of the view and pt_view rows (view_block, view_knots,
    supersample; the renderer's defaults for those not given); ``stochastic`` > 0: also
    "stochastic" with that many samples per block (block ``stochastic_block``, None the
    renderer's default), and with ``pt_stochastic`` > 0 "pt_stochastic"."""
    from clvol.render.renderer import Renderer
    vkw = dict(view_options or {})
    skw = {"view_block": stochastic_block} if stochastic_block else {}
    if "supersample" in vkw:
        skw["supersample"] = vkw["supersample"]
    out = {}

    def pt_filled(ms, paths, extra_for_seed):
        """Two renders whose table is filled by point queries with seeds PT_VIEW_SEEDS (and
        the source options ``extra_for_seed(seed)``): so that scores() removes their noise."""
        from clvol.render.pathtrace import point_query
        halves = []
        for seed in PT_VIEW_SEEDS:
            r = Renderer(scene, "raymarch", grid=grid, ms=ms, **extra_for_seed(seed))
            src, _ = r.active_source()
            if src is r.source:   # the source runs here (not a domain or thin fallback)
                src.query = (lambda sd: lambda p, w: point_query(scene, p, w, paths, seed=sd,
                                                                 grid=grid)["Fms"])(seed)
            halves.append(r.render().layers["total"])
        return (0.5 * (halves[0] + halves[1]), float("nan"), paths, halves)

    if pt_view:
        out["pt_view"] = pt_filled("view", pt_view, lambda seed: vkw)
    if stochastic and pt_stochastic:
        out["pt_stochastic"] = pt_filled(
            "stochastic", pt_stochastic,
            lambda seed: dict(skw, view_samples=stochastic, seed=seed))
    if stochastic:
        def stochastic_render():
            return Renderer(scene, "raymarch", grid=grid, ms="stochastic", weights=weights,
                            view_samples=stochastic, seed=STOCHASTIC_SEED, **skw).render()
        stochastic_render()                                          # build kernels
        res, s = median_time(stochastic_render, repeats)
        out["stochastic"] = (res.layers["total"], s, None, None)
    if pt_lattice:
        from clvol.render.ms.network import DEFAULT_NETWORK_RESOLUTION
        from clvol.render.pathtrace import point_query
        from clvol.render.ms.lattice import fill_fms_lattice
        res = ms_resolution or DEFAULT_NETWORK_RESOLUTION
        ms = fill_fms_lattice(scene, res, lambda p, w: point_query(scene, p, w, pt_lattice, seed=11,
                                                                grid=grid)["Fms"])
        out["pt_lattice"] = (render_raymarch(scene, ms="lattice", ms_lattice=ms, grid=grid)
                             .layers["total"], float("nan"), pt_lattice, None)
    for method, ms in (("network", "network"), ("view", "view"), ("wrenninge", "wrenninge"),
                       ("single", "none")):
        kw = ({"weights": weights, "ms_resolution": ms_resolution} if ms == "network" else
              {"weights": weights, **vkw} if ms == "view" else {})
        if ms in ("network", "view"):     # the network at every scene, even outside its domain
            kw["domain_fallback"] = False
        render_raymarch(scene, ms=ms, grid=grid, **kw)              # build kernels, tables
        res, s = median_time(lambda: render_raymarch(scene, ms=ms, grid=grid, **kw), repeats)
        out[method] = (res.layers["total"], s, None, None)
    budget = out["network"][1]
    render_pathtrace(scene, spp=1, grid=grid, progress=False)        # build the kernel
    res = render_pathtrace(scene, spp=None, time_budget=budget, seed=PT_EQUAL_SEED, grid=grid,
                           progress=False)
    out["pt_equal"] = (res.layers["total"], float(res.header["seconds"]), int(res.header["spp"]),
                       None)
    return out


# --------------------------------------------------------------------------- table, target

def check_target(rows: list[dict]) -> list[tuple[str, bool, str]]:
    """[(criterion, passed, detail)] over the network's rows (see the module docstring)."""
    net = [r for r in rows if r["method"] == "network"]
    out = []
    for col, limit in TARGET.items():
        worst = max(net, key=lambda r: r[col])
        out.append((f"worst {col} <= {limit:g}", worst[col] <= limit,
                    f"{worst[col]:.4g} ({worst['scene']})"))
    losses = []
    for r in net:
        base = [b for b in rows if b["scene"] == r["scene"] and b["method"] in BASELINES]
        best = min(base, key=lambda b: b["rmse100"])
        if r["rmse100"] > best["rmse100"]:
            losses.append(f"{r['scene']}: {r['rmse100']:.3g} > {best['method']} {best['rmse100']:.3g}")
    out.append(("network rmse100 <= best baseline on every scene", not losses,
                "; ".join(losses) or f"{len(net)} of {len(net)} scenes"))
    oof = [r for r in rows if r.get("family") == "out"]
    if oof:
        lo, hi = OOF_MEAN_RANGE
        for method in ("network", "stochastic"):
            mine = [r for r in oof if r["method"] == method]
            if not mine:
                continue
            bad = [f"{r['scene']} {_fmt(r['mean_rgb'], 'mean_rgb')}" for r in mine
                   if not all(lo <= x <= hi for x in r["mean_rgb"])]
            out.append((f"out of family ({method}): image means per channel in {lo}-{hi}", not bad,
                        "; ".join(bad) or f"{len(mine)} of {len(mine)} scenes"))
        src = [r for r in oof if r["method"] == "stochastic"] or [r for r in oof if r["method"] == "network"]
        worst = max(src, key=lambda r: r["rmse100"])
        out.append((f"out of family ({worst['method']}): worst rmse100 <= {OOF_RMSE100:g}",
                    worst["rmse100"] <= OOF_RMSE100, f"{worst['rmse100']:.3g} ({worst['scene']})"))
    return out


def _fmt(v, col):
    if v is None or (isinstance(v, float) and math.isnan(v)):
        return "-"
    if col in ("rmse100", "ref_floor_rmse100"):
        return f"{v:.2f}"
    if col == "relmse":
        return f"{v:.2e}"
    if col in ("flip", "mean", "ref_halves_flip"):
        return f"{v:.3f}"
    if col == "seconds":
        return f"{v:.3f}"
    if col == "mean_rgb":
        return " / ".join(f"{x:.3f}" for x in v)
    return str(v)


def markdown(rows, criteria) -> str:
    lines = ["| " + " | ".join(COLUMNS) + " |", "|" + "---|" * len(COLUMNS)]
    lines += ["| " + " | ".join(_fmt(r[c], c) for c in COLUMNS) + " |" for r in rows]
    lines += ["", "| criterion | result | worst |", "|---|---|---|"]
    lines += [f"| {c} | {'PASS' if ok else 'FAIL'} | {d} |" for c, ok, d in criteria]
    return "\n".join(lines) + "\n"


def write_table(path: Path, rows, criteria) -> None:
    if path.suffix == ".md":
        text = markdown(rows, criteria)
    else:
        buf = io.StringIO()
        w = csv.DictWriter(buf, fieldnames=list(COLUMNS), extrasaction="ignore",
                           lineterminator="\n")
        w.writeheader()
        w.writerows(rows)
        text = buf.getvalue()
    with atomic_open(path, "w") as fh:
        fh.write(text)


# --------------------------------------------------------------------------- main

def resolve_scenes(names) -> dict:
    out = {}
    for n in names or list(SCENES):
        if n in SCENES:
            out[n] = SCENES[n]
        elif n.endswith(".toml") and Path(n).is_file():
            out[Path(n).stem] = Path(n)
        else:
            raise ClvolError(f"--scenes {n!r}: a scene file (.toml) or one of {list(SCENES)}")
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--weights", default=None,
                    help="network weight file (default: the shipped model)")
    ap.add_argument("--size", type=int, default=128, help="image width and height (default 128)")
    ap.add_argument("--ref-spp", type=int, default=4096,
                    help="reference samples per pixel, split into two halves (default 4096)")
    ap.add_argument("--quick", action="store_true", help="64x64, 256-spp references")
    ap.add_argument("--scenes", nargs="+", metavar="NAME|FILE",
                    help=f"subset or other scene files (default: all of {list(SCENES)})")
    ap.add_argument("--cache", default=str(Path.home() / ".cache" / "clvol" / "neural_quality"),
                    help="reference cache folder")
    ap.add_argument("--refs-only", action="store_true", help="build missing references and stop")
    ap.add_argument("--rebuild-refs", action="store_true", help="re-render every reference")
    ap.add_argument("--repeats", type=int, default=3, help="timed renders per method (median)")
    ap.add_argument("--pt-lattice", type=int, default=0, metavar="PATHS",
                    help="also a row with the F_ms lattice filled by path-traced point queries "
                         "(PATHS per point): what the lattice leaves, whatever the network")
    ap.add_argument("--pt-view", type=int, default=0, metavar="PATHS",
                    help="also a row with the view-space table filled by path-traced point "
                         "queries (PATHS per point): what the view-space representation leaves")
    ap.add_argument("--view-block", type=int, default=None,
                    help="the view-space source's block side in pixels (rows view and pt_view; "
                         "default: the renderer's)")
    ap.add_argument("--view-knots", type=int, default=None, metavar="K",
                    help="the view-space source's queries per block (rows view and pt_view; "
                         "default: the renderer's)")
    ap.add_argument("--view-supersample", type=int, default=None, metavar="S",
                    help="S x S rays per pixel for the rows view, pt_view, stochastic and "
                         "pt_stochastic (--view-block and --stochastic-block then "
                         "count sub-pixels): separates the representation from pixel-centre "
                         "sampling, since the references average each pixel's area")
    ap.add_argument("--stochastic", type=int, default=0, metavar="N",
                    help="also a row with --ms stochastic after N samples per block (the still "
                         "view's accumulation)")
    ap.add_argument("--stochastic-block", type=int, default=None, metavar="B",
                    help="the stochastic source's block side (default: the renderer's)")
    ap.add_argument("--pt-stochastic", type=int, default=0, metavar="PATHS",
                    help="with --stochastic: also a row with the stochastic table filled by "
                         "path-traced point queries (PATHS per point), noise removed")
    ap.add_argument("--ms-resolution", type=int, default=None,
                    help="the network's F_ms lattice (default: the renderer's); the target is "
                         "judged at the default, other values show what the lattice costs")
    ap.add_argument("--out", help="also write the table to this .md or .csv file")
    args = ap.parse_args(argv)
    try:
        return run(args)
    except ClvolError as exc:
        print(f"neural_quality: error: {str(exc).splitlines()[0]}", file=sys.stderr)
        return 2


def run(args) -> int:
    if args.quick:
        args.size, args.ref_spp = 64, 256
    if not (8 <= args.size <= 4096):
        raise ClvolError(f"--size {args.size}: must be from 8 to 4096 pixels")
    if not (args.ref_spp >= 2 and args.ref_spp % 2 == 0):
        raise ClvolError(f"--ref-spp {args.ref_spp}: must be an even number >= 2 (two halves)")
    if args.pt_lattice < 0:
        raise ClvolError(f"--pt-lattice {args.pt_lattice}: must be >= 0 paths per point (0: no row)")
    if args.pt_view < 0:
        raise ClvolError(f"--pt-view {args.pt_view}: must be >= 0 paths per point (0: no row)")
    if args.stochastic < 0 or args.pt_stochastic < 0:
        raise ClvolError("--stochastic and --pt-stochastic must be >= 0 (0: no row)")
    if args.pt_stochastic and not args.stochastic:
        raise ClvolError("--pt-stochastic needs --stochastic N (the samples per block)")
    if args.repeats < 1:
        raise ClvolError(f"--repeats {args.repeats}: must be >= 1")
    out_path = Path(args.out) if args.out else None
    if out_path is not None and out_path.suffix not in (".md", ".csv"):
        raise ClvolError(f"--out {args.out}: must end in .md or .csv")
    if out_path is not None and not out_path.parent.is_dir():
        raise ClvolError(f"--out {args.out}: folder {out_path.parent} does not exist")
    weights = Path(args.weights) if args.weights else shipped_weights()
    if not args.refs_only and not weights.is_file():
        raise ClvolError(f"--weights {weights}: no such file")
    if not args.refs_only and not flip_available():
        raise ClvolError("FLIP needs the flip-evaluator package: pip install 'clvol[quality]'")
    scenes = resolve_scenes(args.scenes)
    cache = Path(args.cache)
    from clvol.runtime import get_runtime
    rt = get_runtime()
    print(machine(rt))
    print(f"command: {' '.join(sys.argv)}")
    print(f"{len(scenes)} scenes at {args.size}x{args.size}; references {args.ref_spp} spp "
          f"(2 x {args.ref_spp // 2}) in {cache}; weights {weights}; network F_ms lattice "
          f"{args.ms_resolution or 'default'}", flush=True)

    rows = []
    for name, path in scenes.items():
        scene = bench_scene(path, args.size)
        grid = scene.volume.load()
        family = "out" if getattr(scene.volume, "generator", None) in OUT_OF_FAMILY_GENERATORS else "in"
        h1, h2, _ = reference(name, scene, grid, args.ref_spp // 2, cache, args.rebuild_refs)
        if args.refs_only:
            continue
        renders = render_methods(scene, grid, weights, args.repeats, args.ms_resolution,
                                 args.pt_lattice, args.pt_view,
                                 {k: v for k, v in (("view_block", args.view_block),
                                                    ("view_knots", args.view_knots),
                                                    ("supersample", args.view_supersample))
                                  if v is not None},
                                 args.stochastic, args.pt_stochastic, args.stochastic_block)
        if scene.emission is not None:
            # What the real-time methods skip: emitted light scattered at least once, from a
            # short path-traced render (its own noise is small against the image mean).
            em = render_pathtrace(scene, spp=64, seed=PT_EQUAL_SEED + 1, grid=grid,
                                  progress=False)
            share = float(em.layers["emission_scattered"].mean() / max(em.total.mean(), 1e-30))
            direct = float(em.layers["emission"].mean() / max(em.total.mean(), 1e-30))
            print(f"  {name}: emission seen directly {100 * direct:.1f}% and scattered "
                  f"{100 * share:.1f}% of the path tracer's image mean (64 spp); the real-time "
                  f"methods skip the scattered part", flush=True)
        floor_flip = flip(h1, h2)
        methods = (METHODS + (("pt_lattice",) if args.pt_lattice else ())
                   + (("pt_view",) if args.pt_view else ())
                   + (("stochastic",) if args.stochastic else ())
                   + (("pt_stochastic",) if args.pt_stochastic else ()))
        for method in methods:
            img, secs, spp, halves = renders[method]
            s = scores(img, h1, h2, test_halves=halves)
            rows.append({"scene": name, "family": family, "method": method, **s,
                         "seconds": secs, "spp": spp, "ref_halves_flip": floor_flip})
        print(f"\n{name} ({path.name}; reference noise: rmse100 {s['ref_floor_rmse100']:.2f}, "
              f"FLIP(half 1, half 2) {floor_flip:.3f}; load {load_average()})")
        print(f"  {'method':<10} {'rmse100':>8} {'relMSE':>9} {'FLIP':>6} {'mean':>6} "
              f"{'seconds':>8}  (rmse100 without noise removal)")
        for r in rows[-len(methods):]:
            extra = f", {r['spp']} spp" if r["spp"] is not None else ""
            print(f"  {r['method']:<10} {r['rmse100']:8.2f} {r['relmse']:9.2e} {r['flip']:6.3f} "
                  f"{r['mean']:6.3f} {r['seconds']:8.3f}  ({r['rmse100_raw']:.2f}{extra})",
                  flush=True)
    if args.refs_only:
        print("references ready")
        return 0

    criteria = check_target(rows)
    print("\n" + markdown(rows, criteria))
    for crit, ok, detail in criteria:
        print(f"{'PASS' if ok else 'FAIL'}  {crit}: {detail}")
    print(machine(rt))
    if out_path is not None:
        write_table(out_path, rows, criteria)
        print(f"wrote {out_path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
