"""Training data for the network: procedural volumes, random configurations, path-traced labels.

    spec = DatasetSpec(seed=0, n_volumes=10, configs_per_volume=12)
    make_dataset(spec, "runs/data")          # resumable: finished shards are skipped
    shards = load_shards("runs/data")        # list of Shard (arrays + meta)

A data set is a folder of shards, one per (volume v, configuration c), named
``shard_{v:03d}_{c:03d}.npz``, plus ``spec.json`` (the ``DatasetSpec`` that made it). A shard
holds, for ``points_per_config`` query points of one volume under one configuration (sun
direction, camera position, phase, albedo, density scale):

    points   float32 [n][3]        world positions (density-weighted inside the medium + uniform)
    omegas   float32 [n][3]        unit, toward the configuration's camera (as the renderer's lattice)
    features float32 [n][3][P]     train-mode gather (clvol/layout.py; features[:, 1] is 0: the
    levels   float32 [n][L][P]     model combines ``levels`` itself)
    config   float32 [n][9]        the gather's config (albedo of channel 0; training sets each channel's)
    Fms, Fms_se, F1  float64 [n][3]  labels from clvol.pathtrace.point_query (unit sun, orders >= 2)
    __meta__ uint8                 UTF-8 JSON: spec, shard indices, volume, medium, light, camera,
                                   query seed, code contract (layout version, template hash)

The file is a pure function of (spec, v, c) and the device: fixed zip timestamps, and the
wall-clock timings go to ``timings.jsonl`` in the folder instead (one JSON line per shard).

Robust to a session ending at any moment: a shard is written to a temporary file
(``.shard_*.tmp``, clvol/atomic.py) and renamed into place (``os.replace`` is atomic on one file
system), so a ``shard_*.npz`` is always complete; the loader reads only ``shard_*.npz``, and a
rerun deletes stale temporary files and skips finished shards (one writer per folder at a time). Everything random
is keyed by (spec.seed, v, c): the same spec gives the same shards bit for bit on the same
device, in any order and after any interruption, serially or on Ray (clvol/distributed.py:
workers return the bytes, this process writes them).
"""
from __future__ import annotations

import io
import json
import math
import time
from dataclasses import asdict, dataclass, fields
from pathlib import Path

import numpy as np

from . import layout
from .atomic import atomic_open
from .errors import ClvolError

DATASET_FORMAT = "clvol-dataset"
DATASET_VERSION = 1
SPEC_FILE = "spec.json"
META_KEY = "__meta__"
ARRAYS = ("points", "omegas", "features", "levels", "config", "Fms", "Fms_se", "F1")

# Phase choices for clouds: the MRPNN test protocol's g values plus a uniform draw.
CLOUD_G = (0.857, 0.5, 0.0)
# Albedos of the MRPNN protocol ((1,1,1) taken as the cloud preset's 0.999) plus grey draws.
PROTOCOL_ALBEDOS = ((0.999, 0.999, 0.999), (0.96, 0.98, 1.0), (0.8, 0.9, 1.0))


class DatasetError(ClvolError):
    """A data set folder that does not match the requested spec, or a damaged shard."""


