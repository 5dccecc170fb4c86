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


def test_adapter_probe_is_remembered_under_its_key(monkeypatch):
    """Issue 36: enumerating wgpu's adapters (importing wgpu, opening every driver) was most
    of the render stage's start; an unchanged machine reads the last answer from the user
    cache, a changed key (driver environment) or ``POINTFLOW_ADAPTER_CACHE=0`` probes again,
    and a failed probe is not remembered."""
    monkeypatch.delenv(select.ENV_ADAPTER_CACHE, raising=False)
    monkeypatch.setattr(select, "_adapter_key", lambda c: f"key-{c.power_preference}-{__import__('os').environ.get('VK_ICD_FILENAMES', '')}")
    calls = []
    soft = {"summary": "llvmpipe (CPU) via Vulkan", "adapter_type": "CPU"}

    def probe(c):
        calls.append(c.power_preference)
        return dict(soft)

    monkeypatch.setattr(select, "_probe_adapter_now", probe)
    assert select.probe_adapter(cfg()) == soft
    assert select.probe_adapter(cfg()) == soft
    assert len(calls) == 1  # the second start read the file
    assert json.loads(select.calibration.cache_path(select.ADAPTER_FILE).read_text())["adapter"] == soft
    monkeypatch.setenv("VK_ICD_FILENAMES", "/elsewhere/nvidia_icd.json")  # the key changed: probe again
    assert select.probe_adapter(cfg()) == soft
    assert len(calls) == 2
    monkeypatch.setenv(select.ENV_ADAPTER_CACHE, "0")
    assert select.probe_adapter(cfg()) == soft
    assert len(calls) == 3
    monkeypatch.delenv(select.ENV_ADAPTER_CACHE)
    monkeypatch.setattr(select, "_probe_adapter_now", lambda c: calls.append("none"))  # no adapter now
    monkeypatch.setattr(select, "_adapter_key", lambda c: "another-key")
    assert select.probe_adapter(cfg()) is None
    assert select.probe_adapter(cfg()) is None
    assert calls[-2:] == ["none", "none"]  # a failed probe is tried again at the next start


def test_adapter_key_reads_no_gpu_stack():
    """The key is stat calls and the environment: computing it imports neither wgpu nor moderngl."""
    import subprocess
    import sys

    code = ("import sys; from pointflow.render import select; from pointflow.config import RenderConfig; "
            "k = select._adapter_key(RenderConfig()); "
            "print(k is None or 'wgpu' not in sys.modules and 'moderngl' not in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.stdout.strip() == "True", out.stderr
