"""Host wrapper for cl/grid.cl (grid lookups, ray/box tests, camera rays of grid.h)."""
import numpy as np

from ..runtime import get_runtime


def f4(v) -> np.ndarray:
    """A 3-vector as an OpenCL float4 argument (w = 0)."""
    out = np.zeros(4, np.float32)
    out[:3] = np.asarray(v, np.float64)
    return out


def grid_density(density, bmin, bmax, points, runtime=None) -> np.ndarray:
    rt = runtime or get_runtime()
    density = np.ascontiguousarray(density, np.float32)
    nz, ny, nx = density.shape
    pts = np.ascontiguousarray(points, np.float32).reshape(-1, 3)
    k = rt.program("grid").kernel("grid_density_many", [None, np.int32, np.int32, np.int32,
                                                        None, None, None, np.int32, None])
    out = rt.empty(len(pts))
    rt.launch(k, len(pts), (rt.to_device(density), np.int32(nx), np.int32(ny), np.int32(nz),
                            f4(bmin), f4(bmax), rt.to_device(pts), np.int32(len(pts)), out))
    return rt.from_device(out, (len(pts),))


def box_intersect(origins, dirs, bmin, bmax, tmin=0.0, runtime=None):
    rt = runtime or get_runtime()
    o = np.ascontiguousarray(origins, np.float32).reshape(-1, 3)
    d = np.ascontiguousarray(dirs, np.float32).reshape(-1, 3)
    k = rt.program("grid").kernel("box_intersect_many",
                                  [None, None, None, None, np.float32, np.int32, None])
    out = rt.empty((len(o), 2))
    rt.launch(k, len(o), (rt.to_device(o), rt.to_device(d), f4(bmin), f4(bmax),
                          np.float32(tmin), np.int32(len(o)), out))
    t = rt.from_device(out, (len(o), 2))
    return t[:, 0], t[:, 1]


def camera_rays(camera, runtime=None) -> np.ndarray:
    """(H, W, 3) pixel-centre directions for a clvol.scene.Camera."""
    rt = runtime or get_runtime()
    forward, right, up = camera.basis()
    w, h = camera.width, camera.height
    k = rt.program("grid").kernel("camera_rays", [None, None, None, np.float32, np.int32,
                                                  np.int32, None])
    out = rt.empty((h * w, 3))
    rt.launch(k, w * h, (f4(forward), f4(right), f4(up),
                         np.float32(camera.tan_half_fov), np.int32(w),
                         np.int32(h), out))
    return rt.from_device(out, (h, w, 3))
