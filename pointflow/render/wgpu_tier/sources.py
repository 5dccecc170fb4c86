"""WGSL sources of the wgpu tier: ``.wgsl`` files shipped inside the package (``wgsl/``).

How a shader is put together (the one documented template step): :func:`source` prepends the
structs and constants generated from :mod:`.layout` (one definition for Python and WGSL) to
the concatenation of the named files, e.g. ``common.wgsl`` + ``scan.wgsl`` + ``cull.wgsl``.
Variants that change *which code runs* (colour mode, shape, size space, which per-point tests
are on) are WGSL ``override`` constants given when a pipeline is created, so one file holds
every variant; variants that change *declarations* (the 64-bit or 32-bit key buffer, whose
``atomic<u64>`` must not appear at all without the feature) are separate small files chosen
by name. No string substitution inside a file.
"""
from __future__ import annotations

import functools
from importlib import resources

from . import layout

DIR = "wgsl"


@functools.lru_cache(maxsize=None)
def read(name: str) -> str:
    """The text of ``wgsl/<name>`` (works from a wheel or a zip, via importlib.resources)."""
    return resources.files(__package__).joinpath(DIR, name).read_text(encoding="utf-8")


def names() -> list[str]:
    """Every ``.wgsl`` file the package ships."""
    return sorted(p.name for p in resources.files(__package__).joinpath(DIR).iterdir() if p.name.endswith(".wgsl"))


@functools.lru_cache(maxsize=None)
def source(*files: str) -> str:
    """Generated header + the files in order (WGSL declarations are order-independent)."""
    return layout.wgsl_header() + "".join(f"// ---- {f}\n" + read(f) for f in files)


def constants(**kw: object) -> dict[str, float]:
    """Pipeline-overridable constants as wgpu takes them (bools as 0/1)."""
    return {k: float(int(v)) if isinstance(v, bool) else float(v) for k, v in kw.items()}  # type: ignore[arg-type]
