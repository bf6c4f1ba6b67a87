"""The renderer against images saved before its refactor, and the Renderer API.

Golden images (tests/data/make_goldens.py): the four example scenes (copied to
tests/data/scenes/) at 48^2 through every multiple-scattering source of the ray marcher and
through the path tracer. On the device that made them the images must be bit-identical (the
refactor moves code, it does not change arithmetic). On another device the OpenCL compiler may
contract or reorder float operations differently: there we allow 1e-4 of the image's largest
value per pixel (float32 rounding through a few hundred march steps stays far below that).
"""
from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

DATA = Path(__file__).resolve().parent / "data"
sys.path.insert(0, str(DATA))
import make_goldens as mg  # noqa: E402

from clvol.runtime import get_runtime  # noqa: E402


def _compare(got: dict, want: dict, prefix: str, device: str):
    same_device = device == get_runtime().entry.label
    for key, ref in want.items():
        if not key.startswith(prefix):
            continue
        layer = key[len(prefix):]
        img = got[layer]
        assert img.shape == ref.shape, key
        if same_device:
            np.testing.assert_array_equal(img, ref, err_msg=key)
        else:
            np.testing.assert_allclose(img, ref, rtol=0, atol=1e-4 * max(float(ref.max()), 1e-30),
                                       err_msg=key)


@pytest.fixture(scope="module")
def raymarch_goldens():
    with np.load(DATA / "goldens_raymarch.npz") as z:
        return {k: z[k] for k in z.files}


@pytest.mark.parametrize("ms", list(mg.RAYMARCH_SOURCES))
@pytest.mark.parametrize("name", mg.SCENES)
def test_raymarch_images_match_goldens(raymarch_goldens, name, ms):
    got = mg.render_raymarch_golden(name, ms)
    _compare(got, raymarch_goldens, f"{name}/{ms}/", str(raymarch_goldens["device"]))


@pytest.mark.parametrize("name", mg.SCENES)
def test_pathtrace_images_match_goldens(name):
    with np.load(DATA / "goldens_pathtrace.npz") as z:
        want = {k: z[k] for k in z.files}
    got = mg.render_pathtrace_golden(name)
    _compare(got, want, f"{name}/", str(want["device"]))


# --------------------------------------------------------------------------- Renderer API

import dataclasses  # noqa: E402

import clvol  # noqa: E402
from clvol.cli import main  # noqa: E402
from clvol.errors import ClvolError  # noqa: E402
from clvol.scene import Phase, scene_from_dict  # noqa: E402
from scene_toml import SMALL_CLOUD, write_scene  # noqa: E402

SMALL = {
    "volume": {"generator": "cloud", "seed": 4, "resolution": 16},
    "medium": {"preset": "cloud", "density_scale": 30.0},
    "light": {"direction": [0.5, 0.8, 0.3]},
    "camera": {"origin": [0.3, 0.4, 2.2], "target": [0.0, 0.0, 0.0], "up": [0.0, 1.0, 0.0],
               "fov_y": 35.0, "width": 16, "height": 12},
}


def small_scene(**medium):
    d = {k: dict(v) for k, v in SMALL.items()}
    d["medium"].update(medium)
    return scene_from_dict(d, "<renderer test>")


@pytest.fixture(scope="module")
def scene_file(tmp_path_factory):
    p = tmp_path_factory.mktemp("scene") / "s.toml"
    return write_scene(p, **SMALL_CLOUD)


def test_default_is_raymarch_with_the_shipped_network(scene_file):
    r = clvol.Renderer(clvol.load_scene(scene_file), ms_resolution=8)
    res = r.render()
    h = res.header
    assert r.method == "raymarch" and h["raymarch.ms"] == "network"
    assert h["raymarch.weights"].endswith("full_albedo.npz")
    assert "full_albedo.npz" in h["method.description"]
    assert "network-filled F_ms lattice 8x8x8" in h["simulated"]
    assert res.total.shape == (10, 12, 3) and res.alpha.shape == (10, 12)
    assert res.multiple.max() > 0


