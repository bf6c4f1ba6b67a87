"""``clvol view``: a browser viewer served from this process (aiohttp).

One ``FrameMaker`` owns the ``clvol.Renderer`` objects (one per method in the menu, made on
first use, so device state is shared by every client) and a single render thread: OpenCL
work is serialised, and the event loop stays free to read messages while a frame renders.

Per WebSocket connection the server keeps the newest requested state only. A render loop
takes that state when the previous frame is done, so a burst of requests (a mouse drag)
costs one frame, never a backlog. The path tracer keeps accumulating passes while the state
is unchanged and sends the running mean with its spp count.

Wire format, server -> client: a binary message ``uint32 LE n | n bytes of JSON | PNG``,
so the metadata and the image of a frame cannot be split. Text messages (JSON) carry
``hello``, ``error`` and ``saved``. Client -> server: JSON text, ``{"type": "state",
"state": {...partial ViewState...}}``, ``{"type": "save"}``; see ``docs/viewer.md``.
"""
from __future__ import annotations

import asyncio
import dataclasses
import ipaddress
import json
import os
import struct
import sys
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..errors import ClvolError
from .state import METHODS, ViewerMessageError, ViewState, sky_maps

STATIC_DIR = Path(__file__).with_name("static")
# Path tracer passes: samples per pixel per pass; small so the first image comes quickly.
PT_PASS_SPP = 1
MAX_MESSAGE_BYTES = 64 * 1024


def is_loopback(host: str) -> bool:
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return host == "localhost"


@dataclass
class ViewFrame:
    """A finished frame: the linear image (kept for re-exposure and saving) and its facts."""
    state: ViewState
    layers: dict
    header: dict
    spp: int = 0
    seconds: float = 0.0
    stage_ms: dict = field(default_factory=dict)


def stage_times(header: dict) -> dict[str, float]:
    """Per-stage times in ms from a render header's ``seconds.STAGE`` entries."""
    return {key.split(".", 1)[1]: round(float(value) * 1e3, 3) for key, value in header.items()
            if key.startswith("seconds.") and isinstance(value, (int, float))
            and not isinstance(value, bool)}