@dataclass(frozen=True)
class DatasetSpec:
    """Everything that determines a data set. Volumes 0..n_volumes-n_solids-1 are clouds
    (generator "cloud", random shape parameters), the last ``n_solids`` are solids (blob or
    sphere, 1-3 HG lobes, chromatic albedo)."""
    seed: int = 0
    n_volumes: int = 12
    n_solids: int = 2
    resolution: int = 48             # voxels per side of the generated volumes
    base_resolution: int = 64        # pyramid base of the gather (goes into the weight contract)
    lam: float = layout.DEFAULT_LAMBDA
    configs_per_volume: int = 14
    points_per_config: int = 256
    uniform_fraction: float = 0.2    # of the points drawn uniformly in the box (rest by density)
    n_paths: int = 384               # paths per point query (label standard error ~1/sqrt)
    cloud_density_scale: tuple = (16.0, 96.0)   # log-uniform; unit box, density peak ~1
    solid_density_scale: tuple = (20.0, 200.0)

    def __post_init__(self):
        def bad(name, value, allowed):
            return DatasetError(f"dataset spec [{name}] = {value!r}: {allowed}")
        for name in ("n_volumes", "resolution", "configs_per_volume", "points_per_config", "n_paths"):
            v = getattr(self, name)
            if not (isinstance(v, int) and v >= 1):
                raise bad(name, v, "must be an integer >= 1")
        if not (isinstance(self.n_solids, int) and 0 <= self.n_solids <= self.n_volumes):
            raise bad("n_solids", self.n_solids, f"must be an integer in [0, n_volumes={self.n_volumes}]")
        b = self.base_resolution
        if not (isinstance(b, int) and 2 <= b <= 512 and b & (b - 1) == 0):
            raise bad("base_resolution", b, "must be a power of two from 2 to 512")
        if not 0.0 <= self.uniform_fraction <= 1.0:
            raise bad("uniform_fraction", self.uniform_fraction, "must be in [0, 1]")
        if not 0.0 < self.lam <= 1.0:
            raise bad("lam", self.lam, "must be in (0, 1]")
        for name in ("cloud_density_scale", "solid_density_scale"):
            lo, hi = getattr(self, name)
            if not (0 < lo <= hi and math.isfinite(hi)):
                raise bad(name, (lo, hi), "must be (low, high) with 0 < low <= high")

    def to_dict(self) -> dict:
        d = asdict(self)
        d.update(cloud_density_scale=list(self.cloud_density_scale),
                 solid_density_scale=list(self.solid_density_scale))
        return d

    @classmethod
    def from_dict(cls, d: dict) -> "DatasetSpec":
        names = {f.name for f in fields(cls)}
        unknown = sorted(set(d) - names)
        if unknown:
            raise DatasetError(f"dataset spec: unknown field(s) {unknown}; allowed: {sorted(names)}")
        d = dict(d)
        for k in ("cloud_density_scale", "solid_density_scale"):
            if k in d:
                d[k] = tuple(d[k])
        return cls(**d)

    @property
    def n_shards(self) -> int:
        return self.n_volumes * self.configs_per_volume

    def is_solid(self, v: int) -> bool:
        return v >= self.n_volumes - self.n_solids


def shard_name(v: int, c: int) -> str:
    return f"shard_{v:03d}_{c:03d}.npz"


def _rng(spec: DatasetSpec, *key) -> np.random.Generator:
    # One independent stream per (seed, purpose, indices): shards never share random numbers and
    # do not depend on the order they are made in.
    return np.random.default_rng([spec.seed, *key])


def _unit(rng) -> np.ndarray:
    v = rng.normal(size=3)
    return v / np.linalg.norm(v)


def volume_params(spec: DatasetSpec, v: int) -> dict:
    """The generator call for volume v: {"generator", "seed", "params"}."""
    rng = _rng(spec, 1, v)
    gseed = int(rng.integers(0, 2**31 - 1))
    if not spec.is_solid(v):
        return {"generator": "cloud", "seed": gseed, "params": {
            "coverage": round(float(rng.uniform(0.35, 0.75)), 4),
            "scale": round(float(rng.uniform(0.15, 0.4)), 4),
            "worley": round(float(rng.uniform(0.3, 0.8)), 4),
            "detail": round(float(rng.uniform(0.1, 0.5)), 4)}}
    if rng.uniform() < 0.5:
        return {"generator": "blob", "seed": gseed, "params": {
            "count": int(rng.integers(3, 9)), "radius": round(float(rng.uniform(0.1, 0.16)), 4)}}
    return {"generator": "sphere", "seed": gseed, "params": {
        "radius": round(float(rng.uniform(0.25, 0.42)), 4)}}