def test_cli_default_names_method_and_weights(scene_file, tmp_path, capsys):
    from clvol.image import read_exr
    out = tmp_path / "d.exr"
    assert main(["render", str(scene_file), "-o", str(out), "--ms-resolution", "6"]) == 0
    err = capsys.readouterr().err
    assert "  method: raymarch\n" in err
    assert "method.description: ray marching: exact single scattering + network multiple " \
           "scattering (weights full_albedo.npz)" in err
    h = read_exr(out).header
    assert h["method"] == "raymarch" and h["raymarch.ms"] == "network"
    assert str(h["raymarch.weights"]).endswith("full_albedo.npz")
    # The explicit spelling of the default gives the same image.
    out2 = tmp_path / "e.exr"
    assert main(["render", str(scene_file), "-o", str(out2), "--method", "raymarch", "--ms",
                 "network", "--ms-resolution", "6"]) == 0
    np.testing.assert_array_equal(read_exr(out).layers["total"], read_exr(out2).layers["total"])


@pytest.mark.parametrize("argv,names", [
    (["--spp", "4"], ["--spp", "raymarch"]),
    (["--seed", "3"], ["--seed", "raymarch"]),
    (["--time", "1"], ["--time", "raymarch"]),
    (["--weights", "x.npz", "--ms", "wrenninge"], ["--weights", "--ms network"]),
    (["--ms-resolution", "8", "--ms", "none"], ["--ms-resolution", "--ms network"]),
    (["--octaves", "4"], ["--octaves", "--ms wrenninge"]),          # default source: network
    (["--ms-lattice", "g.npz", "--ms", "network"], ["--ms-lattice", "--ms lattice"]),
    (["--max-order", "2"], ["--max-order 2", "raymarch"]),
    (["--max-order", "1", "--ms", "network"], ["--max-order 1", "--ms network"]),
    (["--method", "pathtrace", "--ms", "none"], ["--ms", "pathtrace"]),
    (["--method", "pathtrace", "--step", "2"], ["--step", "pathtrace"]),
])
def test_unused_options_exit_2_naming_option_and_method(scene_file, tmp_path, capsys, argv, names):
    code = main(["render", str(scene_file), "-o", str(tmp_path / "x.exr")] + argv)
    err = capsys.readouterr().err
    assert code == 2 and err.count("\n") == 1, err
    for n in names:
        assert n in err, (n, err)


def test_unused_options_refused_in_python():
    sc = small_scene()
    with pytest.raises(ClvolError, match=r"option spp \(--spp\) is not used by method 'raymarch'"):
        clvol.Renderer(sc, "raymarch", ms="none", spp=4)
    with pytest.raises(ClvolError, match=r"weights \(--weights\) is used only with --ms network or view or stochastic "):
        clvol.Renderer(sc, ms="none", weights="x.npz")
    with pytest.raises(ClvolError, match="unknown render option 'no_such'"):
        clvol.Renderer(sc, no_such=1)
    with pytest.raises(ClvolError, match="expected a clvol.scene.Camera"):
        clvol.Renderer(sc, ms="none").render(camera=(0, 0, 1))


def test_max_order_1_is_single_scattering_for_every_method():
    sc = small_scene()
    a = clvol.Renderer(sc, max_order=1).render()
    b = clvol.Renderer(sc, ms="none").render()
    assert a.header["raymarch.ms"] == "none"
    np.testing.assert_array_equal(a.total, b.total)
    assert a.multiple.max() == 0
    pt = clvol.Renderer(sc, "pathtrace", max_order=1, spp=2).render()
    assert pt.multiple.max() == 0 and pt.single.max() > 0


