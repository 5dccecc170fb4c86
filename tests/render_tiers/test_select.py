"""Tier selection: env override, crossover, explained skips, runtime fallback."""
from __future__ import annotations

import json

import pytest

from pointflow.config import RenderConfig
from pointflow.render import select
from pointflow.render.base import Renderer, RenderError
from pointflow.render.cpu import CpuRenderer


class BrokenTier(Renderer):
    """A tier whose device cannot start (as a GPU tier without a driver)."""

    tier = "wgpu"

    def __init__(self, cfg, capacity, channels):
        raise RenderError("no adapter: vkCreateInstance failed")

    def render(self, frame, camera):  # pragma: no cover
        raise AssertionError

    def read_image(self):  # pragma: no cover
        raise AssertionError


@pytest.fixture(autouse=True)
def clean_env(monkeypatch, tmp_path):
    monkeypatch.delenv("POINTFLOW_BACKEND", raising=False)
    monkeypatch.delenv("POINTFLOW_CROSSOVER", raising=False)
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))


def cfg(**kw):
    kw.setdefault("size", [32, 24])
    return RenderConfig(**kw)


def test_env_override_beats_config(monkeypatch):
    monkeypatch.setenv("POINTFLOW_BACKEND", "cpu")
    r, lines = select.select_renderer(cfg(backend="gl"), 10**6, [])
    assert r.tier == "cpu"
    assert any("POINTFLOW_BACKEND=cpu overrides render.backend=gl" in l for l in lines)


def test_bad_env_value_is_a_clear_error(monkeypatch):
    monkeypatch.setenv("POINTFLOW_BACKEND", "vulkan")
    with pytest.raises(RenderError, match="POINTFLOW_BACKEND='vulkan'"):
        select.select_renderer(cfg(), 10, [])


def test_small_scene_goes_to_cpu_with_reason():
    r, lines = select.select_renderer(cfg(cpu_crossover_points=5000), 10**6, [], expected_points=4999)
    assert r.tier == "cpu"
    assert "4999 points < crossover 5000 (from render.cpu_crossover_points)" in lines[0]


def test_crossover_sources_in_order(monkeypatch, tmp_path):
    assert select.crossover_points(cfg())[1] in ("built-in default",) or "crossover.json" in select.crossover_points(cfg())[1]
    cache = select.cache_path()
    cache.parent.mkdir(parents=True)
    cache.write_text(json.dumps({"crossover_points": 1234}))
    assert select.crossover_points(cfg()) == (1234, str(cache))
    f = tmp_path / "x.json"
    f.write_text(json.dumps({"crossover_points": 77}))
    monkeypatch.setenv("POINTFLOW_CROSSOVER", str(f))
    assert select.crossover_points(cfg())[0] == 77
    monkeypatch.setenv("POINTFLOW_CROSSOVER", "42")
    assert select.crossover_points(cfg()) == (42, "$POINTFLOW_CROSSOVER")
    assert select.crossover_points(cfg(cpu_crossover_points=9)) == (9, "render.cpu_crossover_points")


def test_auto_logs_each_skip_and_falls_through(monkeypatch):
    monkeypatch.setitem(select.TIERS, "wgpu", f"{__name__}:BrokenTier")
    monkeypatch.setitem(select.TIERS, "gl", "pointflow.render.no_such_tier:GlRenderer")
    monkeypatch.setattr(select, "probe_adapter", lambda c: None)  # no software adapter to weigh
    r, lines = select.select_renderer(cfg(cpu_crossover_points=0), 1000, [])
    assert r.tier == "cpu"
    assert "wgpu: skipped: RenderError: no adapter: vkCreateInstance failed" in lines
    assert any(l.startswith("gl: skipped: not available (ModuleNotFoundError") for l in lines)
    assert lines[-1] == "cpu: chosen (compiled raster)"  # under auto the cpu tier draws compiled


def test_explicit_backend_is_strict_and_quotes_the_error(monkeypatch):
    monkeypatch.setitem(select.TIERS, "wgpu", f"{__name__}:BrokenTier")
    with pytest.raises(RenderError, match=r"tried wgpu\); first error \(wgpu\): RenderError: no adapter"):
        select.select_renderer(cfg(backend="wgpu"), 1000, [])


def test_fallback_after_device_loss_goes_to_next_tier(monkeypatch):
    class LostGl(CpuRenderer):
        tier = "gl"

    lost = LostGl(cfg(), 100, [])
    r = select.fallback_after(lost, RenderError("device lost"))
    assert r.tier == "cpu"
    assert r.selection_log[0] == "gl: failed mid-run (RenderError: device lost); falling back"
    if getattr(r, "raster", None) == "compute":  # the compiled cpu raster; the reference after it
        r = select.fallback_after(r, RenderError("boom"))
        assert type(r) is CpuRenderer
    with pytest.raises(RenderError, match="no tier is left"):
        select.fallback_after(r, RenderError("boom"))