class FrameMaker:
    """Renders frames for every client through one render thread."""

    def __init__(self, scene):
        from .. import Renderer          # the package's one rendering object
        self._renderer_type = Renderer
        self.scene = scene
        self.renderers: dict[str, object] = {}
        self.executor = ThreadPoolExecutor(max_workers=1, thread_name_prefix="clvol-render")
        self.lock = threading.Lock()
        self.frames_rendered = 0
        self.sky_maps = sky_maps(scene)      # the map menu: file name -> path
        from ..sequence import available_frames
        self.frames = available_frames(scene.volume)   # a sequence's frames (play control)
        self.loaded: dict[int, object] = {}            # frame -> LoadedFrame (a few, newest)
        self.showing: dict[str, int | None] = {}       # method -> the frame its renderer has

    def renderer(self, method: str):
        if method not in self.renderers:
            options = dict(METHODS[method])
            if method == "pathtrace":
                options["spp"] = PT_PASS_SPP
            self.renderers[method] = self._renderer_type(self.scene, **options)
        return self.renderers[method]

    @staticmethod
    def refines(frame: ViewFrame) -> bool:
        """Whether rendering the same state again improves ``frame``: the path tracer adds
        a pass; the stochastic source says whether it still draws (its own rule: a still
        view draws STILL_SAMPLES times, then stops; an empty or unlit view never refines);
        the network's sky says whether some of its cells are stale."""
        if frame.state.method == "pathtrace":
            return True
        return (frame.header.get("raymarch.view_refining") is True
                or frame.header.get("raymarch.env_refining") is True)   # sky cells stale

    def volume_for(self, method: str, frame: int | None) -> dict:
        """``render`` keywords that switch ``method``'s renderer to a sequence's ``frame``
        (read on first use, a few kept), or {} when it already shows it."""
        if frame is None or self.showing.get(method) == frame:
            return {}
        from ..sequence import load_frame
        if not self.frames:
            raise ClvolError(f"frame {frame}: the scene's volume is not a sequence (or none of "
                             f"its files exist)")
        if frame not in self.loaded:
            if frame not in self.frames:
                raise ClvolError(f"frame {frame}: not in the sequence (frames {self.frames[0]}"
                                 f"..{self.frames[-1]} found)")
            self.loaded[frame] = load_frame(self.scene, frame)
            while len(self.loaded) > 4:
                self.loaded.pop(next(iter(self.loaded)))
        f = self.loaded[frame]
        return {"grid": f.grid, "emission": f.emission}

    def render(self, state: ViewState, previous: ViewFrame | None) -> ViewFrame:
        """One frame for ``state``; for the path tracer, one more pass averaged into
        ``previous`` when it was made for the same state."""
        with self.lock:
            t0 = time.perf_counter()
            camera = state.camera(self.scene.camera)
            light = state.light(self.scene.light, self.scene.camera, self.sky_maps)
            medium = state.medium(self.scene.medium)
            r = self.renderer(state.method)
            volume = self.volume_for(state.method, state.frame)
            accumulate = (state.method == "pathtrace" and previous is not None
                          and previous.state.accumulation_key() == state.accumulation_key())
            if state.method == "pathtrace":
                pass_index = previous.spp // PT_PASS_SPP if accumulate else 0
                result = r.render(camera=camera, light=light, medium=medium, seed=pass_index,
                                  **volume)
            else:
                result = r.render(camera=camera, light=light, medium=medium, **volume)
            self.showing[state.method] = state.frame
            layers = {k: np.asarray(v, dtype=np.float32) for k, v in result.layers.items()}
            spp = 0
            if state.method == "pathtrace":
                spp = PT_PASS_SPP
                if accumulate:
                    n = previous.spp
                    w = PT_PASS_SPP / (n + PT_PASS_SPP)
                    layers = {k: (previous.layers[k] * (1.0 - w) + v * w).astype(np.float32)
                              for k, v in layers.items() if k in previous.layers}
                    spp = n + PT_PASS_SPP
            if "raymarch.view_accumulated" in result.header:
                spp = int(result.header["raymarch.view_accumulated"])   # samples per block
            seconds = time.perf_counter() - t0
            self.frames_rendered += 1
            return ViewFrame(state=state, layers=layers, header=dict(result.header), spp=spp,
                         seconds=seconds, stage_ms=stage_times(result.header))

    def close(self):
        self.executor.shutdown(wait=True, cancel_futures=True)


def encode_frame(frame: ViewFrame, frame_id: int, exposure: float | str | None,
                 light=None) -> bytes:
    """``exposure``: stops, None (from the image) or "scene" (from ``light``, the frame's
    light: clvol.image.scene_exposure); the frame's meta says which ("exposure_from")."""
    from ..image import choose_exposure, encode_png_rgb8, tonemap_srgb8
    stops, how = choose_exposure(exposure, frame.layers["total"], light)
    pixels, used = tonemap_srgb8(frame.layers["total"], stops, curve="filmic")
    meta = {
        "type": "frame", "id": frame_id, "method": frame.state.method,
        "width": int(pixels.shape[1]), "height": int(pixels.shape[0]),
        "spp": frame.spp, "frame_ms": round(frame.seconds * 1e3, 2),
        "stages_ms": frame.stage_ms, "exposure": used, "exposure_from": how,
        "effects": {k: v for k, v in frame.header.items()
                    if k.startswith(("simulated", "skipped", "effects"))},
        "warning": frame.header.get("warning"),
        "header": {k: v for k, v in frame.header.items() if isinstance(v, (str, int, float))},
        "state": frame.state.to_json(),
    }
    head = json.dumps(meta, default=str).encode()
    return struct.pack("<I", len(head)) + head + encode_png_rgb8(pixels)