@pytest.mark.parametrize("ms,opts", [("none", {}), ("wrenninge", {"step": 0.5, "octaves": 3})])
def test_march_with_is_the_renderers_frame(ms, opts):
    """RayMarcher.march_with (the benchmarks' short form) plans as the Renderer does: a plan
    without the volume's facts marched in world-unit steps and drew other images."""
    from clvol.render.raymarch import RayMarcher
    sc = small_scene()
    ren = clvol.Renderer(sc, ms=ms, **opts)
    want = ren.render()
    rm = RayMarcher(sc.volume.load(), sc.medium, get_runtime())
    layers, plan = rm.march_with(sc.camera, sc.light, ms, **opts)
    assert plan.step == pytest.approx(float(ren.plan().step))
    for k in ("total", "single", "multiple", "alpha"):
        np.testing.assert_array_equal(layers[k], want.layers[k], err_msg=k)


def _fresh(scene, camera=None, light=None, medium=None, **opts):
    sc = dataclasses.replace(scene, camera=camera or scene.camera, light=light or scene.light,
                             medium=medium or scene.medium)
    return clvol.Renderer(sc, **opts).render()


def test_renderer_recomputes_only_what_a_change_invalidates():
    """Counts per stage after each kind of change, and every image bit-identical to a fresh
    Renderer's on the changed scene (kept state is never stale)."""
    sc = small_scene()
    opts = dict(ms_resolution=8)
    r = clvol.Renderer(sc, **opts)

    def step(expect, **change):
        before = dict(r.counts)
        img = r.render(**change)
        diff = {k: r.counts[k] - before.get(k, 0) for k in r.counts if r.counts[k] != before.get(k, 0)}
        assert diff == expect, (change.keys(), diff)
        np.testing.assert_array_equal(img.total, _fresh(sc, **change, **opts).total)
        return img

    # (the network's lattice is filled on the device: no "ms_upload", the grid source's stage)
    first = step({"volume": 1, "device_medium": 1, "network_setup": 1, "light_field": 1,
                  "graded_transmittance": 1, "ms_lattice": 1, "march": 1})
    step({"march": 1})                                                     # nothing changed
    turned = dataclasses.replace(sc.camera, target=(0.1, 0.0, 0.0))        # same position
    step({"march": 1}, camera=turned)
    moved = dataclasses.replace(sc.camera, origin=(0.6, 0.4, 2.1))
    step({"ms_lattice": 1, "march": 1}, camera=moved)
    lit = dataclasses.replace(sc.light, direction=(0.0, 1.0, 0.0))
    step({"light_field": 1, "graded_transmittance": 1, "ms_lattice": 1, "march": 1}, light=lit)
    brighter = dataclasses.replace(sc.light, irradiance=(2.0, 2.0, 2.0))
    img = step({"light_field": 1, "graded_transmittance": 1, "ms_lattice": 1, "march": 1},
               light=brighter)   # back to the scene's direction
    np.testing.assert_allclose(img.total, 2 * first.total, rtol=1e-6, atol=0)
    greyer = dataclasses.replace(sc.medium, albedo=(0.9, 0.9, 0.9))
    step({"ms_lattice": 1, "march": 1}, medium=greyer)
    denser = dataclasses.replace(sc.medium, density_scale=45.0)
    step({"light_field": 1, "graded_transmittance": 1, "ms_lattice": 1, "march": 1},
         medium=denser)
    r2 = clvol.Renderer(sc, ms="wrenninge")
    r2.render()
    r2.render(camera=moved)
    assert r2.counts == {"volume": 1, "device_medium": 1, "light_field": 1, "march": 2}


