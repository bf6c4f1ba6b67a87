"""The OpenCL runtime: device choice, build errors, program cache, padding, profiling."""
import numpy as np
import pytest

from clvol import runtime
from clvol.errors import BuildError, DeviceError


def test_padded_sizes():
    assert runtime.padded(1) == 64 and runtime.padded(64) == 64 and runtime.padded(65) == 128
    assert runtime.padded(0) == 64 and runtime.padded(7, 16) == 16


def test_default_choice_prefers_gpu_then_cpu(monkeypatch):
    monkeypatch.delenv("CLVOL_DEVICE", raising=False)
    monkeypatch.delenv("PYOPENCL_CTX", raising=False)
    entries = runtime.list_devices()
    entry, why = runtime.choose_device()
    kinds = [e.kind for e in entries]
    expect = "gpu" if "gpu" in kinds else "cpu" if "cpu" in kinds else entries[0].kind
    assert entry.kind == expect and why.startswith("default")


def test_default_choice_takes_mesas_clover_last(monkeypatch):
    """Mesa's Clover (installed beside rusticl by mesa-opencl-icd) exposes AMD/Intel GPUs: the
    default takes another platform's GPU first, whichever order the loader lists them in, and
    Clover's only where no other platform has a device of that type; --device still picks it."""
    from types import SimpleNamespace as NS
    import pyopencl as cl
    monkeypatch.delenv("CLVOL_DEVICE", raising=False)
    monkeypatch.delenv("PYOPENCL_CTX", raising=False)

    def entries(*plats):
        return [runtime.DeviceEntry(i, 0, NS(name=name), NS(type=t, name=f"dev{i}"))
                for i, (name, t) in enumerate(plats)]

    gpu, cpu = cl.device_type.GPU, cl.device_type.CPU
    for plats, want in [((("Clover", gpu), ("AMD Accelerated Parallel Processing", gpu)), 1),
                        ((("AMD Accelerated Parallel Processing", gpu), ("Clover", gpu)), 0),
                        ((("Clover", gpu), ("Portable Computing Language", cpu)), 0),
                        ((("Clover", cpu), ("rusticl", cpu), ("Portable Computing Language", cpu)), 1)]:
        es = entries(*plats)
        monkeypatch.setattr(runtime, "list_devices", lambda es=es: es)
        entry, why = runtime.choose_device()
        assert entry.platform_index == want, (plats, why)
        assert why.startswith("default") and ("DEFAULT_LAST" in why) == (want != 0), why
    assert runtime.choose_device("clover")[0].platform_index == 0
    assert runtime.default_last("Clover") and not runtime.default_last("rusticl")


def test_explicit_spec_and_env_precedence(monkeypatch):
    first = runtime.list_devices()[0]
    monkeypatch.setenv("PYOPENCL_CTX", "no-such-device")
    monkeypatch.setenv("CLVOL_DEVICE", first.spec)
    entry, why = runtime.choose_device()
    assert entry.spec == first.spec and why.startswith("CLVOL_DEVICE")  # CLVOL_DEVICE beats PYOPENCL_CTX
    entry, why = runtime.choose_device(first.device.name[:6])  # the argument beats both
    assert why.startswith("--device")
    monkeypatch.delenv("CLVOL_DEVICE")
    with pytest.raises(DeviceError, match="PYOPENCL_CTX='no-such-device' matches no OpenCL device"):
        runtime.choose_device()


def test_bad_device_spec_lists_devices():
    with pytest.raises(DeviceError, match=r"--device='9:9' matches no OpenCL device.*Devices: 0:0"):
        runtime.choose_device("9:9")


def test_describe_devices_marks_the_chosen_one():
    text = runtime.describe_devices()
    assert "chosen: " in text and " * " in text


