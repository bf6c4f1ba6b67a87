"""The browser viewer (``clvol view``): message checks, the orbit frame, the server over a real
WebSocket, Ctrl-C, and the page in headless Chromium (Debian's chromium + chromedriver).

Every server here listens on 127.0.0.1 with port 0 (a free port), never another address.
"""
from __future__ import annotations

import asyncio
import dataclasses
import json
import math
import os
import shutil
import signal
import struct
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from clvol.image import AUTO_WHITE
from clvol.scene import load_scene
from clvol.viewer.state import LIMITS, ViewerMessageError, ViewState, orbit_frame
from scene_toml import write_scene

ROOT = Path(__file__).resolve().parents[1]
SCENE = {"volume": {"generator": "cloud", "seed": 3, "resolution": 32},
         "medium": {"preset": "cloud", "density_scale": 32.0},
         "light": {"direction": [0.6, 0.9, 0.3]},
         "camera": {"origin": [0.0, 0.3, 2.0], "target": [0.0, 0.0, 0.0], "up": [0.0, 1.0, 0.0],
                    "fov_y": 40.0, "width": 64, "height": 64}}


@pytest.fixture(scope="module")
def scene_path(tmp_path_factory):
    """The scene, beside a copy of the shipped sky map (the map menu offers it) and a
    rendered-looking square EXR (which the menu must leave out: not a lat-long map)."""
    from clvol.image import write_exr
    p = tmp_path_factory.mktemp("view") / "small.toml"
    write_scene(p, **SCENE)
    shutil.copy(ROOT / "examples" / "sky_64x32.exr", p.parent / "sky.exr")
    write_exr(p.parent / "render.exr", {"total": np.ones((8, 8, 3), np.float32)})
    return p


# ------------------------------------------------------------------ state and messages

def test_initial_state_reproduces_the_scene_camera_and_light(scene_path):
    scene = load_scene(scene_path)
    s = ViewState.from_scene(scene)
    cam = s.camera(scene.camera)
    assert np.allclose(cam.origin, scene.camera.origin, atol=1e-12)
    light = s.light(scene.light, scene.camera)
    assert np.allclose(light.direction, scene.light.direction, atol=1e-12)
    # The medium is the scene's own until the client changes it.
    assert s.medium(scene.medium) == scene.medium


def test_orbit_keeps_distance_and_turns_about_up(scene_path):
    scene = load_scene(scene_path)
    s = ViewState.from_scene(scene).update({"azimuth": 90.0, "elevation": 0.0, "distance": 3.0})
    o = np.asarray(s.camera(scene.camera).origin)
    assert math.isclose(np.linalg.norm(o), 3.0, rel_tol=1e-12)
    up, x0, y0 = orbit_frame(scene.camera)
    # azimuth 90 deg, elevation 0: along y0, perpendicular to the file camera's direction.
    assert np.allclose(o / 3.0, y0, atol=1e-12) and abs(np.dot(o, up)) < 1e-12


@pytest.mark.parametrize("changes, field", [
    ({"g": 1.5}, "g"), ({"g": "x"}, "g"), ({"g": float("nan")}, "g"),
    ({"albedo": [1, 1]}, "albedo"), ({"albedo": [0.5, 2.0, 0.5]}, "albedo"),
    ({"density_scale": 0.0}, "density_scale"), ({"elevation": 90.0}, "elevation"),
    ({"method": "magic"}, "method"), ({"resolution": 100}, "resolution"),
    ({"resolution": True}, "resolution"), ({"preset": "lava"}, "preset"), ({"zoom": 1}, "zoom"),
    ({"exposure": float("inf")}, "exposure"), ({"exposure": "scenes"}, "exposure"),
    ({"exposure": ["scene"]}, "exposure"),
])
def test_bad_fields_are_refused_by_name(scene_path, changes, field):
    s = ViewState.from_scene(load_scene(scene_path))
    with pytest.raises(ViewerMessageError, match=rf"^'?{field}'?:"):     # unknown names quoted
        s.update(changes)


