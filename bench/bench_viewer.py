"""Frames per second of `clvol view` in a real browser while orbiting.

    python bench/bench_viewer.py [examples/cloud.toml] [--seconds 8] [--size 256]
                                 [--methods single network stochastic ...]

Starts the viewer on 127.0.0.1 (a free port), opens it in headless Chromium (Debian's
chromium + chromedriver, driven by Selenium), and for each method sends the next orbit step
(2 degrees) as soon as a frame arrives, as a user dragging continuously would: a new camera
every frame. Prints frames per second, and the median over the orbit's frames of the frame
time and of each stage (the render header's seconds), with the load.
"""
from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import tempfile
import time

import _common

ROOT = _common.ROOT
ORBIT_JS = """
const seconds = arguments[0], done = arguments[arguments.length - 1];
const start = performance.now(), n0 = window.clvol.framesReceived;
let az = 0;
const metas = [];
const step = () => {
  if (window.clvol.framesReceived > n0) metas.push(window.clvol.lastMeta);
  const t = performance.now() - start;
  if (t > seconds * 1000) {
    done({fps: (window.clvol.framesReceived - n0) / (t / 1000), metas: metas});
    return;
  }
  const seen = window.clvol.framesReceived;
  az += 2;
  window.clvol.socket.send(JSON.stringify({type: 'state', state: {azimuth: az}}));
  const wait = () => (window.clvol.framesReceived > seen ? step() : setTimeout(wait, 2));
  wait();
};
step();"""


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("scene", nargs="?", default=str(ROOT / "examples" / "cloud.toml"))
    ap.add_argument("--seconds", type=float, default=8.0, help="orbit time per method")
    ap.add_argument("--size", type=int, default=256, choices=[64, 128, 256, 512])
    ap.add_argument("--methods", nargs="+", default=["single", "network"])
    args = ap.parse_args(argv)
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service

    print(_common.machine())
    server = subprocess.Popen([sys.executable, "-m", "clvol", "view", args.scene, "--port", "0",
                               "--no-browser"], stdout=subprocess.PIPE, text=True, cwd=ROOT)
    url = server.stdout.readline().split("serving ", 1)[1].split()[0]
    opts = webdriver.ChromeOptions()
    opts.binary_location = "/usr/bin/chromium"
    for flag in ("--headless=new", "--no-sandbox", "--disable-gpu", "--disable-quic",
                 "--no-first-run", "--disable-background-networking",
                 "--disable-component-update", "--disable-sync",
                 f"--user-data-dir={tempfile.mkdtemp(prefix='clvol-bench-')}"):
        opts.add_argument(flag)
    os.environ.setdefault("SE_OFFLINE", "true")
    d = webdriver.Chrome(options=opts, service=Service(executable_path="/usr/bin/chromedriver"))
    try:
        d.set_script_timeout(args.seconds + 120)
        d.get(url)
        t0 = time.time()
        while d.execute_script("return window.clvol.framesReceived") < 1:
            if time.time() - t0 > 180:
                raise SystemExit("no first frame within 180 s")
            time.sleep(0.2)
        print(f"scene {args.scene}, {args.size}x{args.size}, orbit 2 degrees per frame, "
              f"{args.seconds:g} s per method")
        for method in args.methods:
            d.execute_script("window.clvol.socket.send(JSON.stringify({type: 'state', state: "
                             f"{{method: '{method}', resolution: {args.size}}}}}))")
            time.sleep(3.0)          # first frame of the method (builds, lattice) off the clock
            got = d.execute_async_script(ORBIT_JS, args.seconds)
            metas = got["metas"] or [d.execute_script("return window.clvol.lastMeta")]
            names = sorted({k for m in metas for k in m["stages_ms"]})
            med = {k: statistics.median(m["stages_ms"].get(k, 0.0) for m in metas)
                   for k in names}
            stages = ", ".join(f"{k} {v:.1f}" for k, v in med.items() if v)
            print(f"{method:>10}: {got['fps']:6.2f} frames/s; median frame "
                  f"{statistics.median(m['frame_ms'] for m in metas):.1f} ms over {len(metas)} "
                  f"({stages} ms); load {os.getloadavg()[0]:.2f}")
    finally:
        d.quit()
        server.terminate()
        server.wait()
    return 0


if __name__ == "__main__":
    sys.exit(main())