def test_build_error_names_file_and_carries_log(tmp_path, monkeypatch):
    (tmp_path / "include").mkdir()
    (tmp_path / "broken.cl").write_text("__kernel void k(__global float *x) { x[0] = y; }\n")
    monkeypatch.setattr(runtime, "cl_source_dir", lambda: tmp_path)
    rt = runtime.Runtime()
    with pytest.raises(BuildError) as exc:
        rt.program("broken")
    msg = str(exc.value)
    assert "broken.cl failed to build" in msg and "y" in msg and "undeclared" in msg.lower()
    line = exc.value.one_line()     # what clvol info --check prints: one line, kernel + error
    assert "\n" not in line and line.startswith("broken.cl failed to build on ")
    assert "error" in line.lower() and "undeclared" in line.lower()
    with pytest.raises(BuildError, match="no OpenCL source"):
        rt.program("missing")


def test_program_cache_and_defines(tmp_path, monkeypatch):
    (tmp_path / "include").mkdir()
    (tmp_path / "include" / "val.h").write_text("#define BASE 1.0f\n")
    (tmp_path / "fill.cl").write_text(
        '#include "val.h"\n__kernel void fill(__global float *x, const int n) {\n'
        "  int i = get_global_id(0); if (i < n) x[i] = BASE + EXTRA; }\n")
    monkeypatch.setattr(runtime, "cl_source_dir", lambda: tmp_path)
    rt = runtime.Runtime(profiling=True)
    p1 = rt.program("fill", defines={"EXTRA": 2.5})
    assert rt.program("fill", defines={"EXTRA": 2.5}) is p1          # cached
    assert p1.kernel("fill", [None, np.int32]) is p1.kernel("fill")  # kernel objects reused
    p2 = rt.program("fill", defines={"EXTRA": 0.5})
    assert p2 is not p1
    out = rt.empty(7)
    rt.launch(p2.kernel("fill", [None, np.int32]), 7, (out, np.int32(7)))  # padded to 64, guarded
    np.testing.assert_array_equal(rt.from_device(out, (7,)), 1.5)
    # Editing a header changes the source hash, so the stale program is not served.
    (tmp_path / "include" / "val.h").write_text("#define BASE 10.0f\n")
    p3 = rt.program("fill", defines={"EXTRA": 0.5})
    assert p3 is not p2
    rt.launch(p3.kernel("fill", [None, np.int32]), 7, (out, np.int32(7)))
    np.testing.assert_array_equal(rt.from_device(out, (7,)), 10.5)
    report = rt.timing_report()
    assert "fill" in report and rt.kernel_launches["fill"] == 2 and rt.kernel_seconds["fill"] > 0


def test_zero_size_buffers_are_allowed():
    rt = runtime.get_runtime()
    buf = rt.to_device(np.zeros(0, np.float32))
    assert buf.size >= 4
    assert rt.from_device(buf, (0,)).shape == (0,)


def test_transfers_are_counted_by_direction_label_and_size():
    rt = runtime.get_runtime()
    before = rt.transfers.copy()
    a = rt.upload(np.arange(6, dtype=np.float32).reshape(2, 3), label="test-up")
    b = rt.alloc(8)
    rt.write(b, np.ones(5, np.float32), offset=2, label="test-write")
    rt.copy(b, a, nbytes=8)                       # device to device: not a transfer
    got = b.read(label="test-down")
    t = rt.transfers.since(before)
    assert got.tolist()[:2] == [0.0, 1.0] and got.tolist()[2:7] == [1.0] * 5
    assert t.count == {("upload", "test-up"): 1, ("upload", "test-write"): 1,
                       ("readback", "test-down"): 1}
    assert t.nbytes("upload") == 24 + 20 and t.nbytes("readback") == 32
    assert t.sizes[("upload", 24)] == 1 and t.calls("readback") == 1
    # unlabelled transfers carry the calling function's name
    rt.from_device(a, (2, 3))
    assert rt.transfers.since(before).count[("readback", f"{__name__}."
                                             "test_transfers_are_counted_by_direction_label_and_size")] == 1
    assert a.nbytes == 24 and a.reshape(3, 2).shape == (3, 2)