def make_volume(spec: DatasetSpec, v: int):
    from .volume.generators import generate
    p = volume_params(spec, v)
    return generate(p["generator"], seed=p["seed"], resolution=spec.resolution, **p["params"])


def _q(g: float) -> float:
    return round(float(g) * 10) / 10


def config_params(spec: DatasetSpec, v: int, c: int) -> dict:
    """Configuration c of volume v: light and camera directions, phase lobes, albedo, density
    scale (JSON-ready)."""
    rng = _rng(spec, 2, v, c)
    light = _unit(rng)
    cam_dir = _unit(rng)
    cam_dist = float(rng.uniform(1.8, 3.0))
    if spec.is_solid(v):
        n_lobes = int(rng.integers(1, 4))
        # g on a 0.1 lattice: the gather's volume-phase tables cost ~1.5 s per distinct |g|
        # and are cached per process, so a few distinct values keep shards cheap
        gs = [_q(rng.uniform(0.3, 0.9))] + [_q(rng.uniform(-0.5, 0.5)) for _ in range(n_lobes - 1)]
        ws = rng.dirichlet(np.full(n_lobes, 2.0)) if n_lobes > 1 else np.ones(1)
        lobes = [(g, float(w)) for g, w in zip(gs, ws)]
        s = sum(w for _, w in lobes)
        lobes = [(g, w / s) for g, w in lobes]
        albedo = tuple(round(float(a), 4) for a in rng.uniform(0.8, 0.999, 3))
        lo, hi = spec.solid_density_scale
    else:
        k = int(rng.integers(0, len(CLOUD_G) + 1))
        g = CLOUD_G[k] if k < len(CLOUD_G) else _q(rng.uniform(0.0, 0.9))
        lobes = [(g, 1.0)]
        k = int(rng.integers(0, len(PROTOCOL_ALBEDOS) + 1))
        if k < len(PROTOCOL_ALBEDOS):
            albedo = PROTOCOL_ALBEDOS[k]
        else:
            a = round(float(rng.uniform(0.8, 0.999)), 4)
            albedo = (a, a, a)
        lo, hi = spec.cloud_density_scale
    scale = float(np.exp(rng.uniform(np.log(lo), np.log(hi))))
    return {"light": light.tolist(), "camera_dir": cam_dir.tolist(), "camera_distance": cam_dist,
            "lobes": [list(x) for x in lobes], "albedo": list(albedo),
            "density_scale": round(scale, 4)}


def scene_for(spec: DatasetSpec, v: int, c: int):
    """The clvol Scene of shard (v, c) (its camera is only a placeholder: labels need the
    sun and the medium)."""
    from .scene import scene_from_dict
    vp, cp = volume_params(spec, v), config_params(spec, v, c)
    lobes = cp["lobes"]
    phase = ({"type": "hg", "g": lobes[0][0]} if len(lobes) == 1 else
             {"type": "mhg", "lobes": [{"g": g, "weight": w} for g, w in lobes]})
    origin = (np.asarray(cp["camera_dir"]) * cp["camera_distance"]).tolist()
    return scene_from_dict({
        "volume": {"generator": vp["generator"], "seed": vp["seed"], "resolution": spec.resolution,
                   **({"params": vp["params"]} if vp["params"] else {})},
        "medium": {"density_scale": cp["density_scale"], "albedo": list(cp["albedo"]), "phase": phase},
        "light": {"direction": cp["light"], "irradiance": [1.0, 1.0, 1.0]},
        "camera": {"origin": origin, "target": [0.0, 0.0, 0.0], "up": _up_for(origin),
                   "fov_y": 30.0, "width": 8, "height": 8},
    }, f"<dataset shard {v},{c}>")


def _up_for(origin) -> list:
    o = np.asarray(origin, np.float64)
    return [0.0, 1.0, 0.0] if abs(o[1]) < 0.99 * np.linalg.norm(o) else [1.0, 0.0, 0.0]


