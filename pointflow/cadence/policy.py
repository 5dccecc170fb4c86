"""Policy engine: how many points the renderer may draw and how often the view updates.

Inputs: a hardware tier (L/M/H, detected or from config), a runtime mode, optional hard
constraints and a legacy switch (``cfg.policy``). Output: a :class:`PolicyDecision` with the
effective point budget and update cadence, plus every cap that was considered and why.

Reference table (PointFlow), budget / cadence ms::

    tier  base                 eco        balanced   max_throughput  custom
    L     200,000 / 250 ms     x0.4, x2   x0.7, x1   x1.0, x0.625    x1, x1
    M     500,000 / 167 ms
    H     1,000,000 / 125 ms

Constraints (``point_budget_cap``, ``update_cadence_min_ms``) are hard caps in every mode and
with ``legacy``. ``legacy`` = no policy point cap, 167 ms. After the table the budget is
capped by what the view can show (``points_per_pixel`` x viewport pixels; not in legacy), by
the GPU's storage-buffer limit and by the ring capacity (always: nothing more exists).
"""
from __future__ import annotations

import logging
import os
from dataclasses import asdict, dataclass, field
from typing import Any, Literal, Optional


log = logging.getLogger("pointflow.policy")

Tier = Literal["L", "M", "H"]
TIERS: tuple[Tier, ...] = ("L", "M", "H")

#: tier -> (point budget, update cadence ms)
BASE_TABLE: dict[str, tuple[int, float]] = {
    "L": (200_000, 250.0),
    "M": (500_000, 167.0),
    "H": (1_000_000, 125.0),
}
#: mode -> (budget multiplier, cadence multiplier)
MODE_TABLE: dict[str, tuple[float, float]] = {
    "eco": (0.4, 2.0),
    "balanced": (0.7, 1.0),
    "max_throughput": (1.0, 0.625),
    "custom": (1.0, 1.0),
}
LEGACY_CADENCE_MS = 167.0
#: Adaptive cadence never waits longer than this between updates.
ADAPTIVE_MAX_INTERVAL_MS = 200.0
#: Bytes per point in the renderer's largest per-point storage buffer (vec4<f32> positions).
GPU_BYTES_PER_POINT = 16

GIB = 1 << 30
# Detection thresholds: a component reaches tier M / H at these values.
CPU_CORES_FOR = {"M": 4, "H": 8}
MEMORY_FOR = {"M": 8 * GIB, "H": 16 * GIB}
#: A hardware GPU with at least this storage binding size counts as tier H.
GPU_BINDING_FOR_H = 1 * GIB


@dataclass(frozen=True)
class HardwareInfo:
    """What tier detection looks at. GPU fields are ``None`` when no adapter was probed."""

    cpu_cores: int
    memory_bytes: int
    gpu_name: Optional[str] = None
    #: wgpu ``adapter_type``: ``DiscreteGPU``, ``IntegratedGPU``, ``VirtualGPU``, ``CPU``, ``Unknown``.
    gpu_type: Optional[str] = None
    gpu_max_storage_binding: Optional[int] = None
    gpu_max_buffer_size: Optional[int] = None

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


@dataclass(frozen=True)
class Cap:
    """One limit considered on the budget or cadence; ``applied`` = it changed the value."""

    name: str
    limit: float
    reason: str
    applied: bool

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


@dataclass
class PolicyDecision:
    tier: str
    tier_source: Literal["config", "detected"]
    mode: str
    legacy: bool
    #: Points the renderer may draw per frame.
    point_budget: int
    #: The policy's update cadence (used as the floor of the adaptive tick interval).
    update_cadence_ms: float
    base_budget: Optional[int]
    base_cadence_ms: float
    caps: list[Cap] = field(default_factory=list)
    tier_reasons: list[str] = field(default_factory=list)
    hardware: Optional[HardwareInfo] = None

    def to_dict(self) -> dict[str, Any]:
        return {
            "tier": self.tier, "tier_source": self.tier_source, "mode": self.mode, "legacy": self.legacy,
            "point_budget": self.point_budget, "update_cadence_ms": self.update_cadence_ms,
            "base_budget": self.base_budget, "base_cadence_ms": self.base_cadence_ms,
            "caps": [c.to_dict() for c in self.caps], "tier_reasons": list(self.tier_reasons),
            "hardware": self.hardware.to_dict() if self.hardware else None,
        }

    def summary(self) -> str:
        applied = ", ".join(f"{c.name}={c.limit:g}" for c in self.caps if c.applied) or "none"
        return (f"policy: tier {self.tier} ({self.tier_source}), mode {self.mode}"
                f"{' (legacy)' if self.legacy else ''}: budget {self.point_budget:,} points, "
                f"cadence {self.update_cadence_ms:g} ms; caps applied: {applied}")


