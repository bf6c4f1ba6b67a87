#!/usr/bin/env python3
"""One-command device suite: kernel-vs-twin checks and the main timings on one OpenCL device.

    python bench/device_suite.py --out OUT [--device SPEC] [--budget-s 140] [--quick]
                                 [--twins tiny|full|none] [--sizes 256 512 1024]

SPEC as for ``clvol --device`` (default: the first GPU, else the first CPU). Steps:

1. **Twins**: the kernel-vs-twin tests (``tests/test_<stem>.py`` for each ``cl/<stem>.cl``, plus
   every other ``@pytest.mark.oclgrind`` test) run through pytest on that device
   (``--cl-device``, tests/conftest.py), one pytest process per file, several at once.
   ``--twins tiny`` (default) runs the tiny adversarial inputs (the ``oclgrind`` marker: the set
   Oclgrind checks); ``full`` every test of those files; ``none`` skips them.
2. **Timings** (medians, in this process, while the twins run in theirs: their kernels are
   tiny, but a row taken while they still ran is flagged ``overlap``): the default method
   (ray march + network MS, examples/cloud.toml) at each ``--sizes`` for a still frame, a camera
   orbit step and a light change, with the plain march (``--ms none``) beside it; the fused
   gather + MLP (``NetworkSource.evaluate``) at 16K-1M queries; the MLP alone; the gather
   alone; the graded and exact light transmittance; the path tracer's samples/s and
   point-query labels/s. The path tracer's programs are built in a background thread from the
   start (the build releases the GIL; NVIDIA's compiler took ~57 s for one of them). Beside
   the path tracer's rows: its global-memory bytes per sample and the bound memory bandwidth
   sets on samples/s (bench/pt_traffic.py: steps from the kernel's rows, majorant reads from
   a twin replay of a few paths, after the timings).
3. **Output** under ``--out``: ``device_suite.json`` (everything), ``device_suite.md`` (tables),
   ``twins.log`` (the pytest output of every twin file). Printed too.

``--budget-s`` (default 140): past it no new timing starts (the rest are listed as skipped for
the budget) and twin runs still going are stopped (listed as not finished); a watchdog writes
what was measured and exits 3 if the process is still running 25 s after the budget (a hung
build or launch). Exit status: 0 when every twin that ran passed and every timing that ran
worked, 1 otherwise, 3 from the watchdog.

``--quick``: tiny sizes, for a dry run on a CPU (PoCL, rusticl): the CI runs it.
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import os
import platform
import shutil
import statistics
import subprocess
import sys
import tempfile
import threading
import time
import traceback
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np

from _common import ROOT, cpu_model, load_average, rot_y  # noqa: E402  (puts the checkout first)

T0 = time.perf_counter()


def now() -> float:
    return time.perf_counter() - T0


def log(msg: str) -> None:
    print(f"[{now():6.1f} s] {msg}", flush=True)


# --------------------------------------------------------------------------- settings

@dataclasses.dataclass
class Settings:
    sizes: list
    frames: int
    queries: list            # fused gather + MLP
    mlp_n: int
    gather_n: int
    trans_base: int
    trans_repeats: int
    pt_size: int
    pt_volume: int
    pt_spl: int
    pt_repeats: int
    label_points: int
    label_paths: int
    pt_replay: int           # paths replayed by the twin to count majorant reads (pt_traffic)
    pt_count_paths: int      # paths per label point of the count run beside the label row


FULL = Settings(sizes=[256, 512, 1024], frames=5, queries=[16384, 65536, 262144, 1048576],
                mlp_n=262144, gather_n=262144, trans_base=256, trans_repeats=5, pt_size=256,
                pt_volume=128, pt_spl=4, pt_repeats=5, label_points=4096, label_paths=256,
                pt_replay=128, pt_count_paths=16)
QUICK = Settings(sizes=[32, 64], frames=2, queries=[4096, 16384], mlp_n=4096, gather_n=4096,
                 trans_base=32, trans_repeats=2, pt_size=16, pt_volume=32, pt_spl=1,
                 pt_repeats=2, label_points=64, label_paths=16, pt_replay=16, pt_count_paths=4)


# --------------------------------------------------------------------------- machine

def device_info(entry) -> dict:
    from clvol.runtime import describe_lanes
    d = entry.device

    def get(name, default=None):
        try:
            v = getattr(d, name)
            return v.strip() if isinstance(v, str) else v
        except Exception:  # noqa: BLE001 - a driver may not know a query
            return default

    return {"spec": entry.spec, "label": entry.label, "kind": entry.kind,
            "platform": entry.platform.name.strip(),
            "platform_version": entry.platform.version.strip(),
            "device_version": get("version"), "driver_version": get("driver_version"),
            "opencl_c_version": get("opencl_c_version"),
            "compute_units": get("max_compute_units"), "clock_mhz": get("max_clock_frequency"),
            "global_mem_gib": round(get("global_mem_size", 0) / 2**30, 2),
            "max_alloc_gib": round(get("max_mem_alloc_size", 0) / 2**30, 2),
            "local_mem_kib": round(get("local_mem_size", 0) / 2**10, 1),
            "max_work_group_size": get("max_work_group_size"),
            "preferred_vector_width_float": get("preferred_vector_width_float"),
            "native_vector_width_float": get("native_vector_width_float"),
            "lanes": describe_lanes(entry)}


def machine(entry) -> dict:
    import pyopencl
    gpu_name = None
    if shutil.which("nvidia-smi"):
        try:
            gpu_name = subprocess.run(
                ["nvidia-smi", "--query-gpu=name,driver_version,memory.total,clocks.max.sm",
                 "--format=csv,noheader"], capture_output=True, text=True, timeout=20).stdout.strip()
        except Exception:  # noqa: BLE001
            pass
    return {"cpu": cpu_model(), "logical_cores": os.cpu_count(),
            "python": platform.python_version(), "numpy": np.__version__,
            "pyopencl": pyopencl.VERSION_TEXT, "load_average_start": load_average(),
            "date": time.strftime("%Y-%m-%d %H:%M:%S %Z"), "nvidia_smi": gpu_name,
            "host": platform.node(), "device": device_info(entry)}


# --------------------------------------------------------------------------- twins

def twin_files() -> list[str]:
    """tests/conftest.py's TWIN_FILES (one list for the test suite, scripts/twins_on_devices.py
    and this), then the other files with tiny-input kernel tests (the environment map's
    march, ...)."""
    sys.path.insert(0, str(ROOT / "tests"))
    from conftest import TWIN_FILES
    files = list(TWIN_FILES)
    for p in sorted((ROOT / "tests").glob("test_*.py")):
        rel = f"tests/{p.name}"
        if rel not in files and p.name != "test_oclgrind.py" and \
                "pytest.mark.oclgrind" in p.read_text():
            files.append(rel)
    return files


class Twins:
    """The twin test files run as pytest subprocesses, ``jobs`` at a time, in a thread."""

    def __init__(self, spec: str, mode: str, jobs: int, tmp: Path, deadline: float,
                 files: list[str] | None = None):
        self.spec, self.mode, self.jobs, self.tmp, self.deadline = spec, mode, jobs, tmp, deadline
        self.files = list(files) if files else twin_files()
        self.results: dict[str, dict] = {}
        self.procs: dict[str, subprocess.Popen] = {}
        self.lock = threading.Lock()
        self.stopped = False
        self.thread = threading.Thread(target=self._run, daemon=True)
        # the slowest files first (builds of the path tracer's programs, the fused network)
        order = ["pathtrace", "gather_mlp", "gather", "mlp", "envmap", "raymarch"]
        self.files.sort(key=lambda f: next((i for i, s in enumerate(order)
                                            if f == f"tests/test_{s}.py"), len(order)))

    def start(self):
        self.t_start = now()
        self.thread.start()

    def running(self) -> bool:
        return self.thread.is_alive()

    def _cmd(self, f: str, xml: Path) -> list[str]:
        cmd = [sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "-rfE",
               "--cl-device", self.spec, f"--junitxml={xml}", f]
        if self.mode == "tiny":
            cmd[-1:-1] = ["-m", "oclgrind"]
        return cmd

    def _run(self):
        env = dict(os.environ)
        env["PYTHONPATH"] = os.pathsep.join([str(ROOT)] + [p for p in env.get(
            "PYTHONPATH", "").split(os.pathsep) if p])
        env.pop("PYOPENCL_CTX", None)
        todo = list(self.files)
        live: dict[str, tuple] = {}
        while todo or live:
            while todo and len(live) < self.jobs and not self.stopped:
                f = todo.pop(0)
                xml = self.tmp / (Path(f).stem + ".xml")
                out = open(self.tmp / (Path(f).stem + ".log"), "w")
                p = subprocess.Popen(self._cmd(f, xml), cwd=ROOT, env=env, stdout=out,
                                     stderr=subprocess.STDOUT, start_new_session=True)
                with self.lock:
                    self.procs[f] = p
                live[f] = (p, xml, out, now())
            if self.stopped and todo:
                for f in todo:
                    self.results[f] = {"status": "not started (budget)"}
                todo = []
            for f, (p, xml, out, t0) in list(live.items()):
                if p.poll() is None and now() > self.deadline:
                    self._kill(p)
                if p.poll() is not None:
                    out.close()
                    self.results[f] = self._collect(f, p.returncode, xml, now() - t0)
                    del live[f]
            time.sleep(0.2)

    @staticmethod
    def _kill(p):
        try:
            os.killpg(p.pid, 9)
        except OSError:
            pass
        p.wait()

    def stop(self):
        """Stop what still runs (the budget is spent)."""
        self.stopped = True
        self.deadline = min(self.deadline, now())
        self.thread.join(timeout=30)

    def _collect(self, f: str, rc: int, xml: Path, secs: float) -> dict:
        res = {"returncode": rc, "seconds": round(secs, 1), "tests": []}
        if xml.is_file():
            try:
                for tc in ET.parse(xml).getroot().iter("testcase"):
                    st = "passed"
                    msg = ""
                    for tag in ("failure", "error", "skipped"):
                        el = tc.find(tag)
                        if el is not None:
                            st = {"failure": "failed", "error": "error", "skipped": "skipped"}[tag]
                            msg = (el.get("message") or "")[:300]
                    res["tests"].append({"name": tc.get("name"), "status": st,
                                         "seconds": float(tc.get("time") or 0), "message": msg})
            except ET.ParseError as exc:
                res["xml_error"] = str(exc)
        n = {s: sum(t["status"] == s for t in res["tests"])
             for s in ("passed", "failed", "error", "skipped")}
        res.update(n)
        if rc == 5:
            res["status"] = "no tests selected"
        elif rc < 0 or (rc != 0 and not res["tests"]):
            res["status"] = ("stopped at the budget" if rc == -9 else f"crashed (exit {rc})")
        else:
            res["status"] = "passed" if rc == 0 else "FAILED"
        return res


# --------------------------------------------------------------------------- timing helpers

def med_ms(secs) -> float:
    return round(statistics.median(secs) * 1e3, 3)


def timed(fn, repeats: int, finish) -> list[float]:
    out = []
    for _ in range(repeats):
        finish()
        t0 = time.perf_counter()
        fn()
        finish()
        out.append(time.perf_counter() - t0)
    return out


def cloud_scene(size: int):
    from clvol.scene import load_scene
    sc = load_scene(ROOT / "examples" / "cloud.toml")
    return dataclasses.replace(sc, camera=dataclasses.replace(sc.camera, width=size, height=size))


# --------------------------------------------------------------------------- timings

def t_raymarch(ctx) -> list[dict]:
    """The default method (ray march + network MS) and the plain march, per size and change."""
    from clvol.render.renderer import Renderer
    s, rt = ctx["settings"], ctx["rt"]
    rows = []
    grid = cloud_scene(16).volume.load()
    for size in s.sizes:
        if ctx["over"]():
            rows.append({"size": size, "skipped": "budget"})
            continue
        sc = cloud_scene(size)
        for method, kw in (("default", {}), ("plain march (--ms none)", {"ms": "none"})):
            t_build = time.perf_counter()
            r = Renderer(sc, grid=grid, **kw)
            r.render()                      # builds, uploads, first light field and lattice
            rt.finish()
            first = time.perf_counter() - t_build
            row = {"size": size, "method": method, "first_frame_s": round(first, 3),
                   "overlap": ctx["overlap"]()}
            changes = {
                "still": [dict() for _ in range(s.frames)],
                "camera orbit (3 deg/frame)": [
                    {"camera": dataclasses.replace(sc.camera, origin=rot_y(sc.camera.origin, 3 * i))}
                    for i in range(1, s.frames + 1)],
                "light change (5 deg/frame)": [
                    {"light": dataclasses.replace(sc.light, direction=rot_y(sc.light.direction, 5 * i))}
                    for i in range(1, s.frames + 1)]}
            for motion, todo in changes.items():
                secs, net = [], []
                for ch in todo:
                    t0 = time.perf_counter()
                    res = r.render(**ch)
                    secs.append(time.perf_counter() - t0)
                    h = res.header
                    net.append(sum(float(h.get(k, 0.0)) for k in ("seconds.gather",
                                                                   "seconds.network")))
                row[motion + " ms"] = med_ms(secs)
                if method == "default":
                    row[motion + " network stage ms"] = med_ms(net)
            rows.append(row)
            log(f"  raymarch {size}^2 {method}: " + ", ".join(
                f"{k} {v}" for k, v in row.items() if k.endswith(" ms")))
    return rows


def _network_setup(ctx):
    if "net" not in ctx:
        ctx["wait_warm"](("network",))
        from clvol.render.ms import network as rnet
        from clvol.scene import Medium, Phase
        from clvol.volume.generators import generate
        rt = ctx["rt"]
        grid = generate("cloud", seed=1, resolution=128 if not ctx["quick"] else 32)
        medium = Medium(40.0, (0.999,) * 3, Phase.hg(0.857))
        light = np.array([0.3, 0.5, 0.8]) / np.linalg.norm([0.3, 0.5, 0.8])
        src = rnet.NetworkSource(rnet.shipped_weights(), grid, medium, rt, fused=True)
        pyr = src.pyramid
        rs = np.random.default_rng(0)
        occ = np.argwhere(pyr.level(0) > 0)
        n = max(ctx["settings"].queries + [ctx["settings"].gather_n])
        pick = occ[rs.integers(0, len(occ), n)][:, ::-1]
        vox = pyr.cube_size / pyr.base_resolution
        pts = pyr.cube_min + (pick + rs.uniform(0, 1, pick.shape)) * vox
        om = rs.normal(size=(n, 3))
        om /= np.linalg.norm(om, axis=1, keepdims=True)
        src.evaluate(pts[:256], om[:256], light)        # builds, graded fields, bake
        rt.finish()
        ctx["net"] = dict(src=src, pts=pts, om=om, light=light, medium=medium)
    return ctx["net"]


def t_fused(ctx) -> list[dict]:
    """Fused gather + MLP (the network MS source's evaluate) at each query count."""
    net, rt, s = _network_setup(ctx), ctx["rt"], ctx["settings"]
    rows = []
    for n in s.queries:
        if ctx["over"]():
            rows.append({"queries": n, "skipped": "budget"})
            continue
        fn = lambda: net["src"].evaluate(net["pts"][:n], net["om"][:n], net["light"])  # noqa: E731
        fn()
        secs = timed(fn, 5 if not ctx["quick"] else 2, rt.finish)
        ms = med_ms(secs)
        rows.append({"queries": n, "wall ms": ms, "Mqueries/s": round(n / ms * 1e-3, 3),
                     "overlap": ctx["overlap"]()})
        log(f"  fused gather+MLP {n}: {ms} ms, {rows[-1]['Mqueries/s']} Mqueries/s")
    return rows


def t_mlp(ctx) -> list[dict]:
    """The network's forward pass alone on device buffers (cl/mlp.cl)."""
    from clvol.kernels.mlp import MlpKernel
    from clvol.features.weights import Architecture, MlpWeights, default_params, feature_contract
    from reference import mlp as ref
    rt, n = ctx["rt"], ctx["settings"].mlp_n
    arch = Architecture()
    weights = MlpWeights(arch, default_params(arch, np.random.default_rng(0)), feature_contract())
    k = MlpKernel(weights, runtime=rt)
    block = min(n, 8192)
    f, c = ref.random_inputs(block, np.random.default_rng(1), lobes=[(0.8, 0.7), (-0.3, 0.3)])
    reps = -(-n // block)
    f = np.ascontiguousarray(np.tile(f, (reps, 1, 1))[:n])
    c = np.ascontiguousarray(np.tile(c, (reps, 1))[:n])
    fb, cb = rt.upload(f), rt.upload(c)
    rows = []
    for mode, alb in (("grey", None), ("rgb", (0.92, 0.99, 0.94))):
        ch = 1 if alb is None else 3
        out = rt.alloc((n, ch))
        k.enqueue(fb, cb, n, out, alb).wait()
        secs = timed(lambda: k.enqueue(fb, cb, n, out, alb).wait(), 5, rt.finish)
        ms = med_ms(secs)
        rows.append({"queries": n, "mode": mode, "wall ms": ms,
                     "M evaluations/s": round(n * ch / ms * 1e-3, 3),
                     "multiply-adds per evaluation": arch.n_macs()["total"],
                     "overlap": ctx["overlap"]()})
        log(f"  MLP {n} {mode}: {ms} ms")
    return rows


def t_gather(ctx) -> list[dict]:
    """The gather alone (render mode, feature buffers kept between calls)."""
    from clvol.kernels.gather import gather
    net, rt, n = _network_setup(ctx), ctx["rt"], ctx["settings"].gather_n
    src = net["src"]
    w = src.weights
    graded = src.graded(net["light"], net["medium"].density_scale)
    kept = {}

    def run():
        kept["g"] = gather(src.pyramid, graded, net["pts"][:n], net["om"][:n], net["light"],
                           net["medium"], 0.999, mode="render", level_weights=w.level_weights,
                           bias=w.level_bias, as_buffers=True, reuse=kept.get("g"))
    run()
    ms = med_ms(timed(run, 5, rt.finish))
    log(f"  gather {n}: {ms} ms")
    return [{"queries": n, "wall ms": ms, "Mqueries/s": round(n / ms * 1e-3, 3),
             "overlap": ctx["overlap"]()}]


def t_transmittance(ctx) -> list[dict]:
    """Graded transmittance (every level) and the exact light field, per new light direction."""
    from clvol.kernels import transmittance as kt
    from clvol.kernels.pyramid import build_pyramid
    from clvol.volume.generators import generate
    rt, s = ctx["rt"], ctx["settings"]
    grid = generate("cloud", seed=1, resolution=96 if not ctx["quick"] else 24)
    pyr = build_pyramid(grid, s.trans_base, runtime=rt)
    rs = np.random.default_rng(0)
    dirs = [np.array([0.6, 0.9, 0.3]) + rs.normal(0, 0.02, 3) for _ in range(s.trans_repeats)]
    kt.sweep_layout(pyr, 1)
    kt.graded_transmittance(pyr, 64.0, dirs[0])
    kt.light_transmittance(pyr, 64.0, dirs[0], as_buffer=True)
    rows = []
    for label, fn in (("graded, all levels", lambda d: kt.graded_transmittance(pyr, 64.0, d)),
                      ("exact, level 0", lambda d: kt.light_transmittance(pyr, 64.0, d,
                                                                           as_buffer=True))):
        it = iter(dirs * 2)
        ms = med_ms(timed(lambda: fn(next(it)), len(dirs), rt.finish))
        rows.append({"base": s.trans_base, "field": label, "wall ms": ms, "levels": pyr.n_levels,
                     "overlap": ctx["overlap"]()})
        log(f"  transmittance {s.trans_base}^3 {label}: {ms} ms")
    return rows


def pathtrace_setup(ctx, parts=("render", "query")):
    """The path tracer's scene and its render and query programs (``parts``: which to build;
    a warm-up process builds one each)."""
    from clvol.kernels.pathtrace import PathTracer
    from clvol.render.pathtrace import _medium
    from clvol.scene import Camera, Light, Phase, Scene, VolumeSpec
    from clvol.scene import Medium as SceneMedium
    s, rt = ctx["settings"], ctx["rt"]
    l = np.array([0.6, 0.9, 0.3])
    scene = Scene(path=None, volume=VolumeSpec(file=None, generator="cloud", seed=1,
                                               resolution=s.pt_volume),
                  medium=SceneMedium(density_scale=64.0, albedo=(0.99,) * 3, phase=Phase.hg(0.8)),
                  light=Light(direction=tuple(l / np.linalg.norm(l))),
                  camera=Camera((0.0, 0.3, 2.4), (0.0, 0.0, 0.0), (0.0, 1.0, 0.0), 35.0,
                                s.pt_size, s.pt_size))
    grid = scene.volume.load()
    out = dict(scene=scene, grid=grid)
    if "render" in parts:
        t0 = time.perf_counter()
        out["pt"] = pt = PathTracer(_medium(scene, grid, None, scene.light.irradiance, None),
                                    8, runtime=rt)
        pt.render_batch(dataclasses.replace(scene.camera, width=2, height=2), 0, 0, 1)
        out["build_render_s"] = round(time.perf_counter() - t0, 2)
    if "query" in parts:
        from clvol.kernels.pathtrace import QUERY_LANES, path_lanes, specialisation
        t0 = time.perf_counter()
        # the program point_query builds (its PathTracer: the scene's medium, a unit sun)
        med = _medium(scene, grid, None, (1.0, 1.0, 1.0), None)
        defines = specialisation(med, True)[0]
        rt.program("pathtrace", {"PT_LANES": path_lanes(rt, QUERY_LANES), **defines})
        out["build_query_s"] = round(time.perf_counter() - t0, 2)
    return out


def t_pathtrace(ctx) -> list[dict]:
    """Samples/s of a frame (one launch of spl samples per pixel) and point-query labels/s."""
    from clvol.render.pathtrace import point_query
    s, rt = ctx["settings"], ctx["rt"]
    if not ctx["wait_warm"](("pt-render", "pt-query")):
        return [{"skipped": "path tracer programs still building at the budget"}]
    p = pathtrace_setup(ctx)
    pt, scene = p["pt"], p["scene"]
    cam = scene.camera
    n = cam.width * cam.height * s.pt_spl
    pt.render_batch(cam, 0, 0, s.pt_spl)
    it = iter(range(1, 100))
    first = {}   # the first timed launch's rows (samples spl..2 spl - 1), for pt_traffic

    def launch():
        k = next(it)
        r = pt.render_batch(cam, 0, k * s.pt_spl, s.pt_spl)
        if k == 1:
            first["rows"] = r
    secs = timed(launch, s.pt_repeats, rt.finish)
    ms = med_ms(secs)
    rows = [{"path": f"render {cam.width}^2 x {s.pt_spl} spp, cloud {s.pt_volume}^3",
             "wall ms": ms, "M samples/s": round(n / ms * 1e-3, 4),
             "build s (render program)": p["build_render_s"], "overlap": ctx["overlap"]()}]
    log(f"  path tracer render: {ms} ms, {rows[-1]['M samples/s']} M samples/s")
    if ctx["over"]():
        return rows + [{"path": "labels", "skipped": "budget"}]
    import pt_traffic
    pts, om = pt_traffic.label_inputs(s)
    run = lambda: point_query(scene, pts, om, s.label_paths, seed=5, grid=p["grid"],  # noqa: E731
                              runtime=rt)
    run()
    ms = med_ms(timed(run, max(2, s.pt_repeats - 2), rt.finish))
    rows.append({"path": f"labels: {s.label_points} points x {s.label_paths} paths",
                 "wall ms": ms, "labels/s": round(s.label_points / ms * 1e3, 1),
                 "M paths/s": round(s.label_points * s.label_paths / ms * 1e-3, 4),
                 "build s (query program)": p["build_query_s"], "overlap": ctx["overlap"]()})
    log(f"  path tracer labels: {ms} ms")
    if ctx["over"]():
        rows[0]["traffic"] = rows[1]["traffic"] = "skipped (budget)"
        return rows
    pt_traffic_columns(ctx, p, first["rows"], pts, om, rows)
    return rows


def pt_traffic_columns(ctx, p, render_rows, pts, om, rows) -> None:
    """Bytes per sample and the memory-bandwidth bound beside the path tracer's rows
    (bench/pt_traffic.py: the model, and the full count for the docs): steps and vertices
    from the kernel's own rows (the render row's first timed launch; for the labels, a count
    run of the label points x pt_count_paths of their paths, a subset of the timed ones),
    majorant reads per step from a twin replay of pt_replay paths of each kind (host only,
    after the timings)."""
    import pt_traffic
    s, rt = ctx["settings"], ctx["rt"]
    t0 = time.perf_counter()
    pt, cam = p["pt"], p["scene"].camera
    label = rt.entry.label
    rep = pt_traffic.replay_render(pt, cam, 0, s.pt_spl, render_rows,
                                   min(s.pt_replay, cam.width * cam.height))
    summ = {"render": pt_traffic.summary(pt_traffic.row_counts(render_rows), rep, False)}
    qt = pt_traffic.query_tracer(p, rt)
    qrows = qt.query_batch(rt.to_device(pts.astype(np.float32)),
                           rt.to_device(om.astype(np.float32)), len(pts), 5, 0,
                           min(s.pt_count_paths, s.label_paths))
    qrep = pt_traffic.replay_query(qt, rt, pts, om, 5, min(s.pt_replay, len(pts)))
    summ["labels"] = pt_traffic.summary(pt_traffic.row_counts(qrows), qrep, True)
    for row, (kind, key) in zip(rows, (("render", "M samples/s"), ("labels", "M paths/s"))):
        cols, card = pt_traffic.suite_row(summ[kind], label)
        row.update(cols)
        if card and key in row:
            row[f"% of {card} bound (words / sectors)"] = pt_traffic.fraction(
                row[key], summ[kind], card)
        log(f"  path tracer {kind}: {summ[kind]['steps']:.2f} steps, "
            f"{summ[kind]['majorant_reads']:.1f} majorant reads per sample -> "
            f"{cols['B/sample (words / 32-B sectors)']} B/sample (words / 32-B sectors); "
            "bandwidth bound (no caches) "
            + ", ".join(f"{k[len('BW bound '):].split(' M/s')[0]} {v} M/s" for k, v in cols.items()
                        if k.startswith("BW bound")))
    log(f"  path tracer traffic count: {time.perf_counter() - t0:.1f} s")


def warm(name: str, ctx) -> None:
    """What a warm-up process builds (``--warm NAME``): the same programs the timings build,
    so that the driver's on-disk program cache (NVIDIA's ComputeCache, PoCL's kernel cache)
    holds them when the timings ask; processes, not threads, so a driver that builds one
    program at a time per process still builds these side by side."""
    if name == "pt-render":
        pathtrace_setup(ctx, ("render",))
    elif name == "pt-query":
        pathtrace_setup(ctx, ("query",))
    elif name == "network":
        _network_setup(ctx)
        from clvol.kernels.mlp import MlpKernel
        from clvol.features.weights import Architecture, MlpWeights, default_params, feature_contract
        arch = Architecture()
        MlpKernel(MlpWeights(arch, default_params(arch, np.random.default_rng(0)),
                             feature_contract()), runtime=ctx["rt"])
    ctx["rt"].finish()


WARM = ("pt-render", "pt-query", "network")

TIMINGS = [("raymarch", t_raymarch), ("fused gather+MLP", t_fused), ("MLP", t_mlp),
           ("gather", t_gather), ("transmittance", t_transmittance),
           ("path tracer", t_pathtrace)]


# --------------------------------------------------------------------------- report

def markdown(report: dict) -> str:
    m, d = report["machine"], report["machine"]["device"]
    lines = [f"# Device suite: {d['label']}", "",
             f"- device `{d['spec']}` {d['kind']}, {d['compute_units']} CUs, "
             f"{d['global_mem_gib']} GiB, OpenCL C {d['opencl_c_version']}, driver "
             f"{d['driver_version']}, platform {d['platform_version']}",
             f"- preferred / native float vector width {d['preferred_vector_width_float']} / "
             f"{d['native_vector_width_float']}; {d.get('lanes')}",
             f"- host: {m['cpu']}, {m['logical_cores']} logical cores, Python {m['python']}, "
             f"pyopencl {m['pyopencl']}; load average {m['load_average_start']} at the start, "
             f"{report.get('load_average_end')} at the end; {m['date']}",
             f"- settings: {'quick' if report['quick'] else 'full'} "
             f"{json.dumps(report['settings'])}; budget {report['budget_s']} s; "
             f"total {report.get('total_s')} s"]
    if m.get("nvidia_smi"):
        lines.append(f"- nvidia-smi: {m['nvidia_smi']}")
    lines += ["", "## Kernel vs twin", "",
              f"mode `{report['twins_mode']}`; files run as separate pytest processes "
              "(`--cl-device`) while the timings ran", "",
              "| file | status | passed | failed | skipped | s |", "|---|---|---|---|---|---|"]
    for f, r in report["twins"].items():
        lines.append(f"| {f} | {r.get('status')} | {r.get('passed', '')} | "
                     f"{r.get('failed', 0) + r.get('error', 0) if 'failed' in r else ''} | "
                     f"{r.get('skipped', '')} | {r.get('seconds', '')} |")
        for t in r.get("tests", []):
            if t["status"] in ("failed", "error"):
                lines.append(f"|  ↳ {t['name']} | {t['status']} | | | | {t['message'][:150]} |")
    lines += ["", "## Timings (medians; wall clock; `overlap`: twin tests were still running)"]
    for name, res in report["timings"].items():
        lines += ["", f"### {name}", ""]
        if isinstance(res, dict):
            lines.append(f"{res.get('skipped') or res.get('error')}")
            continue
        keys = []
        for row in res:
            keys += [k for k in row if k not in keys]
        lines += ["| " + " | ".join(keys) + " |", "|" + "---|" * len(keys)]
        for row in res:
            lines.append("| " + " | ".join(str(row.get(k, "")) for k in keys) + " |")
    if report.get("notes"):
        lines += ["", "## Notes", ""] + [f"- {n}" for n in report["notes"]]
    return "\n".join(lines) + "\n"


def write(report: dict, out: Path, tmp: Path | None) -> None:
    out.mkdir(parents=True, exist_ok=True)
    report["total_s"] = round(now(), 1)
    report["load_average_end"] = load_average()
    (out / "device_suite.json").write_text(json.dumps(report, indent=1, default=str))
    (out / "device_suite.md").write_text(markdown(report))
    if tmp is not None and tmp.is_dir():
        with open(out / "twins.log", "w") as fh:
            for p in sorted(tmp.glob("*.log")):
                fh.write(f"===== {p.stem}\n{p.read_text(errors='replace')[-20000:]}\n")


# --------------------------------------------------------------------------- main

def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", required=True, type=Path, help="folder for the JSON and markdown")
    ap.add_argument("--device", default=None, help="P:D, gpu, cpu or a name substring "
                    "(default: $CLVOL_DEVICE, else the first GPU, else the first CPU)")
    ap.add_argument("--budget-s", type=float, default=140.0,
                    help="no timing starts past this many seconds (default 140)")
    ap.add_argument("--quick", action="store_true", help="tiny sizes (a dry run on a CPU)")
    ap.add_argument("--twins", choices=["tiny", "full", "none"], default="tiny")
    ap.add_argument("--twin-files", nargs="+", default=None, metavar="FILE",
                    help="only these test files (default: every kernel's, see twin_files)")
    ap.add_argument("--jobs", type=int, default=None,
                    help="twin test files run at once (default: cores / 2, at least 1)")
    ap.add_argument("--sizes", type=int, nargs="+", default=None,
                    help="default-method image sides (default 256 512 1024; --quick 32 64)")
    ap.add_argument("--warm", choices=WARM, default=None, help=argparse.SUPPRESS)
    ap.add_argument("--no-warm", action="store_true",
                    help="build every program in this process when first used (no warm-up "
                         "processes)")
    ap.add_argument("--only", nargs="+", default=None, choices=[n for n, _ in TIMINGS],
                    help="run only these timings")
    args = ap.parse_args(argv)

    from clvol.runtime import choose_device, get_runtime
    entry, why = choose_device(args.device or os.environ.get("CLVOL_DEVICE"))
    spec = entry.spec
    os.environ["CLVOL_DEVICE"] = spec            # every get_runtime() here, and the twins
    os.environ.pop("PYOPENCL_CTX", None)
    settings = dataclasses.replace(QUICK if args.quick else FULL)
    if args.sizes:
        settings.sizes = args.sizes
    if args.warm:
        warm(args.warm, {"rt": get_runtime(spec), "settings": settings, "quick": args.quick,
                         "wait_warm": lambda names: True})
        return 0
    report = {"machine": machine(entry), "device_reason": why, "quick": args.quick,
              "budget_s": args.budget_s, "settings": dataclasses.asdict(settings),
              "twins_mode": args.twins, "twins": {}, "timings": {}, "warm_up": {},
              "notes": []}
    d = report["machine"]["device"]
    log(f"device {spec} {entry.label} ({why}): {d['kind']}, {d['compute_units']} CUs, "
        f"{d['global_mem_gib']} GiB, vector width {d['preferred_vector_width_float']}, "
        f"OpenCL C {d['opencl_c_version']}, driver {d['driver_version']}")
    log(f"host {report['machine']['cpu']}, {os.cpu_count()} cores, load "
        f"{report['machine']['load_average_start']}; settings "
        f"{'quick' if args.quick else 'full'}; budget {args.budget_s:.0f} s")

    tmp = Path(tempfile.mkdtemp(prefix="clvol_suite_"))
    lock = threading.Lock()

    def dump_and_exit():
        with lock:
            report["notes"].append(f"watchdog: still running {args.budget_s + 25:.0f} s in; "
                                   "wrote what was measured and exited")
            try:
                if twins is not None:
                    for f, p in list(twins.procs.items()):
                        if p.poll() is None:
                            Twins._kill(p)
                            report["twins"].setdefault(f, {"status": "stopped by the watchdog"})
                    report["twins"].update(twins.results)
                for p, _ in warmers.values():
                    if p.poll() is None:
                        Twins._kill(p)
                write(report, args.out, tmp)
            finally:
                os._exit(3)

    watchdog = threading.Timer(args.budget_s + 25, dump_and_exit)
    watchdog.daemon = True
    watchdog.start()

    twins, warmers = None, {}
    if args.twins != "none":
        jobs = args.jobs or max(1, (os.cpu_count() or 2) // 2)
        twins = Twins(spec, args.twins, jobs, tmp, deadline=args.budget_s,
                      files=args.twin_files)
        log(f"twins: {len(twins.files)} files ({args.twins}), {jobs} at a time")
        twins.start()

    todo = [(n, f) for n, f in TIMINGS if not args.only or n in args.only]
    names = {n for n, _ in todo}
    if not args.no_warm:
        want = [w for w, needs in (("pt-render", "path tracer"), ("pt-query", "path tracer"),
                                   ("network", "fused gather+MLP")) if needs in names]
        for w in want:
            cmd = [sys.executable, str(Path(__file__).resolve()), "--warm", w, "--out",
                   str(tmp / "warm"), "--device", spec] + (["--quick"] if args.quick else [])
            warmers[w] = (subprocess.Popen(cmd, cwd=ROOT, stdout=subprocess.DEVNULL,
                                           stderr=open(tmp / f"warm-{w}.err", "w"),
                                           start_new_session=True), now())
        if warmers:
            log(f"warm-up processes building programs: {', '.join(warmers)}")

    def wait_warm(which) -> bool:
        """Wait for the warm-up processes ``which``; False if the budget ran out first."""
        for w in which:
            if w not in warmers:
                continue
            p, t0 = warmers[w]
            try:
                p.wait(timeout=max(0.1, args.budget_s - now()))
            except subprocess.TimeoutExpired:
                Twins._kill(p)
                report["warm_up"][w] = "still building at the budget"
                return False
            if w not in report["warm_up"]:
                err = (tmp / f"warm-{w}.err").read_text(errors="replace").strip()
                report["warm_up"][w] = (f"exit {p.returncode} after {now() - t0:.1f} s"
                                        + (f": {err.splitlines()[-1][:300]}" if err and
                                           p.returncode else ""))
                log(f"warm-up {w}: {report['warm_up'][w]}")
        return True

    rt = get_runtime(spec)
    ctx = {"wait_warm": wait_warm, "rt": rt, "settings": settings, "quick": args.quick,
           "over": lambda: now() > args.budget_s,
           "budget_left": lambda: args.budget_s - now(),
           "overlap": lambda: bool(twins is not None and twins.running())}

    failed = False
    for name, fn in todo:
        if ctx["over"]():
            report["timings"][name] = {"skipped": f"budget of {args.budget_s:.0f} s spent"}
            log(f"{name}: skipped (budget)")
            continue
        log(f"{name} ...")
        t0 = now()
        try:
            rows = fn(ctx)
            report["timings"][name] = rows
        except Exception as exc:  # noqa: BLE001 - one failing path must not stop the others
            failed = True
            first = f"{type(exc).__name__}: {exc}".splitlines()[0][:500]
            report["timings"][name] = {"error": first,
                                       "traceback": traceback.format_exc()[-3000:]}
            log(f"{name}: ERROR {first}")
        log(f"{name}: {now() - t0:.1f} s")
        with lock:
            write(report, args.out, None)   # partial results survive a hard stop

    if twins is not None:
        while twins.running() and not ctx["over"]():
            time.sleep(0.5)
        if twins.running():
            log("budget spent: stopping the twin files still running")
        twins.stop()
        report["twins"] = {f: twins.results.get(f, {"status": "not finished (budget)"})
                           for f in twins.files}
        for f, r in report["twins"].items():
            ok = r.get("status") in ("passed", "no tests selected")
            failed |= not ok
            log(f"twins {f}: {r.get('status')} ({r.get('passed', 0)} passed, "
                f"{r.get('failed', 0)} failed, {r.get('error', 0)} errors, "
                f"{r.get('seconds', '-')} s)")
            for t in r.get("tests", []):
                if t["status"] in ("failed", "error"):
                    log(f"    {t['status']}: {t['name']}: {t['message'][:200]}")
    for w, (p, _) in warmers.items():
        if p.poll() is None:
            Twins._kill(p)
            report["warm_up"].setdefault(w, "stopped at the end")
    if any(isinstance(v, dict) and "skipped" in v for v in report["timings"].values()):
        report["notes"].append("some timings were skipped: the budget was spent")
    with lock:
        watchdog.cancel()
        write(report, args.out, tmp)
    shutil.rmtree(tmp, ignore_errors=True)
    print(markdown(report))
    log(f"wrote {args.out}/device_suite.json, device_suite.md, twins.log")
    return 1 if failed else 0


if __name__ == "__main__":
    rc = main()
    sys.stdout.flush()
    os._exit(rc)   # background build threads (daemon) must not hold the exit
