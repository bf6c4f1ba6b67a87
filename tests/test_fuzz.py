"""Fuzzing with hypothesis: the scene parser, the volume readers and the viewer's messages
get structured and mutated input. Every input must end either in a valid result or in a
ClvolError whose message is one line (what `clvol` prints with exit 2); any other exception,
a NaN in an accepted volume or a multi-line message is a bug.

The budget is seeded (``derandomize``: the same examples every run, so a failure reproduces)
and small enough for CI: 600 examples per test, ~20 s for the file on the 2-core machine, plus 100
renders of fuzzed ``Renderer.render`` arguments (~20 s). A long run:
``CLVOL_FUZZ_EXAMPLES=20000 CLVOL_FUZZ_API_EXAMPLES=5000 python -m pytest tests/test_fuzz.py``
(docs/testing.md).
"""
from __future__ import annotations

import os
import struct

import numpy as np
import pytest

hypothesis = pytest.importorskip("hypothesis")
from hypothesis import HealthCheck, event, given, settings  # noqa: E402
from hypothesis import strategies as st  # noqa: E402

from clvol.errors import ClvolError  # noqa: E402

EXAMPLES = int(os.environ.get("CLVOL_FUZZ_EXAMPLES", "600"))
FUZZ = settings(max_examples=EXAMPLES, derandomize=True, deadline=None,
                suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture])


def _one_line(exc: ClvolError) -> None:
    msg = str(exc)
    assert msg and "\n" not in msg.strip(), f"multi-line error: {msg!r}"


# ----------------------------------------------------------------- scene parser

SCALARS = st.one_of(st.none(), st.booleans(), st.integers(-10**12, 10**12),
                    st.floats(allow_nan=True, allow_infinity=True), st.text(max_size=12))
VALUES = st.recursive(SCALARS, lambda inner: st.one_of(st.lists(inner, max_size=4),
                                                       st.dictionaries(st.text(max_size=8), inner,
                                                                       max_size=3)),
                      max_leaves=8)
VALID = {
    "volume": {"generator": st.sampled_from(["cloud", "sphere", "smoke", "nope", ""]),
               "resolution": st.one_of(st.integers(-4, 24), VALUES), "seed": VALUES,
               "params": VALUES},
    "medium": {"preset": st.sampled_from(["cloud", "jade", "milk", "x"]),
               "density_scale": st.one_of(st.floats(-10, 100), VALUES),
               "albedo": st.one_of(st.lists(st.floats(-1, 2), min_size=0, max_size=4), VALUES),
               "phase": st.one_of(st.fixed_dictionaries({"type": st.just("hg"),
                                                         "g": st.floats(-2, 2)}), VALUES)},
    "light": {"direction": st.one_of(st.lists(st.floats(-2, 2), max_size=4), VALUES),
              "irradiance": VALUES, "environment": VALUES},
    "camera": {"origin": st.lists(st.floats(-5, 5), max_size=4), "target": VALUES,
               "fov_y": st.one_of(st.floats(-10, 200), VALUES),
               "width": st.one_of(st.integers(-2, 16), VALUES), "height": VALUES, "up": VALUES},
}


@st.composite
def scene_dicts(draw):
    out = {}
    for table, fields in VALID.items():
        if draw(st.booleans()) or table == "volume":
            keys = draw(st.lists(st.sampled_from(sorted(fields)), unique=True, max_size=len(fields)))
            out[table] = {k: draw(fields[k]) for k in keys}
            if draw(st.integers(0, 9)) == 0:
                out[table][draw(st.text(max_size=6))] = draw(VALUES)   # an unknown key
    if draw(st.integers(0, 9)) == 0:
        out[draw(st.text(max_size=6))] = draw(VALUES)                 # an unknown table
    return out


@FUZZ
@given(scene_dicts())
def test_scene_dicts_parse_or_fail_in_one_line(data):
    from clvol.scene import scene_from_dict
    try:
        scene_from_dict(data, "<fuzz>")
    except ClvolError as exc:
        _one_line(exc)


@FUZZ
@given(st.text(max_size=300))
def test_scene_text_parses_or_fails_in_one_line(tmp_path_factory, text):
    from clvol.scene import load_scene
    path = tmp_path_factory.mktemp("toml") / "s.toml"
    path.write_text(text, encoding="utf-8")
    try:
        load_scene(path)
    except ClvolError as exc:
        _one_line(exc)


# --set items: a known field (so the value reaches its check) or any text, = any text or a
# TOML-looking value
_SET_KEYS = st.one_of(st.sampled_from(["medium.density_scale", "medium.albedo", "medium.phase",
                                       "medium.preset", "light.direction", "light.irradiance",
                                       "camera.fov_y", "camera.width", "volume.generator"]),
                      st.text(max_size=20))