def test_outside_the_domain_warns_and_uses_the_measured_alternative(capsys):
    # albedo 0.2: below the shipped weights' albedo range (0.3-1), where no measurement
    # found an analytic source better: the network is kept, with the warning
    sc = small_scene(albedo=0.2)
    res = clvol.Renderer(sc, ms_resolution=8).render()
    err = capsys.readouterr().err
    assert err.count("clvol: warning: scene outside the network's training domain") == 1
    assert "albedo 0.2 outside [0.3, 1]" in err and "network is used all the same" in err
    assert "albedo 0.2" in res.header["warning"] and res.header["raymarch.ms"] == "network"
    # g = -0.5 and -0.9 are inside the default model's domain now: no warning, the network
    for g in (-0.5, -0.9):
        res = clvol.Renderer(small_scene(phase={"type": "hg", "g": g}), ms_resolution=8).render()
        assert "warning" not in res.header and res.header["raymarch.ms"] == "network"
        assert capsys.readouterr().err == ""
    # strongly backward beyond the domain (g -0.95 < -0.9): Wrenninge octaves at high albedo,
    # single scattering at lower albedo
    for albedo, alt in ((0.999, "wrenninge"), (0.6, "none")):
        sc = small_scene(albedo=albedo, phase={"type": "hg", "g": -0.95})
        r = clvol.Renderer(sc, ms_resolution=8)
        res = r.render()
        res2 = r.render()
        assert capsys.readouterr().err.count("warning") == 1       # once per Renderer and reason
        assert res.header["raymarch.ms"] == alt and f"--ms {alt} instead" in res.header["warning"]
        np.testing.assert_array_equal(res.total, clvol.Renderer(sc, ms=alt).render().total)
        np.testing.assert_array_equal(res.total, res2.total)
        assert "network_setup" not in r.counts
        kept = clvol.Renderer(sc, ms_resolution=8, domain_fallback=False).render()
        assert kept.header["raymarch.ms"] == "network" and "warning" in kept.header
        capsys.readouterr()
    inside = clvol.Renderer(small_scene(), ms_resolution=8).render()
    assert "warning" not in inside.header and capsys.readouterr().err == ""


def test_albedo_zero_runs_no_network_and_equals_the_general_path():
    sc = small_scene(albedo=[0.0, 0.0, 0.0])
    sc = dataclasses.replace(sc, light=dataclasses.replace(sc.light, environment=(0.2, 0.3, 0.4)))
    r = clvol.Renderer(sc, ms_resolution=8)
    fast = r.render()
    assert "network_setup" not in r.counts and "light_field" not in r.counts
    general = clvol.Renderer(sc, ms_resolution=8, shortcuts=False).render()
    np.testing.assert_array_equal(fast.total, general.total)
    assert fast.alpha.max() > 0.5 and fast.single.max() == 0 and fast.multiple.max() == 0


def test_view_independent_cache_fills_once_per_light():
    """--ms-directions K: K fills per light and medium, then camera positions cost a blend
    (no network evaluation); the blend is a convex combination of the K directions' values."""
    sc = small_scene()
    r = clvol.Renderer(sc, ms_resolution=8, ms_directions=6)
    r.render()
    assert r.counts["ms_directional_fill"] == 1
    table = r.source._table[1]                          # (K, gz, gy, gx)
    moved = dataclasses.replace(sc.camera, origin=(-1.0, 0.8, 1.5))
    img = r.render(camera=moved)
    assert r.counts["ms_directional_fill"] == 1 and r.counts["ms_lattice"] == 2
    v = r.source.ms_lattice.values
    assert np.all(v >= table.min(axis=0) * (1 - 1e-6)) and np.all(v <= table.max(axis=0) * (1 + 1e-6))
    assert np.all(np.isfinite(img.total)) and img.multiple.max() > 0
    r.render(light=dataclasses.replace(sc.light, direction=(0.0, 1.0, 0.0)))
    assert r.counts["ms_directional_fill"] == 2
    with pytest.raises(ClvolError, match="ms_directions = 3"):
        clvol.Renderer(sc, ms_directions=3)


def test_progressive_refresh_converges_to_the_full_lattice():
    """--ms-refresh K: a camera move refills one of K interleaved subsets per frame; at rest the
    others follow, and after K frames the image is bit-identical to a full refill's."""
    sc = small_scene()
    moved = dataclasses.replace(sc.camera, origin=(0.9, 0.5, 1.9))
    r = clvol.Renderer(sc, ms_resolution=8, ms_refresh=3)
    r.render()
    full_points = r.source.info["points"]
    first = r.render(camera=moved)
    assert r.source.info["points"] < full_points / 2          # one subset of the active points
    want = _fresh(sc, camera=moved, ms_resolution=8).total
    assert not np.array_equal(first.total, want)              # two subsets still stale
    r.render(camera=moved)
    last = r.render(camera=moved)
    np.testing.assert_array_equal(last.total, want)
    n = r.counts["ms_lattice"]
    r.render(camera=moved)
    assert r.counts["ms_lattice"] == n                        # converged: nothing left to refill


