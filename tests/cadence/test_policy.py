"""Policy engine: the whole reference table, constraints, legacy, view/GPU/ring caps, detection."""
import logging

import pytest

from pointflow.cadence.policy import (
    BASE_TABLE,
    GIB,
    GPU_BYTES_PER_POINT,
    MODE_TABLE,
    HardwareInfo,
    detect_hardware,
    detect_tier,
    gpu_info_from_adapter,
    resolve_policy,
    tick_interval_ms,
)
from pointflow.config import load_config

MODES = ["eco", "balanced", "max_throughput", "custom"]
# PointFlow reference: (budget, cadence ms) per tier x mode
EXPECTED = {
    ("L", "eco"): (80_000, 500.0), ("L", "balanced"): (140_000, 250.0),
    ("L", "max_throughput"): (200_000, 156.25), ("L", "custom"): (200_000, 250.0),
    ("M", "eco"): (200_000, 334.0), ("M", "balanced"): (350_000, 167.0),
    ("M", "max_throughput"): (500_000, 104.375), ("M", "custom"): (500_000, 167.0),
    ("H", "eco"): (400_000, 250.0), ("H", "balanced"): (700_000, 125.0),
    ("H", "max_throughput"): (1_000_000, 78.125), ("H", "custom"): (1_000_000, 125.0),
}


def cfg(policy=None, size=(1920, 1080), ring=10_000_000, **extra):
    d = {"source": {"transport": "synthetic"}, "policy": policy or {}, "render": {"size": list(size)},
         "ring": {"max_points": ring}}
    d.update(extra)
    return load_config(d)


@pytest.mark.parametrize("tier,mode", sorted(EXPECTED))
def test_reference_table(tier, mode):
    d = resolve_policy(cfg({"tier": tier, "mode": mode}), probe_gpu=False)
    budget, cadence = EXPECTED[(tier, mode)]
    assert (d.tier, d.tier_source, d.mode) == (tier, "config", mode)
    assert d.point_budget == budget
    assert d.update_cadence_ms == pytest.approx(cadence)
    assert not any(c.applied for c in d.caps)  # a 1920x1080 view and a 10M ring cap nothing here
    assert d.to_dict()["point_budget"] == budget


def test_tables_match_reference():
    assert BASE_TABLE == {"L": (200_000, 250.0), "M": (500_000, 167.0), "H": (1_000_000, 125.0)}
    assert MODE_TABLE == {"eco": (0.4, 2.0), "balanced": (0.7, 1.0), "max_throughput": (1.0, 0.625),
                          "custom": (1.0, 1.0)}


@pytest.mark.parametrize("tier", ["L", "M", "H"])
@pytest.mark.parametrize("mode", MODES)
def test_constraints_are_hard_caps_in_every_mode(tier, mode):
    d = resolve_policy(cfg({"tier": tier, "mode": mode, "point_budget_cap": 50_000,
                            "update_cadence_min_ms": 600.0}), probe_gpu=False)
    assert d.point_budget == 50_000
    assert d.update_cadence_ms == 600.0
    names = {c.name for c in d.caps if c.applied}
    assert {"point_budget_cap", "update_cadence_min_ms"} <= names
    # a constraint looser than the table changes nothing and is reported as not applied
    d2 = resolve_policy(cfg({"tier": tier, "mode": mode, "point_budget_cap": 5_000_000,
                             "update_cadence_min_ms": 1.0}), probe_gpu=False)
    assert (d2.point_budget, d2.update_cadence_ms) == pytest.approx(EXPECTED[(tier, mode)])
    assert not any(c.applied for c in d2.caps)


@pytest.mark.parametrize("tier", ["L", "M", "H"])
def test_legacy_no_point_cap_167ms(tier):
    d = resolve_policy(cfg({"tier": tier, "mode": "eco", "legacy": True}, size=(320, 240), ring=3_000_000),
                       probe_gpu=False)
    assert d.legacy and d.update_cadence_ms == 167.0
    assert d.point_budget == 3_000_000  # only the ring (what exists) limits it; no view cap in legacy
    assert [c.name for c in d.caps] == ["ring"]
    d = resolve_policy(cfg({"tier": tier, "legacy": True, "point_budget_cap": 1234, "update_cadence_min_ms": 300}),
                       probe_gpu=False)
    assert (d.point_budget, d.update_cadence_ms) == (1234, 300.0)  # constraints still bind


def test_view_cap_logged_with_reason(caplog):
    with caplog.at_level(logging.INFO, logger="pointflow.policy"):
        d = resolve_policy(cfg({"tier": "H", "mode": "max_throughput", "points_per_pixel": 2.0}, size=(320, 240)),
                           probe_gpu=False)
    assert d.point_budget == 2 * 320 * 240
    cap = [c for c in d.caps if c.name == "view"][0]
    assert cap.applied and "320x240" in cap.reason
    assert any("view" in r.getMessage() and "153600" in r.getMessage() for r in caplog.records)