def test_a_refused_message_changes_nothing(scene_path):
    s = ViewState.from_scene(load_scene(scene_path))
    with pytest.raises(ViewerMessageError):
        s.update({"g": 0.1, "albedo": "red"})
    assert s.g == ViewState.from_scene(load_scene(scene_path)).g


def test_preset_sets_albedo_and_its_own_phase(scene_path):
    scene = load_scene(scene_path)
    s = ViewState.from_scene(scene).update({"preset": "jade"})
    m = s.medium(scene.medium)
    assert m.albedo == (0.92, 0.99, 0.94) and len(m.phase.lobes) == 2
    # Moving g afterwards replaces the two lobes by one HG lobe of that g.
    m2 = s.update({"g": 0.3}).medium(scene.medium)
    assert len(m2.phase.lobes) == 1 and m2.phase.lobes[0].g == 0.3


def test_limits_cover_every_numeric_field():
    numeric = {"azimuth", "elevation", "distance", "sun_azimuth", "sun_elevation", "g",
               "density_scale", "exposure", "albedo", "sky"}
    assert numeric == set(LIMITS)


def test_sky_control_sets_the_environment(scene_path):
    """The sky field becomes the light's constant environment (all 0: none), is checked like
    the albedo, and a Renderer given that light renders the sky-lit medium."""
    import clvol
    scene = load_scene(scene_path)
    s = ViewState.from_scene(scene)
    assert s.light(scene.light, scene.camera).environment == scene.light.environment
    blue = s.update({"sky": [0.2, 0.3, 0.6]})
    li = blue.light(scene.light, scene.camera)
    assert li.environment == (0.2, 0.3, 0.6)
    assert blue.update({"sky": [0, 0, 0]}).light(scene.light, scene.camera).environment is None
    for bad in ([1, 2], [0.1, -1, 0.2], "blue"):
        with pytest.raises(ViewerMessageError, match="sky"):
            s.update({"sky": bad})
    cam = dataclasses.replace(scene.camera, width=12, height=10)
    r = clvol.Renderer(dataclasses.replace(scene, camera=cam), ms="none")
    dark = r.render(light=dataclasses.replace(li, irradiance=(0.0, 0.0, 0.0), environment=None))
    lit = r.render(light=dataclasses.replace(li, irradiance=(0.0, 0.0, 0.0)))
    assert dark.layers["single"].max() == 0 and lit.layers["single"].max() > 0


def test_sky_map_menu_offers_the_folders_maps_and_lights_with_them(scene_path):
    """sky_maps lists the valid lat-long EXRs beside the scene (not the square one); a client
    picks one by name (never a path; other names refused), and the light carries that map
    scaled by ``sky``; null goes back to the constant sky."""
    import clvol
    from clvol.viewer.state import sky_maps
    scene = load_scene(scene_path)
    maps = sky_maps(scene)
    assert list(maps) == ["sky.exr"]
    s = ViewState.from_scene(scene)
    assert s.sky_map is None
    for bad in ("render.exr", "../sky.exr", str(scene_path.parent / "sky.exr"), 3):
        with pytest.raises(ViewerMessageError, match="sky_map"):
            s.update({"sky_map": bad}, maps)
    picked = s.update({"sky_map": "sky.exr", "sky": [0.5, 0.5, 0.5]}, maps)
    li = picked.light(scene.light, scene.camera, maps)
    assert li.environment_map == maps["sky.exr"] and li.environment is None
    assert li.environment_scale == (0.5, 0.5, 0.5)
    back = picked.update({"sky_map": None}, maps).light(scene.light, scene.camera, maps)
    assert back.environment_map is None and back.environment == (0.5, 0.5, 0.5)
    assert picked.accumulation_key() != s.update({"sky": [0.5, 0.5, 0.5]}).accumulation_key()
    # The map lights the medium with the sun off, and not as the constant sky of its mean
    # would (the map is brighter overhead: the two images differ by more than rounding).
    cam = dataclasses.replace(scene.camera, width=12, height=10)
    r = clvol.Renderer(dataclasses.replace(scene, camera=cam), ms="none")
    dark = dict(irradiance=(0.0, 0.0, 0.0))
    by_map = r.render(light=dataclasses.replace(li, **dark)).layers["single"]
    mean = tuple(float(v) for v in li.sky_mean())
    by_mean = r.render(light=dataclasses.replace(back, environment=mean, **dark)).layers["single"]
    assert by_map.max() > 0
    assert np.abs(by_map - by_mean).max() > 1e-3 * by_map.max()


