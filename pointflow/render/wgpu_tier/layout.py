"""One definition of the uniform blocks the wgpu shaders read, and of their flag words.

Each block is a table of (field, WGSL type); from it come both the numpy dtype the Python
side fills (offsets by the WGSL uniform layout rules: scalars 4-byte aligned, vec4/mat4x4
and arrays of vec4 16-byte aligned, struct size a multiple of its largest alignment) and the
WGSL ``struct`` text that :mod:`.wgsl` prepends to every shader. So the two cannot drift;
``tests/render_wgpu/test_layout.py`` checks on the GPU that a shader reads every field at the
offset numpy wrote it to.
"""
from __future__ import annotations

import enum

import numpy as np

#: WGSL type -> (numpy shape, base dtype, alignment in bytes)
_TYPES = {
    "f32": ((), "<f4", 4),
    "u32": ((), "<u4", 4),
    "i32": ((), "<i4", 4),
    "vec2<f32>": ((2,), "<f4", 8),
    "vec4<f32>": ((4,), "<f4", 16),
    "vec4<u32>": ((4,), "<u4", 16),
    "mat4x4<f32>": ((16,), "<f4", 16),  # column-major, 16 floats
    "array<vec4<f32>, 6>": ((6, 4), "<f4", 16),
    "array<vec4<i32>, 4>": ((4, 4), "<i4", 16),
}

#: the per-frame parameters of every wgpu pass (shaders: ``P``), one record per segment of a
#: ring split over several buffers (head/size/capacity/n_slots then describe the segment in its
#: chunk's buffers; slot_base, logical_base and group_base place it in the whole ring)
PARAMS = (
    ("vp", "mat4x4<f32>"), ("model", "mat4x4<f32>"), ("planes", "array<vec4<f32>, 6>"),
    ("fixed_color", "vec4<f32>"),
    ("vw", "f32"), ("vh", "f32"), ("point_size", "f32"), ("size_scale", "f32"),
    ("now_hi", "f32"), ("now_lo", "f32"), ("window_ms", "f32"), ("imp_lo", "f32"),
    ("imp_scale", "f32"), ("range_lo", "f32"), ("range_scale", "f32"), ("range_hi", "f32"),
    ("head", "u32"), ("size", "u32"), ("capacity", "u32"), ("lod_stride", "u32"),
    ("seed", "u32"), ("flags", "u32"), ("budget", "u32"), ("color_mode", "u32"),
    ("budget_seed", "u32"), ("groups_x", "u32"), ("n_slots", "u32"), ("groups_total", "u32"),
    ("depth_scale", "f32"), ("slot_base", "u32"), ("logical_base", "u32"), ("group_base", "u32"),
)

#: the compute method's per-dispatch parameters (shaders: ``C``)
CPARAMS = (
    ("background", "u32"), ("groups_x", "u32"), ("budget_on", "u32"), ("first_group", "u32"),
    ("pick_x0", "u32"), ("pick_y0", "u32"), ("pick_w", "u32"), ("pick_h", "u32"),
)

#: eye-dome lighting (shaders: ``E``): the 8 neighbour offsets of rules.edl_offsets as
#: (dx0, dy0, dx1, dy1), ... (dy counts rows downward), ``k = 300 * strength / 8``, the
#: output image's row pitch in pixels and its size
EDL = (
    ("offsets", "array<vec4<i32>, 4>"), ("k", "f32"), ("row_pitch", "u32"), ("width", "u32"), ("height", "u32"),
)


def _align(x: int, a: int) -> int:
    return (x + a - 1) // a * a


def dtype(table) -> np.dtype:
    """The numpy structured dtype with the WGSL uniform-layout offsets of ``table``."""
    names, formats, offsets = [], [], []
    off, big = 0, 4
    for name, wt in table:
        shape, base, al = _TYPES[wt]
        off = _align(off, al)
        names.append(name)
        formats.append((base, shape) if shape else base)
        offsets.append(off)
        off += int(np.prod(shape, dtype=int)) * 4 if shape else 4
        big = max(big, al)
    return np.dtype({"names": names, "formats": formats, "offsets": offsets, "itemsize": _align(off, big)})


def wgsl_struct(name: str, table) -> str:
    """The WGSL ``struct`` for ``table`` (fields in order; WGSL applies the same offsets)."""
    return f"struct {name} {{\n" + "".join(f"  {f}: {t},\n" for f, t in table) + "};\n"


class Flag(enum.IntFlag):
    """``Params.flags`` bits."""
    WINDOW = 1
    IMPORTANCE = 2
    IMP_DEGENERATE = 4
    WORLD_SIZE = 16
    ROUND = 32
    RANGE_AUTO = 64
    RANGE_DEGENERATE = 128
    COLOUR_IN_VS = 256
    BATCH_LOD = 512  #: footprint LOD: a slot is drawn iff ``slot & blod[slot >> 14] == 0``


class ColourMode(enum.IntEnum):
    """``Params.color_mode``."""
    FIXED = 0
    RGB = 1
    SCALAR = 2
    Z = 3
    TIME = 4


#: words of the 16-word state buffer (counters + indirect args) the shaders name
STATE_WORDS = {"S_COUNT1": 8, "S_COUNT2": 9, "S_NONFINITE": 12, "S_OCCUPIED": 13}
NO_BUDGET = 0xFFFFFFFF

PARAMS_DTYPE = dtype(PARAMS)
CPARAMS_DTYPE = dtype(CPARAMS)
EDL_DTYPE = dtype(EDL)


def wgsl_constants() -> str:
    """WGSL ``const`` declarations of the flags, colour modes and state words."""
    lines = [f"const F_{f.name}: u32 = {int(f.value)}u;" for f in Flag]
    lines += [f"const C_{m.name}: u32 = {int(m.value)}u;" for m in ColourMode]
    lines += [f"const {k}: u32 = {v}u;" for k, v in STATE_WORDS.items()]
    return "\n".join(lines) + "\n"


def wgsl_header() -> str:
    """Structs + constants every shader starts with."""
    return (wgsl_struct("Params", PARAMS) + wgsl_struct("CParams", CPARAMS) + wgsl_struct("EdlParams", EDL)
            + wgsl_constants())