def test_gpu_storage_cap():
    hw = HardwareInfo(cpu_cores=16, memory_bytes=64 * GIB, gpu_name="small", gpu_type="DiscreteGPU",
                      gpu_max_storage_binding=4 * 2**20, gpu_max_buffer_size=2**31)
    d = resolve_policy(cfg({"mode": "max_throughput"}), hardware=hw)
    assert d.point_budget == 4 * 2**20 // GPU_BYTES_PER_POINT
    assert [c.name for c in d.caps if c.applied] == ["gpu_storage"]


def test_ring_cap():
    d = resolve_policy(cfg({"tier": "H", "mode": "max_throughput"}, ring=250_000), probe_gpu=False)
    assert d.point_budget == 250_000
    assert [c.name for c in d.caps if c.applied] == ["ring"]


@pytest.mark.parametrize("hw,tier", [
    (HardwareInfo(2, 4 * GIB), "L"),
    (HardwareInfo(4, 8 * GIB), "M"),
    (HardwareInfo(8, 16 * GIB), "H"),
    (HardwareInfo(32, 4 * GIB), "L"),                       # memory limits
    (HardwareInfo(2, 64 * GIB), "L"),                       # cores limit
    (HardwareInfo(16, 64 * GIB, "lavapipe", "CPU", 128 << 20, 1 << 31), "L"),     # software GPU
    (HardwareInfo(16, 64 * GIB, "igpu", "IntegratedGPU", 2 * GIB, 1 << 32), "M"),
    (HardwareInfo(16, 64 * GIB, "dgpu", "DiscreteGPU", 128 << 20, 1 << 32), "M"),  # small binding
    (HardwareInfo(16, 64 * GIB, "dgpu", "DiscreteGPU", 2 * GIB, 1 << 33), "H"),
])
def test_detection_reaches_every_tier(hw, tier):
    got, reasons = detect_tier(hw)
    assert got == tier
    assert len(reasons) == 3
    d = resolve_policy(cfg({"tier": "auto"}), hardware=hw)
    assert d.tier == tier and d.tier_source == "detected"
    assert d.point_budget <= EXPECTED[(tier, "balanced")][0]


def test_detect_hardware_real_machine():
    hw = detect_hardware(probe_gpu=False)
    assert hw.cpu_cores >= 1 and hw.memory_bytes > 0 and hw.gpu_type is None
    assert detect_tier(hw)[0] in ("L", "M", "H")


def test_tick_interval_fixed_and_adaptive():
    c = cfg({"tier": "M"}, cadence={"target_hz": 50})
    d = resolve_policy(c, probe_gpu=False)
    assert tick_interval_ms(c, d) == 20.0
    assert tick_interval_ms(c, d, frame_ema_ms=500) == 20.0  # fixed mode ignores frame time
    c = cfg({"tier": "H", "mode": "max_throughput"}, cadence={"adaptive": True})
    d = resolve_policy(c, probe_gpu=False)                     # policy cadence 78.125 ms
    assert tick_interval_ms(c, d) == pytest.approx(78.125)
    assert tick_interval_ms(c, d, frame_ema_ms=10) == pytest.approx(78.125)
    assert tick_interval_ms(c, d, frame_ema_ms=60) == pytest.approx(120.0)   # 2 x EMA
    assert tick_interval_ms(c, d, frame_ema_ms=400) == pytest.approx(200.0)  # ceiling
    c = cfg({"tier": "H", "update_cadence_min_ms": 300}, cadence={"adaptive": True})
    d = resolve_policy(c, probe_gpu=False)
    assert tick_interval_ms(c, d, frame_ema_ms=400) == pytest.approx(300.0)  # hard floor wins
    c = cfg({"update_cadence_min_ms": 40}, cadence={"target_hz": 60})
    assert tick_interval_ms(c, resolve_policy(c, probe_gpu=False)) == pytest.approx(40.0)


@pytest.mark.gpu
def test_detection_reads_real_adapter_limits():
    from gpu_util import require_adapter

    adapter = require_adapter()
    hw = detect_hardware(probe_gpu=True)
    assert hw.gpu_type is not None, "wgpu found an adapter but policy detection did not"
    assert hw.gpu_max_storage_binding == adapter.limits["max-storage-buffer-binding-size"]
    g = gpu_info_from_adapter(adapter)  # what the render stage sends in its hello
    assert g["max_storage_binding"] == hw.gpu_max_storage_binding and g["type"] == adapter.info["adapter_type"]
    tier, reasons = detect_tier(hw)
    assert any(r.startswith("gpu:") and "not probed" not in r for r in reasons)
    if hw.gpu_type == "CPU":
        assert tier == "L"  # a software rasteriser never counts as a real GPU
    d = resolve_policy(cfg({"mode": "max_throughput"}, ring=10**9), hardware=hw)
    assert d.point_budget <= hw.gpu_max_storage_binding // GPU_BYTES_PER_POINT