_TOML_NUMBERS = st.one_of(st.integers(-10**6, 10**6).map(str),
                          st.floats(allow_nan=True, allow_infinity=True).map(
                              lambda x: "nan" if x != x else ("inf" if x > 0 else "-inf")
                              if abs(x) == float("inf") else repr(x)))
_SET_VALUES = st.one_of(
    _TOML_NUMBERS, st.lists(_TOML_NUMBERS, max_size=4).map(lambda v: "[" + ", ".join(v) + "]"),
    st.sampled_from(["{ type = \"hg\", g = 2 }", "{ type = \"hg\", g = 0.5 }", "\"milk\"",
                     "\"cloud\"", "true", "[[]]", "{}", "\"\""]),
    st.text(max_size=30))


@FUZZ
@given(st.lists(st.one_of(st.builds(lambda k, v: f"{k}={v}", _SET_KEYS, _SET_VALUES),
                          st.text(max_size=40)), max_size=3))
def test_set_items_apply_or_fail_in_one_line(items):
    """The command line's --set reader (scenefile.py load_scene_overridden) on any items."""
    from pathlib import Path
    from clvol.scene import load_scene_overridden
    try:
        load_scene_overridden(Path(__file__).parents[1] / "examples" / "cloud.toml", items)
        event("applied")
    except ClvolError as exc:
        _one_line(exc)
        event("refused: " + str(exc).split(": ")[1 if "(with" in str(exc) else 0][:20])


# ----------------------------------------------------------------- volume readers

def _real_files(folder):
    from clvol.volume.grid import DensityGrid
    from clvol.volume.io import write_volume
    rng = np.random.default_rng(0)
    d = (rng.random((5, 4, 6)) * (rng.random((5, 4, 6)) > 0.3)).astype(np.float32)
    g = DensityGrid(d, np.array([-0.6, -0.4, -0.5]), np.array([0.6, 0.4, 0.5]))    # cubic voxels (.vdb)
    out = {}
    for ext in (".vol", ".npz", ".npy"):
        p = folder / f"v{ext}"
        # .npy stores no box: write it with the default one
        write_volume(p, g if ext != ".npy" else DensityGrid(d, np.full(3, -0.5), np.full(3, 0.5)))
        out[ext] = p.read_bytes()
    from clvol.volume.vdb import write_vdb
    write_vdb(folder / "v.vdb", g)
    out[".vdb"] = (folder / "v.vdb").read_bytes()
    return out


_REAL = {}


def real_volume_bytes(tmp_path_factory):
    """The real files' bytes, made once (kept out of hypothesis' arguments, so that a
    falsifying example prints the mutation, not the file)."""
    if not _REAL:
        _REAL.update(_real_files(tmp_path_factory.mktemp("vols")))
    return _REAL


MUTATIONS = st.lists(st.tuples(st.sampled_from(["flip", "cut", "insert", "word"]),
                               st.floats(0, 1), st.integers(0, 2**32 - 1)), min_size=1, max_size=4)


def _mutate(data: bytes, ops) -> bytes:
    b = bytearray(data)
    for op, where, value in ops:
        i = min(int(where * len(b)), max(len(b) - 1, 0))
        if op == "flip" and b:
            b[i] ^= 1 << (value % 8)
        elif op == "cut":
            del b[i:]
        elif op == "insert":
            b[i:i] = bytes([value % 256]) * (1 + value % 7)
        elif op == "word" and len(b) >= i + 4:
            b[i:i + 4] = struct.pack("<I", value)          # sizes, counts, offsets
    return bytes(b)


@pytest.mark.parametrize("ext", [".vol", ".npz", ".npy", ".vdb"])
@FUZZ
@given(ops=MUTATIONS)
def test_mutated_volume_files_read_or_fail_in_one_line(tmp_path_factory, ext, ops):
    from clvol.volume.io import read_volume
    real = real_volume_bytes(tmp_path_factory)
    assert ext in real
    path = tmp_path_factory.mktemp("mut") / f"m{ext}"
    path.write_bytes(_mutate(real[ext], ops))
    try:
        g = read_volume(path, max_bytes=1 << 26) if ext == ".vdb" else read_volume(path)
    except ClvolError as exc:
        _one_line(exc)
        return
    d = np.asarray(g.density)
    assert d.ndim == 3 and np.isfinite(d).all() and (d >= 0).all()


# ----------------------------------------------------------------- viewer messages

@pytest.fixture(scope="module")
def view_state():
    from clvol.scene import load_scene
    from clvol.viewer.state import ViewState
    from pathlib import Path
    root = Path(__file__).resolve().parents[1]
    return ViewState.from_scene(load_scene(root / "tests" / "data" / "scenes" / "cloud.toml"))