# ------------------------------------------------------------------ the server process

def _start_server(scene_path, tmp_path, *extra):
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    proc = subprocess.Popen(
        [sys.executable, "-m", "clvol", "view", str(scene_path), "--port", "0", "--no-browser",
         "--save-dir", str(tmp_path), *extra],
        cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
    line = proc.stdout.readline()
    if "serving" not in line:
        proc.kill()
        raise AssertionError(f"server did not start: {line!r} {proc.stderr.read()}")
    url = line.split("serving ", 1)[1].split()[0]
    assert url.startswith("http://127.0.0.")       # loopback only
    return proc, url


@pytest.fixture(scope="module")
def server(scene_path, tmp_path_factory):
    pytest.importorskip("aiohttp")
    save = tmp_path_factory.mktemp("saved")
    proc, url = _start_server(scene_path, save)
    yield url, save
    proc.send_signal(signal.SIGINT)
    try:
        proc.wait(timeout=20)
    except subprocess.TimeoutExpired:
        proc.kill()


def _parse_frame(data: bytes) -> tuple[dict, bytes]:
    n = struct.unpack("<I", data[:4])[0]
    return json.loads(data[4:4 + n]), data[4 + n:]


async def _next_frame(ws, timeout=60):
    import aiohttp
    while True:
        msg = await asyncio.wait_for(ws.receive(), timeout)
        if msg.type == aiohttp.WSMsgType.BINARY:
            return _parse_frame(msg.data)
        if msg.type != aiohttp.WSMsgType.TEXT:
            raise AssertionError(f"socket ended: {msg}")


async def _settle(ws, method="network"):
    """Switch the connection to ``method`` and return its first frame. The viewer's default,
    the stochastic view, keeps sending frames while it refines; the protocol tests need a
    method that sends one frame per change (the lattice), and frames of the old method
    still in flight are skipped."""
    await ws.send_str(json.dumps({"type": "state", "state": {"method": method}}))
    while True:
        meta, png = await _next_frame(ws)
        if meta["method"] == method:
            return meta, png


def test_server_protocol_errors_frames_and_save(server):
    import aiohttp
    url, save_dir = server

    async def run():
        async with aiohttp.ClientSession() as session:
            async with session.ws_connect(url + "ws") as ws:
                hello = await ws.receive_json()
                assert hello["type"] == "hello" and hello["state"]["method"] == "stochastic"
                meta, png = await _settle(ws)
                assert png[:8] == b"\x89PNG\r\n\x1a\n" and meta["width"] == 64
                assert meta["header"], "the frame carries the render header"
                for bad in ("{not json", json.dumps([1]), json.dumps({"type": "fly"}),
                            json.dumps({"type": "state", "state": {"g": 7}})):
                    await ws.send_str(bad)
                    reply = await ws.receive_json()
                    assert reply["type"] == "error" and reply["message"]
                # Still serving after the bad messages: a valid change gives a new frame.
                await ws.send_str(json.dumps({"type": "state", "state": {"azimuth": 30.0}}))
                meta2, _ = await _next_frame(ws)
                assert meta2["state"]["azimuth"] == 30.0 and meta2["id"] > meta["id"]
                assert meta2["exposure_from"] == "chosen from the image"
                # Exposure from the scene's light (clvol.image.scene_exposure), then back.
                await ws.send_str(json.dumps({"type": "state", "state": {"exposure": "scene"}}))
                meta3, _ = await _next_frame(ws)
                assert meta3["exposure_from"] == "from the scene's light"
                # SCENE's light: irradiance 1, no sky -> log2(0.8 pi) = +1.33 stops.
                assert meta3["exposure"] == pytest.approx(math.log2(AUTO_WHITE * math.pi))
                await ws.send_str(json.dumps({"type": "state", "state": {"exposure": None}}))
                meta4, _ = await _next_frame(ws)
                assert meta4["exposure_from"] == "chosen from the image"
                # An exposure-only change (no new render) is what a save records (before:
                # the last render's state, exposure null).
                await ws.send_str(json.dumps({"type": "state", "state": {"exposure": 1.5}}))
                meta5, _ = await _next_frame(ws)
                assert meta5["exposure"] == 1.5 and meta5["exposure_from"] == "given"
                await ws.send_str(json.dumps({"type": "save"}))
                while True:
                    msg = await ws.receive()
                    if msg.type == aiohttp.WSMsgType.TEXT:
                        saved = json.loads(msg.data)
                        break
                assert saved["type"] == "saved"
                return Path(saved["path"])

    path = asyncio.run(run())
    assert path.parent == save_dir and path.suffix == ".exr"
    from clvol.image import read_exr
    img = read_exr(path)
    assert np.isfinite(img.rgb).all() and img.rgb.shape == (64, 64, 3)
    assert img.header.get("viewer.method") == "network" and "viewer.state" in img.header
    assert json.loads(img.header["viewer.state"])["exposure"] == 1.5
    assert img.header.get("method") == "raymarch"      # the render header is kept


def test_newest_request_wins_and_a_dropped_client_leaves_nothing(server):
    import aiohttp
    url, _ = server

    async def status(session):
        async with session.get(url + "status") as r:
            return await r.json()

    async def run():
        async with aiohttp.ClientSession() as session:
            before = (await status(session))["frames_rendered"]
            async with session.ws_connect(url + "ws") as ws:
                await ws.receive_json()
                # A burst of 20 orbit steps while the first frame renders.
                for i in range(20):
                    await ws.send_str(json.dumps({"type": "state", "state": {"azimuth": float(i)}}))
                metas = []
                while not metas or metas[-1]["state"]["azimuth"] != 19.0:
                    metas.append((await _next_frame(ws))[0])
            rendered = (await status(session))["frames_rendered"] - before
            # Far fewer frames than requests: stale states were skipped, the newest shown.
            assert len(metas) <= 4 and rendered <= 4, (len(metas), rendered)
            # A client that goes away mid-frame.
            ws = await session.ws_connect(url + "ws")
            await ws.receive_json()
            await ws.send_str(json.dumps({"type": "state", "state": {"azimuth": 123.0}}))
            await ws.close()
            for _ in range(100):
                if (await status(session))["connections"] == 0:
                    break
                await asyncio.sleep(0.1)
            assert (await status(session))["connections"] == 0

    asyncio.run(run())


def test_stochastic_method_refines_while_still_then_idles_and_reprojects_on_move(server):
    """The stochastic view-space source: while the view is still the server keeps rendering,
    one more sample per block each frame, until STILL_SAMPLES; then it sends nothing more.
    An orbit step keeps MOVE_HISTORY samples of history plus the new one."""
    import aiohttp
    from clvol.render.ms.view import MOVE_HISTORY, STILL_SAMPLES
    url, _ = server

    async def run():
        async with aiohttp.ClientSession() as session:
            async with session.ws_connect(url + "ws") as ws:
                await ws.receive_json()
                await _settle(ws)                          # the lattice: one frame, then idle
                # back to the stochastic view, turned a little: the source's history (shared
                # by the connections) is reprojected, then refines up to STILL_SAMPLES
                await ws.send_str(json.dumps({"type": "state",
                                              "state": {"method": "stochastic",
                                                        "azimuth": 2.0}}))
                counts, refining = [], True
                while refining:
                    meta, _ = await _next_frame(ws)
                    if meta["method"] == "stochastic":
                        counts.append(meta["spp"])
                        assert "view_depths" in meta["stages_ms"]
                        refining = meta["header"]["raymarch.view_refining"]
                # one more sample per block per frame, STILL_SAMPLES draws after the move,
                # on top of at most MOVE_HISTORY reprojected ones
                assert 1 <= counts[0] <= MOVE_HISTORY + 1
                assert counts == list(range(counts[0], counts[0] + STILL_SAMPLES))
                with pytest.raises(asyncio.TimeoutError):      # converged: no more frames
                    await _next_frame(ws, timeout=1.5)
                await ws.send_str(json.dumps({"type": "state", "state": {"azimuth": 4.0}}))
                meta, _ = await _next_frame(ws)
                assert meta["state"]["azimuth"] == 4.0 and meta["spp"] == MOVE_HISTORY + 1
                await ws.send_str(json.dumps({"type": "state", "state": {"method": "network"}}))
                await _next_frame(ws)

    asyncio.run(run())


def test_loopback_check():
    from clvol.viewer.server import is_loopback
    assert is_loopback("127.0.0.1") and is_loopback("127.0.0.2") and is_loopback("::1")
    assert is_loopback("localhost")
    assert not is_loopback("0.0.0.0") and not is_loopback("10.1.2.3") and not is_loopback("example.org")


def test_ctrl_c_stops_cleanly(scene_path, tmp_path):
    pytest.importorskip("aiohttp")
    proc, _ = _start_server(scene_path, tmp_path)
    proc.send_signal(signal.SIGINT)
    out, err = proc.communicate(timeout=30)
    assert proc.returncode == 0 and "stopped" in err and "Traceback" not in err
    # Another loopback address is not loopback-only by name, but is by address: no warning.
    proc, url = _start_server(scene_path, tmp_path, "--host", "127.0.0.2")
    proc.send_signal(signal.SIGINT)
    _, err = proc.communicate(timeout=30)
    assert url.startswith("http://127.0.0.2:") and "no authentication" not in err


def test_missing_save_dir_exits_2_at_start(scene_path, tmp_path):
    proc = subprocess.run([sys.executable, "-m", "clvol", "view", str(scene_path), "--port", "0",
                           "--no-browser", "--save-dir", str(tmp_path / "missing")], cwd=ROOT,
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 2 and "--save-dir" in proc.stderr and "does not exist" in proc.stderr


def test_failed_save_is_a_message_and_the_page_stays_connected(scene_path, tmp_path):
    """The save folder vanishes while serving: "save" answers an error message, and the
    same socket still renders the next change (it used to close the socket)."""
    pytest.importorskip("aiohttp")
    import aiohttp
    save = tmp_path / "saves"
    save.mkdir()
    proc, url = _start_server(scene_path, save)

    async def run():
        async with aiohttp.ClientSession() as session:
            async with session.ws_connect(url + "ws") as ws:
                await ws.receive_json()                               # hello
                meta, _ = await _settle(ws)
                save.rmdir()
                await ws.send_str(json.dumps({"type": "save"}))
                while True:
                    msg = await asyncio.wait_for(ws.receive(), 60)
                    assert msg.type in (aiohttp.WSMsgType.TEXT, aiohttp.WSMsgType.BINARY), msg
                    if msg.type == aiohttp.WSMsgType.TEXT:
                        reply = json.loads(msg.data)
                        break
                assert reply["type"] == "error" and "does not exist" in reply["message"]
                await ws.send_str(json.dumps({"type": "state", "state": {"azimuth": 20.0}}))
                meta2, _ = await _next_frame(ws)
                assert meta2["state"]["azimuth"] == 20.0 and meta2["id"] > meta["id"]
    try:
        asyncio.run(run())
    finally:
        proc.send_signal(signal.SIGINT)
        try:
            proc.wait(timeout=20)
        except subprocess.TimeoutExpired:
            proc.kill()


def test_bad_port_exits_2(scene_path):
    proc = subprocess.run([sys.executable, "-m", "clvol", "view", str(scene_path), "--port",
                           "70000", "--no-browser"], cwd=ROOT, capture_output=True, text=True)
    assert proc.returncode == 2 and "--port 70000" in proc.stderr


# ------------------------------------------------------------------ the page in Chromium

CHROMIUM = shutil.which("chromium") or "/usr/bin/chromium"
CHROMEDRIVER = shutil.which("chromedriver") or "/usr/bin/chromedriver"

PIXEL_DIGEST_JS = """
const img = document.getElementById('frame');
const c = document.createElement('canvas');
c.width = img.naturalWidth; c.height = img.naturalHeight;
const g = c.getContext('2d'); g.drawImage(img, 0, 0);
const d = g.getImageData(0, 0, c.width, c.height).data;
let lo = 255, hi = 0, h = 0;
for (let i = 0; i < d.length; i += 4) {
  const v = d[i] + d[i + 1] + d[i + 2];
  lo = Math.min(lo, d[i]); hi = Math.max(hi, d[i]);
  h = (h * 31 + v) >>> 0;
}
return [lo, hi, h, c.width];
"""


@pytest.fixture
def browser():
    webdriver = pytest.importorskip("selenium.webdriver")
    if not (os.path.exists(CHROMIUM) and os.path.exists(CHROMEDRIVER)):
        if os.environ.get("CI"):
            pytest.fail("CI must run the browser test: scripts/setup.sh installs chromium")
        pytest.skip("Debian's chromium and chromium-driver are not installed (scripts/setup.sh "
                    "installs them)")
    import tempfile
    from selenium.webdriver.chrome.service import Service
    opts = webdriver.ChromeOptions()
    opts.binary_location = CHROMIUM
    profile = tempfile.mkdtemp(prefix="clvol-chrome-")
    for flag in ("--headless=new", "--no-sandbox", "--disable-gpu", "--disable-quic",
                 "--no-first-run", "--disable-background-networking",
                 "--disable-component-update", "--disable-sync", "--window-size=1000,800",
                 f"--user-data-dir={profile}"):
        opts.add_argument(flag)
    os.environ.setdefault("SE_OFFLINE", "true")     # never let Selenium Manager download
    driver = webdriver.Chrome(options=opts, service=Service(executable_path=CHROMEDRIVER))
    driver.set_script_timeout(60)
    yield driver
    driver.quit()
    shutil.rmtree(profile, ignore_errors=True)


def _wait(driver, predicate, what, timeout=45.0):
    t0 = time.monotonic()
    while time.monotonic() - t0 < timeout:
        value = predicate()
        if value:
            return value
        time.sleep(0.05)
    raise AssertionError(f"timed out waiting for {what}; page errors: "
                         f"{driver.execute_script('return window.clvol.errors')}")


def _frames(driver) -> int:
    return int(driver.execute_script("return window.clvol.framesReceived"))


def _meta(driver) -> dict:
    return driver.execute_script("return window.clvol.lastMeta")


def test_page_in_headless_chromium(server, browser, tmp_path):
    from selenium.webdriver.common.action_chains import ActionChains
    from selenium.webdriver.common.by import By
    url, _ = server
    d = browser
    d.get(url)
    _wait(d, lambda: _frames(d) >= 1, "the first frame")
    # The default method is the stochastic view (every front door's): while still, its
    # samples per block climb.
    assert d.execute_script("return document.getElementById('method').value") == "stochastic"
    _wait(d, lambda: _meta(d)["method"] == "stochastic" and _meta(d)["spp"] >= 6,
          "stochastic frames refining")
    assert d.find_element(By.ID, "spplabel").text == "samples"
    # The progressive view (in the menu): path-traced points arrive in its blocks while still
    # (the panel shows their mean per block).
    d.execute_script("const m = document.getElementById('method'); m.value = 'progressive';"
                     "m.dispatchEvent(new Event('change'));")
    _wait(d, lambda: _meta(d)["method"] == "progressive" and _meta(d)["spp"] >= 6,
          "progressive frames refining")
    _wait(d, lambda: d.find_element(By.ID, "paths").text.endswith(" per block")
          and float(d.find_element(By.ID, "paths").text.split()[0]) > 0, "paths per block")
    # No horizontal scrollbar: a long menu label once widened the panel past the window.
    assert d.execute_script("const e = document.documentElement;"
                            "return e.scrollWidth <= e.clientWidth")
    # The checks below compare pixels of one still image: the lattice sends one per change.
    d.execute_script("const m = document.getElementById('method'); m.value = 'network';"
                     "m.dispatchEvent(new Event('change'));")
    _wait(d, lambda: _meta(d)["method"] == "network", "a lattice frame")
    _wait(d, lambda: d.execute_script("return document.getElementById('frame').complete"), "decode")
    shot = tmp_path / "page.png"
    d.save_screenshot(str(shot))
    assert shot.stat().st_size > 1000
    # The frame's figures are above the fold (they sat below it at 1100x750).
    assert d.execute_script("return document.getElementById('stages')"
                            ".getBoundingClientRect().top < window.innerHeight / 2")
    lo, hi, digest0, width = d.execute_script(PIXEL_DIGEST_JS)
    assert width == 64 and hi - lo > 20, "the frame is not blank"

    # Drag: the camera orbits and a different frame arrives.
    n = _frames(d)
    img = d.find_element(By.ID, "frame")
    ActionChains(d).move_to_element(img).click_and_hold().move_by_offset(60, 0).release().perform()
    _wait(d, lambda: _frames(d) > n and _meta(d)["state"]["azimuth"] != 0.0, "a frame after the drag")
    _wait(d, lambda: d.execute_script(PIXEL_DIGEST_JS)[2] != digest0, "a different image")

    # The albedo slider changes the frame.
    n = _frames(d)
    digest1 = d.execute_script(PIXEL_DIGEST_JS)[2]
    d.execute_script("const s = document.getElementById('albedo0'); s.value = 0.3;"
                     "s.dispatchEvent(new Event('input'));")
    _wait(d, lambda: _frames(d) > n and _meta(d)["state"]["albedo"][0] == 0.3, "albedo frame")
    _wait(d, lambda: d.execute_script(PIXEL_DIGEST_JS)[2] != digest1, "a darker image")

    # A preset moves the albedo and g sliders to its values, so that touching one albedo
    # slider afterwards sends the preset's other channels, not the stale ones.
    d.execute_script("const p = document.getElementById('preset'); p.value = 'jade';"
                     "p.dispatchEvent(new Event('change'));")
    _wait(d, lambda: _meta(d)["state"]["preset"] == "jade", "a jade frame")
    jade = _meta(d)["state"]
    _wait(d, lambda: d.execute_script("return [0, 1, 2].map(i => Number(document."
                                      "getElementById('albedo' + i).value))") == jade["albedo"],
          "the albedo sliders at the preset's values")
    assert abs(float(d.execute_script("return document.getElementById('g').value")) - jade["g"]) < 1e-6
    # ... and the numbers beside the sliders show the preset's values.
    _wait(d, lambda: d.find_element(By.ID, "g_num").text == f"{jade['g']:.2f}", "g's number")
    assert d.find_element(By.ID, "albedo0_num").text == f"{jade['albedo'][0]:.3f}"
    dens = float(d.find_element(By.ID, "density_num").text)
    # the slider holds log10 in steps of 0.01 (10^0.005 - 1 = 1.2% either side) and the
    # number has 3 digits (0.2% more)
    assert abs(dens / _meta(d)["state"]["density_scale"] - 1) < 0.014
    n = _frames(d)
    d.execute_script("const s = document.getElementById('albedo1'); s.value = 0.5;"
                     "s.dispatchEvent(new Event('input'));")
    _wait(d, lambda: _frames(d) > n and _meta(d)["state"]["albedo"][1] == 0.5, "albedo 1 frame")
    assert _meta(d)["state"]["albedo"] == [jade["albedo"][0], 0.5, jade["albedo"][2]]

    # A malformed message gets an error reply, and frames still arrive afterwards.
    d.execute_script("window.clvol.socket.send('{oops');")
    _wait(d, lambda: any("error" in e for e in d.execute_script("return window.clvol.errors")),
          "the error reply")
    # The message box wraps a long unbroken message (the reply echoes the unknown type)
    # instead of scrolling sideways.
    d.execute_script("window.clvol.socket.send(JSON.stringify({type: 'x'.repeat(300)}));")
    _wait(d, lambda: any("xxxxxxxxxx" in e for e in d.execute_script("return window.clvol.errors")),
          "the long error reply")
    assert d.execute_script("const m = document.getElementById('messages');"
                            "return m.scrollWidth <= m.clientWidth + 1")
    n = _frames(d)
    d.execute_script("const s = document.getElementById('g'); s.value = 0.2;"
                     "s.dispatchEvent(new Event('input'));")
    _wait(d, lambda: _frames(d) > n, "a frame after the error")

    # A slider's number follows the slider as it moves.
    assert d.find_element(By.ID, "g_num").text == "0.20"
    # Exposure from the light: the menu sends "scene", the slider shows the stops used.
    d.execute_script("const e = document.getElementById('expmode'); e.value = 'scene';"
                     "e.dispatchEvent(new Event('change'));")
    _wait(d, lambda: _meta(d)["exposure_from"] == "from the scene's light", "a light-exposed frame")
    assert abs(float(d.execute_script("return document.getElementById('exposure').value"))
               - math.log2(AUTO_WHITE * math.pi)) < 0.051            # the slider's step is 0.1
    d.execute_script("const e = document.getElementById('expmode'); e.value = 'image';"
                     "e.dispatchEvent(new Event('change'));")
    _wait(d, lambda: _meta(d)["exposure_from"] == "chosen from the image", "an auto frame")

    # The sky map menu lists the folder's map; picking it sends its name and a frame lit by
    # it comes back (white at scale 1 when the sky was off).
    assert d.execute_script("return [...document.getElementById('skymap').options]"
                            ".map(o => o.value)") == ["", "sky.exr"]
    d.execute_script("const m = document.getElementById('skymap'); m.value = 'sky.exr';"
                     "m.dispatchEvent(new Event('change'));")
    _wait(d, lambda: _meta(d)["state"]["sky_map"] == "sky.exr", "a frame under the map")
    assert _meta(d)["state"]["sky"] == [1.0, 1.0, 1.0]
    d.execute_script("const m = document.getElementById('skymap'); m.value = '';"
                     "m.dispatchEvent(new Event('change'));")
    _wait(d, lambda: _meta(d)["state"]["sky_map"] is None, "a frame under the constant sky")

    # The path tracer accumulates while the view is still: spp grows.
    d.execute_script("const m = document.getElementById('method'); m.value = 'pathtrace';"
                     "m.dispatchEvent(new Event('change'));")
    _wait(d, lambda: _meta(d)["method"] == "pathtrace", "a path-traced frame")
    spp0 = _meta(d)["spp"]
    _wait(d, lambda: _meta(d)["spp"] >= spp0 + 2, "spp to grow")
    # ... and the page shows the count.
    _wait(d, lambda: (lambda t: t.isdigit() and int(t) >= spp0 + 2)(d.find_element(By.ID, "spp").text),
          "the spp display")

    # Frames per second at 256^2 with the paper's method while orbiting: every frame that
    # arrives triggers the next camera step, as a user dragging continuously would.
    d.execute_script("const m = document.getElementById('method'); m.value = 'network';"
                     "m.dispatchEvent(new Event('change'));"
                     "const r = document.getElementById('resolution'); r.value = '256';"
                     "r.dispatchEvent(new Event('change'));")
    _wait(d, lambda: _meta(d)["method"] == "network" and _meta(d)["width"] == 256, "256^2 frames")
    fps = d.execute_async_script("""
        const done = arguments[0];
        const start = performance.now(), n0 = window.clvol.framesReceived;
        let az = 0;
        const step = () => {
          const t = performance.now() - start;
          if (t > 4000) { done((window.clvol.framesReceived - n0) / (t / 1000)); return; }
          const seen = window.clvol.framesReceived;
          az += 3;
          window.clvol.socket.send(JSON.stringify({type: 'state', state: {azimuth: az}}));
          const wait = () => (window.clvol.framesReceived > seen ? step() : setTimeout(wait, 2));
          wait();
        };
        step();""")
    print(f"\nviewer: {fps:.2f} frames/s at 256x256 while orbiting (paper's method, "
          f"{os.cpu_count()} cores, load {os.getloadavg()[0]:.1f})")
    assert fps > 0


def test_stage_times_come_from_the_header_seconds_entries():
    from clvol.viewer.server import stage_times
    header = {"seconds": 0.5, "seconds.march": 0.0125, "seconds.gather": 2, "method": "raymarch",
              "seconds.flag": True, "raymarch.step": 0.01}
    assert stage_times(header) == {"march": 12.5, "gather": 2000.0}