def sample_points(spec: DatasetSpec, grid, v: int, c: int) -> np.ndarray:
    """points_per_config world points: density-weighted voxel picks jittered within the voxel,
    plus a ``uniform_fraction`` drawn uniformly in the box (empty space near the medium is on
    the renderer's lattice too)."""
    rng = _rng(spec, 3, v, c)
    n = spec.points_per_config
    n_uni = int(round(spec.uniform_fraction * n))
    dens = grid.density.astype(np.float64).ravel()
    lo, hi = np.asarray(grid.bbox_min, np.float64), np.asarray(grid.bbox_max, np.float64)
    total = dens.sum()
    if total <= 0:           # an empty volume: all uniform
        n_uni = n
    idx = rng.choice(dens.size, n - n_uni, p=dens / total) if n > n_uni else np.zeros(0, int)
    nz, ny, nx = grid.density.shape
    zyx = np.stack(np.unravel_index(idx, (nz, ny, nx)), axis=1)
    inside = lo + (zyx[:, ::-1] + rng.uniform(0, 1, (len(idx), 3))) * np.asarray(grid.cell_size)
    uni = lo + rng.uniform(0, 1, (n_uni, 3)) * (hi - lo)
    return np.concatenate([inside, uni]).astype(np.float32)


def _code_contract(spec: DatasetSpec) -> dict:
    from .templates import load_templates
    return {"layout_version": layout.LAYOUT_VERSION, "template_hash": load_templates().sha256,
            "base_resolution": spec.base_resolution, "lambda": spec.lam,
            "n_levels": layout.n_levels(spec.base_resolution)}


def make_shard(spec: DatasetSpec, v: int, c: int, grid=None, pyramid=None, runtime=None) -> dict:
    """Arrays and meta of shard (v, c) (nothing written). ``grid``/``pyramid``: volume v's, if
    the caller already has them (they are a pure function of (spec, v))."""
    from .kernels.gather import gather
    from .kernels.pyramid import build_pyramid
    from .kernels.transmittance import graded_transmittance
    from .pathtrace import point_query
    t0 = time.perf_counter()
    scene = scene_for(spec, v, c)
    grid = grid if grid is not None else make_volume(spec, v)
    pyramid = pyramid if pyramid is not None else build_pyramid(grid, spec.base_resolution, runtime)
    pts = sample_points(spec, grid, v, c)
    om = np.asarray(scene.camera.origin, np.float64) - pts
    om /= np.linalg.norm(om, axis=1, keepdims=True)
    qseed = int(_rng(spec, 4, v, c).integers(0, 2**31 - 1))
    lab = point_query(scene, pts, om, spec.n_paths, seed=qseed, grid=grid, runtime=runtime)
    t_labels = time.perf_counter() - t0
    l = np.asarray(scene.light.direction, np.float64)
    graded = graded_transmittance(pyramid, scene.medium.density_scale, l, lam=spec.lam)
    g = gather(pyramid, graded, pts, om, l, scene.medium, scene.medium.albedo[0], mode="train")
    arrays = {"points": pts, "omegas": om.astype(np.float32), "features": g["features"],
              "levels": g["levels"], "config": g["config"], "Fms": lab["Fms"],
              "Fms_se": lab["Fms_se"], "F1": lab["F1"]}
    for k, a in arrays.items():
        if not np.all(np.isfinite(a)):
            raise DatasetError(f"shard ({v}, {c}): non-finite values in {k}")
    meta = {"format": DATASET_FORMAT, "format_version": DATASET_VERSION, "spec": spec.to_dict(),
            "volume_index": v, "config_index": c, "volume": volume_params(spec, v),
            "config": config_params(spec, v, c), "camera_origin": list(scene.camera.origin),
            "query_seed": qseed, "paths_truncated": int(lab["truncated"]),
            "contract": _code_contract(spec),
            "seconds": {"labels": round(t_labels, 3), "total": round(time.perf_counter() - t0, 3)},
            "label_median_rel_se": float(np.median(lab["Fms_se"][:, 0] /
                                                   np.maximum(lab["Fms"][:, 0], 1e-30)))}
    return {"arrays": arrays, "meta": meta}


