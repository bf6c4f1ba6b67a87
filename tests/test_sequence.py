"""Volume sequences and density updates (issue 28): ``Renderer.set_density`` recomputes only
what a new density invalidates, ``clvol render --frames`` writes one EXR per frame, reads the
next frame on a second thread, and stops at a missing frame with exit 2 keeping what it wrote."""
from __future__ import annotations

import numpy as np
import pytest

import clvol
from clvol.cli import main
from clvol.errors import ClvolError
from clvol.image import read_exr
from clvol.scene import load_scene
from clvol.sequence import check_output_pattern, parse_frames
from clvol.volume.generators import generate
from clvol.volume.grid import DensityGrid
from scene_toml import scene_toml


def _frames(tmp_path, n=3, emission=True, size=12):
    """n frames of a small cloud-like blob that drifts, with a temperature grid."""
    for f in range(1, n + 1):
        g = generate("cloud", seed=f, resolution=size)
        arrays = {"density": g.density, "bbox_min": g.bbox_min, "bbox_max": g.bbox_max}
        if emission:
            arrays["temperature"] = (900.0 + 2500.0 * g.density / max(g.density.max(), 1e-6)
                                     ).astype(np.float32)
        np.savez(tmp_path / f"fire_{f:04d}.npz", **arrays)
    em = ({"grid": "temperature", "kind": "blackbody", "scale": 40.0} if emission else None)
    text = scene_toml({"file": "fire_{frame:04d}.npz", "frame": 1},
                      {"density_scale": 20.0, "albedo": 0.7, "phase": {"type": "hg", "g": 0.4}},
                      {"direction": [0.3, 0.9, 0.2]},
                      {"origin": [0.3, 0.2, 2.4], "target": [0.0, 0.0, 0.0], "fov_y": 35.0,
                       "width": 12, "height": 10}, em)
    (tmp_path / "fire.toml").write_text(text)
    return tmp_path / "fire.toml"


def test_parse_frames_and_output_pattern():
    assert parse_frames("1-4") == [1, 2, 3, 4]
    assert parse_frames("1,5,9") == [1, 5, 9]
    assert parse_frames("0-2,7") == [0, 1, 2, 7]
    for bad in ("", "a", "5-2", "1,1", "-3", "1.5"):
        with pytest.raises(ClvolError):
            parse_frames(bad)
    check_output_pattern("o_{frame:03d}.exr", [1, 2])
    check_output_pattern("o.exr", [1])
    with pytest.raises(ClvolError, match="would write one file"):
        check_output_pattern("o.exr", [1, 2])


def test_scene_sequence_fields(tmp_path):
    sc = load_scene(_frames(tmp_path, 2))
    assert sc.volume.is_sequence and sc.volume.frame == 1
    assert sc.volume.frame_file(2).name == "fire_0002.npz"
    assert sc.emission.kind == "blackbody" and sc.emission.grid == "temperature"
    again = clvol.scene.scene_from_dict(sc.to_dict(), base_dir=tmp_path)
    assert again.emission == sc.emission and again.volume.frame == 1
    bad = (tmp_path / "fire.toml").read_text().replace("frame = 1", "frame = 9")
    (tmp_path / "bad.toml").write_text(bad)
    with pytest.raises(ClvolError, match="fire_0009.npz"):
        load_scene(tmp_path / "bad.toml")


def _fresh(sc, grid, emission=None, **opts):
    return clvol.Renderer(sc, grid=grid, **opts).render(
        **({} if emission is None else {"grid": grid, "emission": emission}))


def test_set_density_recomputes_only_what_the_density_invalidates(tmp_path):
    """Counts per stage after a new density, and the image bit-identical to a fresh
    Renderer's on that density (no stale state)."""
    sc = load_scene(_frames(tmp_path, 2, emission=False))
    g1 = sc.volume.load()
    g2 = sc.volume.for_frame(2).load()
    r = clvol.Renderer(sc, ms_resolution=8)
    r.render()
    before = dict(r.counts)
    img = r.render(grid=g2)
    diff = {k: r.counts[k] - before.get(k, 0) for k in r.counts if r.counts[k] != before.get(k, 0)}
    assert diff == {"device_medium": 1, "network_pyramid": 1, "light_field": 1,
                    "graded_transmittance": 1, "ms_lattice": 1, "march": 1}
    np.testing.assert_array_equal(img.total, clvol.Renderer(sc, grid=g2, ms_resolution=8)
                                  .render().total)
    back = r.render(grid=g1)
    np.testing.assert_array_equal(back.total, clvol.Renderer(sc, grid=g1, ms_resolution=8)
                                  .render().total)
    # the analytic source: only the density's own stages
    r2 = clvol.Renderer(sc, ms="wrenninge")
    r2.render()
    r2.set_density(g2)
    r2.render()
    assert r2.counts == {"volume": 1, "device_medium": 2, "light_field": 2, "march": 2}
    with pytest.raises(ClvolError, match="expected a clvol.volume.grid.DensityGrid"):
        r2.set_density(g2.density)


