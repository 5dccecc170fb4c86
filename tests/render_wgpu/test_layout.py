"""One definition of the shaders' uniform blocks (wgpu_tier/layout.py): the WGSL structs the
shaders declare and the numpy offsets the Python side writes agree, checked on the GPU; and
the package ships its .wgsl files (also inside a built wheel)."""
from __future__ import annotations

import re
import subprocess
import sys
import zipfile
from pathlib import Path

import numpy as np
import pytest

from gpu_util import require_adapter

from pointflow.render.wgpu_tier import layout, sources

ROOT = Path(__file__).resolve().parents[2]


def _reads(table) -> list[str]:
    """WGSL expressions of every 32-bit word of the struct ``U``, in field order."""
    out = []
    for name, wt in table:
        if wt == "mat4x4<f32>":
            out += [f"U.{name}[{c}][{r}]" for c in range(4) for r in range(4)]
        elif wt.startswith("array<vec4"):
            n = int(re.search(r", (\d+)>", wt).group(1))
            out += [f"U.{name}[{i}][{j}]" for i in range(n) for j in range(4)]
        elif wt.startswith("vec"):
            out += [f"U.{name}[{j}]" for j in range(int(wt[3]))]
        else:
            out.append(f"U.{name}")
    return out


def _element_offsets(dt: np.dtype) -> list[int]:
    """Byte offset of every 32-bit element, in field order, by the numpy dtype."""
    out = []
    for name in dt.names:
        sub, off = dt.fields[name][:2]
        out += [off + 4 * k for k in range(max(1, int(np.prod(sub.shape, dtype=int))))]
    return out


@pytest.mark.parametrize("struct,table,dt", [("Params", layout.PARAMS, layout.PARAMS_DTYPE),
                                             ("CParams", layout.CPARAMS, layout.CPARAMS_DTYPE)])
def test_wgsl_struct_reads_every_field_where_numpy_wrote_it(struct, table, dt):
    adapter = require_adapter()
    dev = adapter.request_device_sync()
    wgpu = sys.modules["wgpu"]
    reads = _reads(table)
    offs = _element_offsets(dt)
    assert len(reads) == len(offs)
    # every word of the record gets a distinct value; the shader copies each field's words out
    raw = np.arange(1, dt.itemsize // 4 + 1, dtype=np.uint32) * np.uint32(2654435761)
    body = "\n".join(f"  o[{i}] = bitcast<u32>({e});" for i, e in enumerate(reads))
    code = (layout.wgsl_header() + f"@group(0) @binding(0) var<uniform> U: {struct};\n"
            "@group(0) @binding(1) var<storage, read_write> o: array<u32>;\n"
            f"@compute @workgroup_size(1) fn main() {{\n{body}\n}}\n")
    BU = wgpu.BufferUsage
    ubo = dev.create_buffer_with_data(data=raw.tobytes(), usage=BU.UNIFORM)
    out = dev.create_buffer(size=4 * len(reads), usage=BU.STORAGE | BU.COPY_SRC)
    pipe = dev.create_compute_pipeline(layout="auto", compute={"module": dev.create_shader_module(code=code),
                                                               "entry_point": "main"})
    bg = dev.create_bind_group(layout=pipe.get_bind_group_layout(0), entries=[
        {"binding": 0, "resource": {"buffer": ubo}}, {"binding": 1, "resource": {"buffer": out}}])
    enc = dev.create_command_encoder()
    cp = enc.begin_compute_pass()
    cp.set_pipeline(pipe)
    cp.set_bind_group(0, bg)
    cp.dispatch_workgroups(1)
    cp.end()
    dev.queue.submit([enc.finish()])
    got = np.frombuffer(dev.queue.read_buffer(out), np.uint32)
    want = raw[np.asarray(offs) // 4]
    bad = [reads[i] for i in np.flatnonzero(got != want)]
    assert not bad, f"WGSL reads these fields at other offsets than numpy writes: {bad[:8]}"
    assert dt.itemsize % 16 == 0 and raw.nbytes == dt.itemsize
    dev.destroy()


def test_flags_and_constants_come_from_the_one_definition():
    src = sources.source("common.wgsl", "scan.wgsl", "cull.wgsl")
    for f in layout.Flag:
        assert f"const F_{f.name}: u32 = {int(f.value)}u;" in src
    assert re.search(r"struct Params \{", src) and "head: u32," in src
    # no shader file declares its own copy of a generated struct or constant
    for name in sources.names():
        text = sources.read(name)
        assert "struct Params" not in text and "struct CParams" not in text, name
        assert not re.search(r"const (F|C|S)_[A-Z_]+\s*:", text), name


def test_package_ships_its_wgsl_files():
    names = sources.names()
    assert {"common.wgsl", "cull.wgsl", "draw.wgsl", "raster.wgsl", "resolve.wgsl"} <= set(names)
    on_disk = sorted(p.name for p in (ROOT / "pointflow" / "render" / "wgpu_tier" / "wgsl").glob("*.wgsl"))
    assert names == on_disk


def test_built_wheel_contains_the_wgsl_files_and_calibration(tmp_path):
    r = subprocess.run([sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation", "-q",
                        "-w", str(tmp_path), str(ROOT)], capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr[-2000:]
    wheel = next(tmp_path.glob("pointflow-*.whl"))
    files = set(zipfile.ZipFile(wheel).namelist())
    for name in sources.names():
        assert f"pointflow/render/wgpu_tier/wgsl/{name}" in files, name
    assert "pointflow/render/calibration/raster_crossover.json" in files
    assert "pointflow/render/calibration/crossover.json" in files