# A fixed zip timestamp (the earliest zip can hold): np.savez stamps each member with the
# current time, so two runs would differ in a few header bytes.
_ZIP_EPOCH = (1980, 1, 1, 0, 0, 0)


def shard_bytes(arrays: dict, meta: dict) -> bytes:
    """The .npz file of a shard as bytes (what a remote worker sends back to the driver).

    A pure function of the arrays and meta: zip members in a fixed order with a fixed
    timestamp, and the meta's wall-clock ``seconds`` left out (they go to the folder's
    ``timings.jsonl``), so the same spec gives the same bytes serially, on Ray, or resumed.
    np.load reads it like any np.savez file."""
    import zipfile
    meta = {k: v for k, v in meta.items() if k != "seconds"}
    members = {META_KEY: np.frombuffer(json.dumps(meta, sort_keys=True).encode("utf-8"), np.uint8),
               **arrays}
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", zipfile.ZIP_STORED) as zf:
        for key, a in members.items():
            info = zipfile.ZipInfo(key + ".npy", date_time=_ZIP_EPOCH)
            with zf.open(info, "w", force_zip64=True) as f:
                np.lib.format.write_array(f, np.asanyarray(a), allow_pickle=False)
    return buf.getvalue()


def _write_json_atomic(path: Path, obj) -> None:
    with atomic_open(path, "w") as f:
        json.dump(obj, f, indent=1, sort_keys=True)


def check_spec_file(out_dir: Path, spec: DatasetSpec) -> None:
    """Create spec.json, or refuse a folder made with another spec (mixing would be silent)."""
    path = out_dir / SPEC_FILE
    want = {"format": DATASET_FORMAT, "format_version": DATASET_VERSION, "spec": spec.to_dict()}
    if path.exists():
        try:
            have = json.loads(path.read_text())
        except ValueError as exc:
            raise DatasetError(f"{path}: not valid JSON ({exc})") from None
        if have != want:
            diff = [k for k in set(have.get("spec", {})) | set(want["spec"])
                    if have.get("spec", {}).get(k) != want["spec"].get(k)]
            raise DatasetError(f"{path}: the folder holds a data set of another spec (fields "
                               f"{sorted(diff) or ['format']} differ); use another folder or the same spec")
    else:
        _write_json_atomic(path, want)