# --------------------------------------------------------------------------- detection
def gpu_info_from_adapter(adapter: Any) -> dict[str, Any]:
    """``{"name", "type", "max_storage_binding", "max_buffer_size"}`` of a wgpu adapter (what
    the render stage puts in its hello, see :mod:`pointflow.cadence.messages`)."""
    info = dict(adapter.info)
    limits = adapter.limits
    return {
        "name": str(info.get("device") or info.get("description") or info.get("vendor") or "unknown"),
        "type": str(info.get("adapter_type") or "Unknown"),
        "max_storage_binding": int(limits["max-storage-buffer-binding-size"]),
        "max_buffer_size": int(limits["max-buffer-size"]),
    }


def _probe_gpu(power_preference: str = "high-performance") -> dict[str, Any]:
    """Adapter name/type/limits via wgpu; {} when wgpu or an adapter is unavailable."""
    try:
        import wgpu  # noqa: PLC0415 - optional and slow to import

        adapter = wgpu.gpu.request_adapter_sync(power_preference=power_preference)
        if adapter is None:
            return {}
        g = gpu_info_from_adapter(adapter)
        return {"gpu_name": g["name"], "gpu_type": g["type"], "gpu_max_storage_binding": g["max_storage_binding"],
                "gpu_max_buffer_size": g["max_buffer_size"]}
    except Exception as exc:  # noqa: BLE001 - detection is best effort
        log.debug("GPU probe failed: %s", exc)
        return {}


