"""Tier selection while the compiled raster's loops are not cached: the compiled method is
skipped (never waited for), the next tiers draw in the MEANWHILE order (env
POINTFLOW_RASTER_MEANWHILE), and the renderer carries ``compiled_pending`` for the render
stage to compile and switch. The cache's state is set here, not made: the real empty cache
runs in test_compile_beside.py. No timing, so load changes nothing."""
from __future__ import annotations

import pytest

from pointflow.render import cpu_kernels, select
from pointflow.render.config import RenderConfig

pytest.importorskip("numba")


def _cfg(**kw) -> RenderConfig:
    return RenderConfig(size=[32, 18], **kw)


@pytest.mark.parametrize("state", ["missing", "unwritable"])
def test_explicit_compute_draws_with_the_reference_meanwhile(monkeypatch, state):
    monkeypatch.setattr(cpu_kernels, "cache_state", lambda: state)
    r, lines = select.select_renderer(_cfg(backend="cpu", raster="compute"), 100, ["intensity"])
    assert r.tier == "cpu" and getattr(r, "raster", None) != "compute"
    assert r.compiled_pending == state
    assert any(line.startswith("cpu-compute: not yet") for line in lines)


def test_meanwhile_order_is_taken_from_the_environment(monkeypatch):
    monkeypatch.setattr(cpu_kernels, "cache_state", lambda: "missing")
    monkeypatch.setenv(select.ENV_MEANWHILE, "cpu")
    tiers = []
    r = select._try(["cpu-compute", "wgpu", "gl", "cpu"], _cfg(), 100, ["intensity"], tiers)
    assert r.tier == "cpu" and r.compiled_pending == "missing"


def test_a_cached_raster_is_taken_at_once(monkeypatch):
    monkeypatch.setattr(cpu_kernels, "cache_state", lambda: "ready")
    r, _ = select.select_renderer(_cfg(backend="cpu", raster="compute"), 100, ["intensity"])
    assert getattr(r, "raster", None) == "compute" and r.compiled_pending is None