def pending_shards(spec: DatasetSpec, out_dir) -> list[tuple[int, int]]:
    """Prepare ``out_dir`` for a (resumed) run and list the shards still to make: checks or
    creates spec.json, removes temporary files of a run killed mid-write, skips finished
    shards."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    check_spec_file(out, spec)
    for stale in out.glob(".shard_*.tmp"):     # a previous run killed mid-write
        stale.unlink()
    return [(v, c) for v in range(spec.n_volumes) for c in range(spec.configs_per_volume)
            if not (out / shard_name(v, c)).exists()]


class ShardMaker:
    """Makes shards one after another in one process, keeping the last volume's grid and
    pyramid (they depend on (spec, v) only). Used by the serial loop and by each Ray worker."""

    def __init__(self, runtime=None):
        self.runtime = runtime
        self._volume = (None, None, None)

    def __call__(self, spec: DatasetSpec, v: int, c: int) -> tuple[bytes, dict]:
        """(the shard file's bytes, its meta including the timings the file leaves out)."""
        from .kernels.pyramid import build_pyramid
        key = (json.dumps(spec.to_dict(), sort_keys=True), v)
        if self._volume[0] != key:
            grid = make_volume(spec, v)
            self._volume = (key, grid, build_pyramid(grid, spec.base_resolution, self.runtime))
        shard = make_shard(spec, v, c, self._volume[1], self._volume[2], self.runtime)
        return shard_bytes(shard["arrays"], shard["meta"]), shard["meta"]


TIMINGS_FILE = "timings.jsonl"


def write_shard(out_dir, v: int, c: int, data: bytes, log: dict | None = None) -> None:
    """The driver's write of one finished shard: the bytes atomically, then one line of
    ``log`` (timings, the node that made it) to timings.jsonl, for labelling-cost
    measurements; the loader never reads it."""
    out = Path(out_dir)
    with atomic_open(out / shard_name(v, c), "wb") as f:
        f.write(data)
    if log:
        with open(out / TIMINGS_FILE, "a") as f:
            f.write(json.dumps({"shard": shard_name(v, c), **log}, sort_keys=True) + "\n")


def shard_progress(n_shards: int, spec: DatasetSpec, progress: bool):
    """The progress bar of a data set run: shards done/total, labels per second, ETA."""
    from .progress import Progress
    return Progress(n_shards, label="dataset", unit=" shards", delay=0.0 if progress else 1e30,
                    rate_per_unit=spec.points_per_config, rate_unit="labels")


def make_dataset(spec: DatasetSpec, out_dir, runtime=None, progress: bool = True,
                 max_shards: int | None = None, on_shard=None) -> dict:
    """Make every missing shard of ``spec`` in ``out_dir``, serially in this process (Ray:
    clvol/distributed.py). Returns {"made", "skipped"} counts. ``max_shards``: stop after
    making this many (tests); ``on_shard(v, c)`` is called after each shard is written."""
    out = Path(out_dir)
    todo = pending_shards(spec, out)
    made = 0
    maker = ShardMaker(runtime)
    with shard_progress(len(todo), spec, progress) as bar:
        for v, c in todo:
            if max_shards is not None and made >= max_shards:
                break
            data, meta = maker(spec, v, c)
            write_shard(out, v, c, data, meta.get("seconds"))
            made += 1
            bar.update(1)
            if on_shard is not None:
                on_shard(v, c)
    return {"made": made, "skipped": spec.n_shards - len(todo)}


@dataclass
class Shard:
    path: Path
    arrays: dict
    meta: dict

    @property
    def volume(self) -> int:
        return int(self.meta["volume_index"])

    @property
    def config_index(self) -> int:
        return int(self.meta["config_index"])

    @property
    def albedo(self) -> tuple:
        return tuple(self.meta["config"]["albedo"])


def read_shard(path) -> Shard:
    path = Path(path)
    try:
        with np.load(path, allow_pickle=False) as z:
            meta = json.loads(z[META_KEY].tobytes().decode("utf-8"))
            missing = [k for k in ARRAYS if k not in z.files]
            if missing:
                raise DatasetError(f"{path}: shard lacks array(s) {missing}")
            arrays = {k: z[k] for k in ARRAYS}
    except DatasetError:
        raise
    except Exception as exc:
        raise DatasetError(f"{path}: cannot read shard ({type(exc).__name__}: {exc})") from None
    if meta.get("format") != DATASET_FORMAT or meta.get("format_version") != DATASET_VERSION:
        raise DatasetError(f"{path}: [format] {meta.get('format')!r} version "
                           f"{meta.get('format_version')!r}; expected {DATASET_FORMAT!r} {DATASET_VERSION}")
    return Shard(path, arrays, meta)


def load_shards(data_dir) -> list[Shard]:
    """Every finished shard of a data set folder (``shard_*.npz`` only; temporary files of an
    interrupted run are never read), in name order, all made with one spec and one contract."""
    d = Path(data_dir)
    if not (d / SPEC_FILE).exists():
        raise DatasetError(f"{d}: no {SPEC_FILE}; not a clvol data set folder")
    shards = [read_shard(p) for p in sorted(d.glob("shard_*.npz"))]
    if not shards:
        raise DatasetError(f"{d}: no finished shards")
    c0 = shards[0].meta["contract"]
    for s in shards[1:]:
        if s.meta["contract"] != c0:
            raise DatasetError(f"{s.path}: [contract] {s.meta['contract']} differs from "
                               f"{shards[0].path}'s {c0}")
    return shards