def detect_hardware(*, probe_gpu: bool = True, power_preference: str = "high-performance") -> HardwareInfo:
    """CPU cores (affinity-aware), total memory (psutil) and, optionally, the GPU adapter."""
    try:
        cores = len(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        cores = os.cpu_count() or 1
    try:
        import psutil  # noqa: PLC0415

        mem = int(psutil.virtual_memory().total)
    except Exception:  # noqa: BLE001
        mem = int(os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES"))
    gpu = _probe_gpu(power_preference) if probe_gpu else {}
    return HardwareInfo(cpu_cores=cores, memory_bytes=mem, **gpu)


def detect_tier(hw: HardwareInfo) -> tuple[Tier, list[str]]:
    """The weakest component decides: tier = min(CPU tier, memory tier, GPU tier)."""
    def level(value: float, need: dict[str, float]) -> int:
        return 2 if value >= need["H"] else 1 if value >= need["M"] else 0

    reasons = []
    cpu = level(hw.cpu_cores, CPU_CORES_FOR)
    reasons.append(f"cpu: {hw.cpu_cores} cores -> {TIERS[cpu]} (M >= {CPU_CORES_FOR['M']}, H >= {CPU_CORES_FOR['H']})")
    mem = level(hw.memory_bytes, MEMORY_FOR)
    reasons.append(f"memory: {hw.memory_bytes / GIB:.1f} GiB -> {TIERS[mem]} "
                   f"(M >= {MEMORY_FOR['M'] // GIB} GiB, H >= {MEMORY_FOR['H'] // GIB} GiB)")
    levels = [cpu, mem]
    if hw.gpu_type is not None:
        t = hw.gpu_type.lower()
        binding = hw.gpu_max_storage_binding or 0
        if "cpu" in t:
            gpu, why = 0, "software adapter"
        elif "discrete" in t and binding >= GPU_BINDING_FOR_H:
            gpu, why = 2, f"discrete, storage binding {binding / GIB:.1f} GiB"
        else:
            gpu, why = 1, f"{hw.gpu_type}, storage binding {binding / (1 << 20):.0f} MiB"
        reasons.append(f"gpu: {hw.gpu_name} ({why}) -> {TIERS[gpu]}")
        levels.append(gpu)
    else:
        reasons.append("gpu: not probed (does not limit the tier)")
    return TIERS[min(levels)], reasons


# --------------------------------------------------------------------------- resolution
def resolve_policy(cfg: Any, *, hardware: Optional[HardwareInfo] = None,
                   probe_gpu: bool = True) -> PolicyDecision:
    """Apply tier, mode, legacy, constraints, view, GPU and ring caps; log every cap applied.
    ``cfg``: the run's :class:`pointflow.config.PipelineConfig` (the loader sits above the
    stages, so it is not imported here)."""
    p = cfg.policy
    reasons: list[str] = []
    if p.tier in TIERS:
        tier, source = p.tier, "config"
        reasons.append("set in config (policy.tier)")
    else:
        if hardware is None:
            hardware = detect_hardware(probe_gpu=probe_gpu, power_preference=cfg.render.power_preference)
        tier, reasons = detect_tier(hardware)
        source = "detected"
    base_budget, base_cadence = BASE_TABLE[tier]
    caps: list[Cap] = []
    if p.legacy:
        budget: float = float("inf")
        cadence = LEGACY_CADENCE_MS
        table_budget: Optional[int] = None
    else:
        bm, cm = MODE_TABLE[p.mode]
        budget = round(base_budget * bm)
        cadence = base_cadence * cm
        table_budget = int(budget)

    def cap_budget(name: str, limit: float, reason: str) -> None:
        nonlocal budget
        applied = limit < budget
        caps.append(Cap(name, float(limit), reason, applied))
        if applied:
            log.info("policy: point budget capped %s -> %d by %s (%s)",
                     "unbounded" if budget == float("inf") else f"{int(budget):,}", int(limit), name, reason)
            budget = int(limit)

    if p.point_budget_cap is not None:
        cap_budget("point_budget_cap", p.point_budget_cap, "policy.point_budget_cap constraint (hard cap)")
    if p.update_cadence_min_ms is not None:
        applied = p.update_cadence_min_ms > cadence
        caps.append(Cap("update_cadence_min_ms", float(p.update_cadence_min_ms),
                        "policy.update_cadence_min_ms constraint (hard cap)", applied))
        if applied:
            log.info("policy: update cadence raised %.1f -> %.1f ms by update_cadence_min_ms",
                     cadence, p.update_cadence_min_ms)
            cadence = float(p.update_cadence_min_ms)
    w, h = cfg.render.size
    if not p.legacy:
        view = int(p.points_per_pixel * w * h)
        cap_budget("view", view, f"viewport {w}x{h} x points_per_pixel {p.points_per_pixel:g}")
    if hardware is not None and hardware.gpu_max_storage_binding:
        lim = hardware.gpu_max_storage_binding
        if hardware.gpu_max_buffer_size:
            lim = min(lim, hardware.gpu_max_buffer_size)
        cap_budget("gpu_storage", lim // GPU_BYTES_PER_POINT,
                   f"GPU storage buffer limit {lim} B / {GPU_BYTES_PER_POINT} B per point")
    cap_budget("ring", cfg.ring.max_points, "ring.max_points (no more points exist)")
    decision = PolicyDecision(tier=tier, tier_source=source, mode=p.mode, legacy=p.legacy,
                              point_budget=int(budget), update_cadence_ms=float(cadence),
                              base_budget=table_budget, base_cadence_ms=float(cadence if p.legacy else base_cadence),
                              caps=caps, tier_reasons=reasons, hardware=hardware)
    log.info("%s", decision.summary())
    return decision


def tick_interval_ms(cfg: Any, decision: PolicyDecision, frame_ema_ms: Optional[float] = None) -> float:
    """The cadence period. Fixed: ``1000 / target_hz``. Adaptive:
    ``min(200, max(policy cadence, 2 x renderer frame-time EMA))``. ``update_cadence_min_ms``
    is a hard floor in both (it wins over the 200 ms ceiling)."""
    if cfg.cadence.adaptive:
        ms = max(decision.update_cadence_ms, 2.0 * frame_ema_ms if frame_ema_ms else 0.0)
        ms = min(ADAPTIVE_MAX_INTERVAL_MS, ms)
    else:
        ms = 1000.0 / cfg.cadence.target_hz
    floor = cfg.policy.update_cadence_min_ms
    if floor:
        ms = max(ms, float(floor))
    return ms