class Connection:
    """One client: its newest state, its last frame, and its render loop."""

    def __init__(self, ws, maker: FrameMaker, initial: ViewState, save_dir: Path):
        self.ws, self.maker, self.save_dir = ws, maker, save_dir
        self.state = initial
        self.wake = asyncio.Event()
        self.wake.set()                     # the first frame
        self.last: ViewFrame | None = None
        self.frame_id = 0
        self.closed = False

    async def send_json(self, obj):
        if not self.ws.closed:
            await self.ws.send_str(json.dumps(obj))

    async def handle(self, text: str):
        try:
            if len(text) > MAX_MESSAGE_BYTES:
                raise ViewerMessageError(f"message of {len(text)} bytes; at most {MAX_MESSAGE_BYTES}")
            try:
                msg = json.loads(text)
            except json.JSONDecodeError as e:
                raise ViewerMessageError(f"not JSON ({e.msg} at {e.pos})") from None
            if not isinstance(msg, dict) or "type" not in msg:
                raise ViewerMessageError('expected an object with a "type"')
            kind = msg["type"]
            if kind == "state":
                self.state = self.state.update(msg.get("state"), self.maker.sky_maps)
                self.wake.set()
            elif kind == "save":
                await self.save()
            else:
                raise ViewerMessageError(f"type: {kind!r} is not one of state, save")
        except ViewerMessageError as e:
            await self.send_json({"type": "error", "message": str(e)})
        except ClvolError as e:        # e.g. the save folder vanished: say so, stay connected
            await self.send_json({"type": "error", "message": str(e).splitlines()[0]})

    async def save(self):
        from ..image import write_exr      # writes atomically
        if self.last is None:
            raise ViewerMessageError("save: no frame yet")
        name = time.strftime("clvol_view_%Y%m%d_%H%M%S") + f"_{self.frame_id}.exr"
        path = self.save_dir / name
        header = {**{k: v for k, v in self.last.header.items() if isinstance(v, (str, int, float))},
                  "viewer.method": self.last.state.method,
                  "viewer.state": json.dumps(self.last.state.to_json())}
        if self.last.spp:
            header["spp"] = self.last.spp
        loop = asyncio.get_running_loop()
        await loop.run_in_executor(None, lambda: write_exr(path, self.last.layers, header))
        await self.send_json({"type": "saved", "path": str(path)})

    async def render_loop(self):
        loop = asyncio.get_running_loop()
        while not self.closed:
            await self.wake.wait()
            self.wake.clear()
            state = self.state
            last = self.last
            if (last is not None and not self.maker.refines(last)
                    and last.state.accumulation_key() == state.accumulation_key()):
                # only the exposure changed: re-tone-map, under the new state (a save then
                # records the exposure shown, not the last render's)
                frame = dataclasses.replace(last, state=state)
            else:
                try:
                    frame = await loop.run_in_executor(self.maker.executor, self.maker.render,
                                                       state, last)
                except ClvolError as e:
                    await self.send_json({"type": "error", "message": str(e).splitlines()[0]})
                    continue
            if self.closed or self.ws.closed:
                return
            self.last = frame
            self.frame_id += 1
            # "from the light" uses the frame's own light (the client's sun and sky)
            light = frame.state.light(self.maker.scene.light, self.maker.scene.camera,
                                      self.maker.sky_maps)
            data = await loop.run_in_executor(None, encode_frame, frame, self.frame_id,
                                              state.exposure, light)
            try:
                await self.ws.send_bytes(data)
            except (ConnectionError, RuntimeError):
                return
            if self.maker.refines(frame) and self.state is state:
                self.wake.set()               # keep accumulating while the view is still


