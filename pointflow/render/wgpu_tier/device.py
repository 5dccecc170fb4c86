"""Adapter and device selection for the wgpu tier.

Software adapters (Mesa lavapipe/llvmpipe) are accepted: that is how CI runs. Vulkan is
preferred over GL because wgpu's GL backend lacks some compute features.
``POINTFLOW_WGPU_ADAPTER=<substring>`` picks the first adapter whose summary contains it.
"""
from __future__ import annotations

import os
from typing import Any, Optional

_BACKEND_RANK = {"Vulkan": 0, "Metal": 0, "D3D12": 1, "OpenGL": 3, "OpenGLES": 3}


def _ensure_runtime_dir() -> None:
    # wgpu-native's Vulkan loader warns loudly without it; harmless but noisy.
    if not os.environ.get("XDG_RUNTIME_DIR"):
        d = f"/tmp/xdg-{os.getuid()}"
        os.makedirs(d, mode=0o700, exist_ok=True)
        os.environ["XDG_RUNTIME_DIR"] = d


def select_adapter(power_preference: str = "high-performance") -> tuple[Optional[Any], str]:
    """(adapter, why) — the adapter to use, or (None, reason)."""
    _ensure_runtime_dir()
    try:
        import wgpu
    except Exception as e:  # pragma: no cover
        return None, f"wgpu not importable: {e}"
    want = os.environ.get("POINTFLOW_WGPU_ADAPTER", "").strip().lower()
    try:
        adapters = list(wgpu.gpu.enumerate_adapters_sync())
    except Exception as e:
        return None, f"enumerating adapters failed: {type(e).__name__}: {e}"
    if not adapters:
        return None, "no wgpu adapter (no Vulkan/Metal/D3D12/GL driver found)"
    if want:
        for a in adapters:
            if want in a.summary.lower():
                return a, f"POINTFLOW_WGPU_ADAPTER={want!r} matched {a.summary}"
        return None, (f"POINTFLOW_WGPU_ADAPTER={want!r} matches none of: "
                      + "; ".join(a.summary for a in adapters))
    # Ask wgpu for its preference (power_preference), then prefer a compute-capable backend.
    try:
        pref = wgpu.gpu.request_adapter_sync(power_preference=power_preference)
    except Exception:
        pref = None
    kind_rank = {"DiscreteGPU": 0, "IntegratedGPU": 1, "VirtualGPU": 2, "CPU": 3, "Unknown": 4}
    if power_preference == "low-power":
        kind_rank.update({"IntegratedGPU": 0, "DiscreteGPU": 1})

    def rank(a) -> tuple:
        info = a.info
        return (_BACKEND_RANK.get(info.get("backend_type", ""), 2),
                kind_rank.get(info.get("adapter_type", "Unknown"), 4),
                0 if (pref is not None and a.summary == pref.summary) else 1)

    best = sorted(adapters, key=rank)[0]
    return best, f"{best.summary} ({power_preference}; {len(adapters)} adapter(s) found)"


def request_device(adapter: Any, want_timestamps: bool,
                   optional_features: tuple[str, ...] = ()) -> tuple[Any, dict[str, Any]]:
    """Device with the adapter's storage/buffer limits, timestamp queries when offered, and
    those of ``optional_features`` the adapter has (all or none: they are used together)."""
    feats = []
    ts = bool(want_timestamps and "timestamp-query" in adapter.features)
    if ts:
        feats.append("timestamp-query")
    extra = list(optional_features) if all(f in adapter.features for f in optional_features) else []
    feats += extra
    lim = adapter.limits
    keys = ("max-storage-buffer-binding-size", "max-buffer-size", "max-compute-workgroups-per-dimension",
            "max-storage-buffers-per-shader-stage", "max-texture-dimension-2d")
    required = {k: lim[k] for k in keys if k in lim}
    device = adapter.request_device_sync(required_features=feats, required_limits=required,
                                         label="pointflow-wgpu")
    return device, {"timestamps": ts, "features": extra, "limits": {k: int(device.limits[k]) for k in keys if k in device.limits}}


def adapter_summary(adapter: Any) -> dict[str, Any]:
    info = adapter.info
    return {"summary": adapter.summary, "backend": info.get("backend_type", ""),
            "adapter_type": info.get("adapter_type", ""), "vendor": info.get("vendor", ""),
            "device": info.get("device", ""), "description": info.get("description", "")}