def test_set_density_with_emission_and_the_path_tracer(tmp_path):
    sc = load_scene(_frames(tmp_path, 2))
    v2 = sc.volume.for_frame(2)
    g2 = v2.load()
    e2 = sc.emission.load(v2, g2)
    r = clvol.Renderer(sc, ms="none")
    first = r.render()
    assert r.counts["emission"] == 1 and first.layers["emission"].max() > 0
    with pytest.raises(ClvolError, match="emission grid too"):
        r.set_density(g2)
    img = r.render(grid=g2, emission=e2)
    assert r.counts["emission_upload"] == 2 and r.counts["emission"] == 1
    fresh = clvol.Renderer(sc, ms="none").render(grid=g2, emission=e2)
    np.testing.assert_array_equal(img.total, fresh.total)
    assert not np.array_equal(img.total, first.total)
    pt = clvol.Renderer(sc, "pathtrace", spp=2)
    a = pt.render(grid=g2, emission=e2)
    assert {"emission", "emission_scattered"} <= set(a.layers)
    assert pt.counts["device_medium"] == 1


def test_cli_frames_write_one_exr_each_and_stop_at_a_missing_frame(tmp_path, capsys):
    path = _frames(tmp_path, 3)
    out = str(tmp_path / "out_{frame:03d}.exr")
    code = main(["render", str(path), "--ms", "none", "--frames", "1-3", "-o", out, "--quiet"])
    err = capsys.readouterr().err
    assert code == 0 and "wrote 3 frames" in err, err
    imgs = [read_exr(tmp_path / f"out_{f:03d}.exr") for f in (1, 2, 3)]
    assert all(i.header.get("frame") in (str(f), f) for i, f in zip(imgs, (1, 2, 3)))
    assert not np.array_equal(imgs[0].rgb, imgs[1].rgb)
    single = clvol.Renderer(load_scene(path), ms="none").render()   # frame = 1 in the scene
    np.testing.assert_array_equal(imgs[0].rgb, single.total)
    # frame 4 is missing: 2 and 3 are written again, then exit 2 naming the missing file
    for f in (2, 3):
        (tmp_path / f"out_{f:03d}.exr").unlink()
    code = main(["render", str(path), "--ms", "none", "--frames", "2-5", "-o", out, "--quiet"])
    err = capsys.readouterr().err
    assert code == 2 and "fire_0004.npz" in err and err.count("\n") == 1, err
    assert (tmp_path / "out_002.exr").exists() and (tmp_path / "out_003.exr").exists()
    assert not (tmp_path / "out_004.exr").exists()
    code = main(["render", str(path), "--frames", "1,2", "-o", str(tmp_path / "x.exr")])
    assert code == 2 and "would write one file" in capsys.readouterr().err


def test_bundle_refuses_emission_in_one_line(tmp_path, capsys):
    path = _frames(tmp_path, 1)
    code = main(["bundle", str(path), str(tmp_path / "b")])
    err = capsys.readouterr().err
    assert code == 2 and "no emission" in err and err.count("\n") == 1, err


def test_viewer_plays_a_sequence(tmp_path):
    """The viewer's frame field switches the volume (clvol/viewer/server.py FrameMaker):
    frames differ, returning to a frame gives its image again bit for bit (no stale state),
    a frame not in the sequence is refused by name."""
    from clvol.viewer.server import FrameMaker
    from clvol.viewer.state import ViewState
    sc = load_scene(_frames(tmp_path, 3))
    maker = FrameMaker(sc)
    try:
        assert maker.frames == [1, 2, 3]
        s = ViewState.from_scene(sc).update({"method": "single", "resolution": 64})
        assert s.frame == 1
        a = maker.render(s.update({"frame": 2}), None)
        b = maker.render(s.update({"frame": 3}), a)
        c = maker.render(s.update({"frame": 2}), b)
        np.testing.assert_array_equal(a.layers["total"], c.layers["total"])
        assert not np.array_equal(a.layers["total"], b.layers["total"])
        with pytest.raises(ClvolError, match="frame 9: not in the sequence"):
            maker.render(s.update({"frame": 9}), c)
        with pytest.raises(Exception, match="frame"):
            s.update({"frame": "two"})
    finally:
        maker.close()