def test_optically_thin_media_skip_the_network():
    """Largest optical thickness < 0.5: single scattering only (measured at least as accurate
    as the network there, docs/raymarch.md); the image is the --ms none image, no network is
    set up; --no-shortcuts runs the network."""
    from clvol.volume.stats import volume_stats
    sc = small_scene()
    tau1 = volume_stats(sc.volume.load(), 1.0)["max_optical_thickness"]
    thin = small_scene(density_scale=0.3 / tau1)
    r = clvol.Renderer(thin, ms_resolution=8)
    res = r.render()
    assert "network_setup" not in r.counts and "optically thin" in res.header["skipped"]
    np.testing.assert_array_equal(res.total, clvol.Renderer(thin, ms="none").render().total)
    general = clvol.Renderer(thin, ms_resolution=8, shortcuts=False)
    assert general.render().multiple.max() > 0 and general.counts["network_setup"] == 1
    thick = clvol.Renderer(small_scene(density_scale=0.6 / tau1), ms_resolution=8)
    thick.render()
    assert thick.counts["network_setup"] == 1


def test_per_frame_seed_is_path_tracer_only_and_reproducible():
    import dataclasses
    import clvol
    from clvol.errors import ClvolError
    scene = clvol.load_scene(Path(__file__).parent / "data" / "scenes" / "milk.toml")
    scene = dataclasses.replace(scene, camera=dataclasses.replace(scene.camera, width=12, height=12))
    pt = clvol.Renderer(scene, method="pathtrace", spp=2, seed=0)
    a, b = pt.render(seed=5).total, pt.render(seed=6).total
    assert np.array_equal(a, pt.render(seed=5).total) and not np.array_equal(a, b)
    # The seed option of the constructor is the default of render().
    assert np.array_equal(clvol.Renderer(scene, method="pathtrace", spp=2, seed=5).render().total, a)
    with pytest.raises(ClvolError, match="takes its seed as an option"):
        clvol.Renderer(scene).render(seed=1)
    with pytest.raises(ClvolError, match="seed"):
        pt.render(seed=-1)
    # Every frame read the one volume uploaded at the first.
    assert pt.counts["device_medium"] == 1 and pt.counts["pathtrace"] == 3


def test_missing_layer_names_the_method_and_the_layers_it_has():
    from clvol.render import RenderResult
    res = RenderResult({"total": np.zeros((2, 2, 3))}, {"method": "pathtrace"})
    assert res.total.shape == (2, 2, 3)
    with pytest.raises(ClvolError, match=r"pathtrace made no 'alpha' layer; it has total"):
        res.alpha


def test_public_names_are_listed_and_misspelled_options_get_a_suggestion():
    assert {"Renderer", "RenderResult", "load_scene"} <= set(dir(clvol))
    with pytest.raises(ClvolError, match=r"unknown render option 'stpe': did you mean 'step'\?"):
        clvol.Renderer(clvol.load_scene(DATA.parents[1] / "examples" / "cloud.toml"), stpe=2)


def test_renderer_dispatches_every_method_through_its_table():
    """The Renderer's method table and the CLI's METHODS name the same methods, and a name
    outside the table is refused in one line before any device work."""
    from clvol.render import METHODS
    from clvol.render.renderer import Renderer
    assert set(Renderer._METHODS) == set(METHODS)
    for setup, frame, supersample in Renderer._METHODS.values():
        for attr in (frame, supersample) + ((setup,) if setup else ()):
            assert callable(getattr(Renderer, attr))
    from clvol.errors import ClvolError
    with pytest.raises(ClvolError, match="splat"):
        Renderer(clvol.load_scene(Path(__file__).parents[1] / "examples" / "cloud.toml"), "splat")