FIELDS = ["azimuth", "elevation", "distance", "sun_azimuth", "sun_elevation", "albedo", "g",
          "density_scale", "resolution", "preset", "method", "exposure", "sky", "nope"]


# besides arbitrary values, the strings the viewer gives meaning to (exposure "scene")
VIEWER_VALUES = st.one_of(VALUES, st.sampled_from(["scene", "image", "network", "stochastic"]))


@FUZZ
@given(st.one_of(VALUES, st.dictionaries(st.sampled_from(FIELDS), VIEWER_VALUES, max_size=5)))
def test_viewer_state_messages_apply_or_fail_in_one_line(view_state, changes):
    from clvol.viewer.state import ViewerMessageError
    try:
        new = view_state.update(changes)
    except ViewerMessageError as exc:
        _one_line(exc)
        return
    for v in new.to_json().values():       # an accepted state holds finite numbers only
        for x in (v if isinstance(v, (list, tuple)) else [v]):
            if isinstance(x, float):
                assert np.isfinite(x)


# ----------------------------------------------------------------- the WebSocket handler

class _FakeSocket:
    """What Connection.handle sends, kept (no network)."""
    closed = False

    def __init__(self):
        self.sent = []

    async def send_str(self, text):
        self.sent.append(text)


@pytest.fixture(scope="module")
def viewer_connection(view_state, tmp_path_factory):
    """A clvol.viewer.server.Connection on a fake socket and a stand-in frame maker (the
    handler reads only its sky-map menu): the handler itself, fuzzed without a server."""
    from types import SimpleNamespace
    from clvol.viewer.server import Connection
    maker = SimpleNamespace(sky_maps={})
    return lambda: Connection(_FakeSocket(), maker, view_state, tmp_path_factory.mktemp("save"))


def _state_message(changes):
    import json
    return json.dumps({"type": "state", "state": changes}, allow_nan=True)


WS_TEXT = st.one_of(
    st.text(max_size=64),                                             # anything at all
    VALUES.map(lambda v: __import__("json").dumps(v, allow_nan=True)),  # any JSON
    st.dictionaries(st.sampled_from(["type", "state", "x"]),
                    st.one_of(st.sampled_from(["state", "save", "nope", ""]), VALUES),
                    max_size=3).map(lambda d: __import__("json").dumps(d, allow_nan=True)),
    st.dictionaries(st.sampled_from(FIELDS), VIEWER_VALUES, max_size=5).map(_state_message),
    st.integers(60, 70).map(lambda k: '{"type": "state", "state": {"nope": "'
                            + "x" * (k * 1024) + '"}}'),              # near the size limit
)


WS_EXAMPLES = int(os.environ.get("CLVOL_FUZZ_WS_EXAMPLES", "200"))


@settings(FUZZ, max_examples=WS_EXAMPLES)
@given(st.lists(WS_TEXT, min_size=1, max_size=4))
def test_viewer_websocket_handler_answers_every_message(viewer_connection, texts):
    """Connection.handle (clvol/viewer/server.py) on what a client could send: never raises;
    every reply is {"type": "error", "message": one line}; a state it keeps holds finite
    numbers; a save before any frame is refused in one line. CI: 200 seeded examples of
    up to 4 messages each (derandomize: the same every run), ~2 s at load ~1;
    CLVOL_FUZZ_WS_EXAMPLES for more."""
    import asyncio
    import json
    conn = viewer_connection()
    for text in texts:
        asyncio.run(conn.handle(text))
    for reply in conn.ws.sent:
        r = json.loads(reply)
        assert r["type"] == "error", r
        assert r["message"] and "\n" not in r["message"].strip(), r
    for v in conn.state.to_json().values():
        for x in (v if isinstance(v, (list, tuple)) else [v]):
            if isinstance(x, float):
                assert np.isfinite(x)


def test_viewer_websocket_handler_cases(viewer_connection):
    """The seeded fuzz's classes, written out: not JSON, no type, an unknown type, an
    oversized message, a save with no frame, then a valid state change (no reply, kept)."""
    import asyncio
    import json
    conn = viewer_connection()
    for text, words in (("{", "not JSON"), ("[]", '"type"'), ('{"type": "x"}', "not one of"),
                        ("x" * (70 * 1024), "at most"), ('{"type": "save"}', "no frame")):
        asyncio.run(conn.handle(text))
        assert words in json.loads(conn.ws.sent[-1])["message"], conn.ws.sent[-1]
    n = len(conn.ws.sent)
    asyncio.run(conn.handle(json.dumps({"type": "state", "state": {"albedo": [0.5, 0.6, 0.7]}})))
    assert len(conn.ws.sent) == n and conn.state.albedo == (0.5, 0.6, 0.7), conn.state.albedo


# ----------------------------------------------------------------- Renderer.render arguments