def make_app(scene, save_dir: Path | None = None):
    from aiohttp import WSMsgType, web

    maker = FrameMaker(scene)
    initial = ViewState.from_scene(scene)
    app = web.Application()
    app["maker"] = maker
    app["connections"] = set()
    save_dir = Path(save_dir or Path.cwd())
    if not save_dir.is_dir():
        raise ClvolError(f"--save-dir {save_dir}: folder does not exist")
    if not os.access(save_dir, os.W_OK):
        raise ClvolError(f"--save-dir {save_dir}: folder is not writable")

    async def index(request):
        return web.FileResponse(STATIC_DIR / "index.html")

    async def status(request):
        return web.json_response({"connections": len(app["connections"]),
                                  "frames_rendered": maker.frames_rendered,
                                  "methods": list(METHODS)})

    async def websocket(request):
        # No per-message deflate: frames are PNG (already compressed), so it would only cost CPU.
        ws = web.WebSocketResponse(max_msg_size=MAX_MESSAGE_BYTES * 4, compress=False)
        await ws.prepare(request)
        conn = Connection(ws, maker, initial, save_dir)
        app["connections"].add(conn)
        await conn.send_json({"type": "hello", "state": initial.to_json(),
                              "methods": list(METHODS), "sky_maps": list(maker.sky_maps),
                              "frames": maker.frames,
                              "scene": str(scene.path) if scene.path else None})
        task = asyncio.create_task(conn.render_loop())
        try:
            async for msg in ws:
                if msg.type == WSMsgType.TEXT:
                    await conn.handle(msg.data)
                elif msg.type == WSMsgType.BINARY:
                    await conn.send_json({"type": "error", "message": "binary messages are not accepted"})
                elif msg.type == WSMsgType.ERROR:
                    break
        finally:
            conn.closed = True
            conn.wake.set()
            task.cancel()
            try:
                await task
            except (asyncio.CancelledError, Exception):
                pass
            app["connections"].discard(conn)
        return ws

    async def on_shutdown(app):
        for conn in list(app["connections"]):
            await conn.ws.close()

    async def on_cleanup(app):
        maker.close()

    app.router.add_get("/", index)
    app.router.add_get("/status", status)
    app.router.add_get("/ws", websocket)
    app.router.add_static("/static", STATIC_DIR)
    app.on_shutdown.append(on_shutdown)
    app.on_cleanup.append(on_cleanup)
    return app


def serve(scene, host: str = "127.0.0.1", port: int = 8765, open_browser: bool = True,
          save_dir: Path | None = None) -> int:
    """Serve until Ctrl-C. Port 0 picks a free port; the URL is printed once listening."""
    from aiohttp import web

    if not is_loopback(host):
        print(f"clvol view: warning: listening on {host}, reachable from other machines; "
              f"the viewer has no authentication", file=sys.stderr)
    app = make_app(scene, save_dir)

    async def main():
        import signal
        import socket
        stop = asyncio.Event()
        loop = asyncio.get_running_loop()
        for sig in (signal.SIGINT, signal.SIGTERM):
            loop.add_signal_handler(sig, stop.set)
        sock = socket.socket(socket.AF_INET6 if ":" in host else socket.AF_INET)
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            sock.bind((host, port))
        except OSError as e:
            sock.close()
            raise ClvolError(f"--host {host} --port {port}: cannot listen ({e.strerror or e})") from None
        runner = web.AppRunner(app, handle_signals=False)
        await runner.setup()
        await web.SockSite(runner, sock).start()
        bound = sock.getsockname()[1]
        url = f"http://{host if ':' not in host else '[' + host + ']'}:{bound}/"
        print(f"clvol view: serving {url} (Ctrl-C stops)", flush=True)
        if open_browser:
            import webbrowser
            webbrowser.open(url)
        try:
            await stop.wait()
        finally:
            await runner.cleanup()

    try:
        asyncio.run(main())
    except KeyboardInterrupt:
        pass
    print("clvol view: stopped", file=sys.stderr, flush=True)
    return 0