API_EXAMPLES = int(os.environ.get("CLVOL_FUZZ_API_EXAMPLES", "100"))
API_FUZZ = settings(FUZZ, max_examples=API_EXAMPLES)
FLOATS = st.one_of(st.floats(-4, 4), st.sampled_from([0.0, -0.0, 1e-30, 1e30, -1e30]),
                   st.floats(allow_nan=True, allow_infinity=True))
VEC = st.one_of(st.tuples(FLOATS, FLOATS, FLOATS), st.lists(FLOATS, max_size=4), SCALARS)
SIZES = st.one_of(st.integers(-2, 24), st.sampled_from([16385, 2**31, 10**12]), FLOATS, SCALARS)


def mostly(valid, invalid):
    """``valid`` nine times in ten, else ``invalid``: so that most parts are accepted and
    rendered, with one bad field at a time often enough."""
    return st.integers(0, 9).flatmap(lambda i: valid if i < 9 else invalid)


def _vec(lo, hi):
    return st.tuples(*[st.floats(lo, hi)] * 3)


@st.composite
def render_arguments(draw):
    """Camera, light and medium built in code as an API user would (any field any value),
    or something that is not one at all; None keeps the scene's."""
    from clvol.scene import Camera, Light, Medium, Phase
    phases = mostly(st.one_of(st.sampled_from([Phase.isotropic(), Phase.hg(-0.9),
                                               Phase.mhg([(0.6, 0.8), (-0.2, 0.2)])]),
                              st.builds(Phase.hg, st.floats(-0.99, 0.99))),
                    st.one_of(st.builds(Phase.hg, FLOATS), SCALARS))
    camera = st.builds(Camera, origin=mostly(_vec(-3, 3), VEC),
                       target=mostly(_vec(-0.5, 0.5), VEC), up=mostly(_vec(-1, 1), VEC),
                       fov_y=mostly(st.floats(0.5, 179), FLOATS),
                       width=mostly(st.integers(1, 24), SIZES),
                       height=mostly(st.integers(1, 24), SIZES))
    light = st.builds(Light, direction=mostly(_vec(-1, 1), VEC),
                      irradiance=mostly(_vec(0, 4), VEC),
                      environment=st.one_of(st.none(), mostly(_vec(0, 1), VEC)))
    medium = st.builds(Medium, density_scale=mostly(st.floats(0, 200), FLOATS),
                       albedo=mostly(_vec(0, 1), VEC), phase=phases)
    out = {}
    for name, strat in (("camera", camera), ("light", light), ("medium", medium)):
        choice = draw(st.integers(0, 19))
        if choice < 12:
            out[name] = draw(strat)
        elif choice == 12:
            out[name] = draw(SCALARS)              # not a Camera, Light or Medium at all
    return out


@pytest.fixture(scope="module")
def api_renderers():
    import clvol
    from clvol.scene import scene_from_dict
    scene = scene_from_dict({
        "volume": {"generator": "sphere", "resolution": 8},
        "medium": {"preset": "cloud", "density_scale": 8.0},
        "light": {"direction": [0.3, 1.0, 0.2]},
        "camera": {"origin": [0.0, 0.3, 2.5], "target": [0.0, 0.0, 0.0], "fov_y": 35.0,
                   "width": 12, "height": 10}}, "<fuzz>")
    return [clvol.Renderer(scene, ms="none"), clvol.Renderer(scene, "pathtrace", spp=1)]


@API_FUZZ
@given(render_arguments(), st.integers(0, 1))
def test_render_arguments_render_or_fail_in_one_line(api_renderers, monkeypatch, args, which):
    """Every argument either raises a one-line ClvolError within 5 s or renders a finite image
    of the asked size (within 60 s, a kernel build included): no other exception, no NaN, no
    hang (issue 41: a camera at its target ran until killed). The memory limit is set low (64 MiB) so that an accepted large
    image is refused the same way on any machine."""
    import time
    from clvol.render.memory import LIMIT_ENV
    monkeypatch.setenv(LIMIT_ENV, "64M")
    r = api_renderers[which]
    t0 = time.perf_counter()
    try:
        img = r.render(**args)
    except ClvolError as exc:
        _one_line(exc)
        assert time.perf_counter() - t0 < 5.0
        event("refused: " + str(exc).split(": [")[-1].split("]")[0][:30])
        return
    # a render may build a new kernel variant first (a few seconds on PoCL at load ~8: one
    # first call measured 5.2 s, its replay 0.06 s): the bound is for a hang, not a budget
    assert time.perf_counter() - t0 < 60.0
    event("rendered")
    cam = args.get("camera") or r.scene.camera
    assert img.total.shape == (int(cam.height), int(cam.width), 3)
    for name, layer in img.layers.items():
        assert np.isfinite(layer).all(), name
