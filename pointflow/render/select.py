"""Choosing a render tier, and falling back when one fails.

Modelled on pyzmq's backend selection: an environment override, candidates tried in
order, every skip explained, and a clear error quoting the first real failure when
nothing works.

- ``POINTFLOW_BACKEND`` (``auto``/``wgpu``/``gl``/``cpu``) overrides ``render.backend``.
- An explicit tier is strict: it is the only candidate (its failure is the error).
- ``auto`` tries wgpu → gl → cpu. Scenes smaller than the cpu crossover go to the cpu
  tier first: below it, uploading to a GPU costs more than it saves (measured by
  ``bench/bench_tiers.py``, see :func:`crossover_points` for where the number comes from).
  When the wgpu adapter is a software one (Mesa lavapipe/llvmpipe: adapter type CPU) and
  the compiled cpu raster measured faster than it (``cpu_raster.json``, written by
  ``bench/bench_render.py --cpu-crossover --install``), the cpu tier goes first.
- The cpu tier has two raster methods (:func:`cpu_method`): ``compute`` (compiled, numba,
  :mod:`.cpu_compute`) and ``reference`` (float64 numpy, :mod:`.cpu`). Without numba, or
  with ``POINTFLOW_NO_NUMBA=1``, ``compute`` falls back to the reference with one log line.
- The compiled method is taken only when its loops are already in numba's disk cache
  (``cpu_kernels.cache_state()``): a render stage never waits for the compiler. Otherwise
  the next candidate draws (``compiled_pending`` set on it) and the render stage compiles
  in the background and switches (:mod:`.rasterswitch`).
- :func:`fallback_after` gives the next tier when one raises ``RenderError`` mid-run.
"""
from __future__ import annotations

import importlib
import json
import logging
import os
from pathlib import Path
from typing import Callable, Optional

from .config import RenderConfig
from . import calibration
from .base import Renderer, RenderError

log = logging.getLogger("pointflow.render.select")

#: Tiers in order of preference for ``auto``.
ORDER = ("wgpu", "gl", "cpu")
#: Where each tier's class lives (imported lazily: a missing GPU stack is a skip, not a crash).
TIERS = {
    "wgpu": "pointflow.render.wgpu_tier:WgpuRenderer",
    "gl": "pointflow.render.gl:GlRenderer",
    "cpu": "pointflow.render.cpu:CpuRenderer",
    # the cpu tier's compiled raster method (render.raster: compute); tried before "cpu"
    "cpu-compute": "pointflow.render.cpu_compute:CpuComputeRenderer",
}
ENV_BACKEND = "POINTFLOW_BACKEND"
ENV_CROSSOVER = "POINTFLOW_CROSSOVER"
#: Used when no calibration file is readable (the package ships one, see
#: :mod:`pointflow.render.calibration`). ``bench/bench_tiers.py`` measured 0 on the
#: development machine (2 cores, lavapipe/llvmpipe): the GPU tiers beat the numpy tier even
#: at 1,000 points there (its fixed per-frame cost is ~12 ms at 1280x720), so size alone
#: never sends a scene to the cpu tier unless a measurement says so.
DEFAULT_CROSSOVER = 0
CROSSOVER_FILE = "crossover.json"
#: where the compiled cpu raster beats the wgpu tier on a software adapter
CPU_RASTER_FILE = "cpu_raster.json"


def _load_class(tier: str) -> type[Renderer]:
    mod, _, name = TIERS[tier].partition(":")
    return getattr(importlib.import_module(mod), name)


def cache_path() -> Path:
    """The per-user file the benchmark writes the measured crossover to."""
    return calibration.cache_path(CROSSOVER_FILE)


def _read_crossover_file(path: Path) -> Optional[int]:
    try:
        data = json.loads(path.read_text())
        return int(data["crossover_points"])
    except (OSError, ValueError, KeyError, TypeError):
        return None


def crossover_points(cfg: Optional[RenderConfig] = None) -> tuple[int, str]:
    """(points, where it came from). First match wins: ``render.cpu_crossover_points``
    (an int), env ``POINTFLOW_CROSSOVER`` (an int or a JSON file path), the user cache
    file (:func:`cache_path`), the default shipped in the package (see
    :mod:`pointflow.render.calibration`), then :data:`DEFAULT_CROSSOVER`."""
    if cfg is not None and isinstance(cfg.cpu_crossover_points, int):
        return cfg.cpu_crossover_points, "render.cpu_crossover_points"
    env = os.environ.get(ENV_CROSSOVER, "").strip()
    if env:
        if env.isdigit():
            return int(env), f"${ENV_CROSSOVER}"
        v = _read_crossover_file(Path(env))
        if v is not None:
            return v, f"${ENV_CROSSOVER} ({env})"
        log.warning("%s=%r is neither an integer nor a readable crossover JSON; ignored", ENV_CROSSOVER, env)
    data, where = calibration.load(CROSSOVER_FILE, ("crossover_points",))
    try:
        return int(data["crossover_points"]), where  # type: ignore[index]
    except (TypeError, ValueError):
        return DEFAULT_CROSSOVER, "built-in default"


def cpu_method(cfg: RenderConfig, explicit: bool) -> tuple[list[str], str]:
    """(candidates for the cpu tier, why): ``["cpu-compute", "cpu"]`` (compiled first, the
    reference if it cannot start) or ``["cpu"]`` (the float64 reference). ``explicit``: the
    cpu tier was asked for by name, where ``raster: auto`` keeps the reference (deterministic
    images, what ``backend: cpu`` has always drawn); under ``backend: auto`` the cpu tier
    draws with the compiled method."""
    want = cfg.raster
    if want == "reference":
        return ["cpu"], "render.raster=reference: the float64 numpy reference"
    if explicit and want != "compute":
        return ["cpu"], (f"backend cpu with render.raster={want}: the float64 numpy reference "
                         "(render.raster: compute asks for the compiled method)")
    from . import cpu_kernels

    off = cpu_kernels.disabled()
    if off:
        return ["cpu"], f"{off}: compiled raster off; the float64 numpy reference draws"
    if not cpu_kernels.available():
        return ["cpu"], "numba is not installed: the float64 numpy reference draws"
    return ["cpu-compute", "cpu"], f"render.raster={want}: the compiled raster (numba), the reference if it cannot start"


def cpu_summary() -> str:
    """The cpu tier's raster methods here, in words (``pointflow info``)."""
    from . import cpu_kernels

    off = cpu_kernels.disabled()
    if off:
        comp = f"compiled raster off ({off})"
    elif not cpu_kernels.available():
        comp = "compiled raster unavailable (numba not installed)"
    else:
        data, where = cpu_raster_crossover()
        if data is None:
            comp = "compiled raster (numba); auto: no measurement against a software adapter"
        else:
            lim = data.get("faster_up_to_points")
            upto = "at every size measured" if lim is None else f"up to {int(lim):,} points"
            comp = f"compiled raster (numba); auto prefers it over a software wgpu adapter {upto} ({where})"
    if not off and cpu_kernels.available():
        st = cpu_kernels.cache_state()
        comp += {"ready": f"; compiled for this machine ({cpu_kernels.cache_dir()})",
                 "missing": f"; not compiled for this machine yet ({cpu_kernels.cache_dir()}): `pointflow warm`, or the "
                            "first run compiles it in the background",
                 "unwritable": "; numba has no writable cache location: set NUMBA_CACHE_DIR"}.get(st, "")
    return f"reference (numpy, float64); {comp}"


def cpu_raster_crossover() -> tuple[Optional[dict], str]:
    """(calibration, where from): ``faster_up_to_points`` (int, or None = at every size
    measured; 0 = never) below which the compiled cpu raster beat the wgpu tier on a
    software adapter, with the speedups measured."""
    return calibration.load(CPU_RASTER_FILE, ("faster_up_to_points",))


def auto_order(points: int, cfg: Optional[RenderConfig] = None) -> tuple[list[str], str]:
    """(the tiers ``auto`` tries, in order, for a ring of ``points``; why): the same decision
    a run makes (:func:`select_renderer`), without starting a tier."""
    lines: list[str] = []
    tiers = _candidates(cfg or RenderConfig(), points, points, lines)
    why = next((ln for ln in lines if not ln.startswith("cpu raster:")), "")
    return tiers, why


def auto_summary(cfg: Optional[RenderConfig] = None) -> str:
    """How ``auto`` picks here, in words (``pointflow info``): the order for each range of
    ring sizes where it differs, each with the reason a run would log."""
    cfg = cfg or RenderConfig()
    xo, _ = crossover_points(cfg)
    data, _ = cpu_raster_crossover()
    lim = (data or {}).get("faster_up_to_points")
    bounds = sorted({b for b in (xo, int(lim) + 1 if lim is not None else 0) if b > 1})
    starts = [1] + bounds
    parts: list[tuple[int, list[str], str]] = []  # (first ring size, order, why), one per range
    for i, n in enumerate(starts):
        tiers, why = auto_order(starts[i + 1] - 1 if i + 1 < len(starts) else n, cfg)
        if parts and parts[-1][1] == tiers:
            parts[-1] = (parts[-1][0], tiers, why)  # the same order: one range, the larger sizes' reason
            continue
        parts.append((n, tiers, why))

    def words(tiers: list[str]) -> str:
        shown = [("cpu (compiled raster)" if t == "cpu-compute" else t) for t in tiers]
        if "cpu-compute" in tiers:
            shown.remove("cpu")  # the reference backs the compiled raster up; said once
        return " > ".join(shown)

    if len(parts) == 1:
        return f"{words(parts[0][1])} at every ring size ({parts[0][2]})"
    out = []
    for i, (n, tiers, why) in enumerate(parts):
        upto = f"below {parts[i + 1][0]:,} points" if i + 1 < len(parts) else f"from {n:,} points"
        out.append(f"{words(tiers)} {upto} ({why})")
    return "; ".join(out)


#: the last adapter probe's answer, per user (:func:`probe_adapter`)
ADAPTER_FILE = "adapter_probe.json"
#: ``0`` turns the adapter probe's cache off (every start enumerates the adapters)
ENV_ADAPTER_CACHE = "POINTFLOW_ADAPTER_CACHE"
#: what can change which adapter wgpu finds: read at each start, the cache's key
_ADAPTER_ENV = ("POINTFLOW_WGPU_ADAPTER", "VK_ICD_FILENAMES", "VK_DRIVER_FILES", "VK_ADD_DRIVER_FILES",
                "WGPU_BACKEND_TYPE", "WGPU_ADAPTER_NAME", "WGPU_POWER_PREF", "LIBGL_ALWAYS_SOFTWARE",
                "GALLIUM_DRIVER", "MESA_LOADER_DRIVER_OVERRIDE", "CUDA_VISIBLE_DEVICES", "LD_LIBRARY_PATH")
_ADAPTER_DIRS = ("/dev/dri", "/usr/share/vulkan/icd.d", "/etc/vulkan/icd.d", "/usr/local/share/vulkan/icd.d")


def _adapter_key(cfg: RenderConfig) -> Optional[str]:
    """What the probe's answer depends on, read without importing wgpu (a few stat calls):
    wgpu's install, the environment that steers the drivers, the GPU device nodes and the
    Vulkan drivers installed. None: wgpu is not installed."""
    import importlib.util

    try:
        spec = importlib.util.find_spec("wgpu")
    except (ImportError, ValueError):
        return None
    if spec is None or not spec.origin:
        return None
    parts = [cfg.power_preference]
    try:
        parts.append(f"{spec.origin}@{os.stat(spec.origin).st_mtime_ns}")
    except OSError:
        return None
    parts += [f"{k}={os.environ.get(k, '')}" for k in _ADAPTER_ENV]
    for d in _ADAPTER_DIRS:
        try:
            parts.append(f"{d}:{','.join(sorted(os.listdir(d)))}")
        except OSError:
            parts.append(f"{d}:-")
    try:
        parts.append("nv:" + ",".join(sorted(n for n in os.listdir("/dev") if n.startswith("nvidia"))))
    except OSError:
        pass
    return "|".join(parts)


def _probe_adapter_now(cfg: RenderConfig) -> Optional[dict]:
    try:
        from .wgpu_tier.device import adapter_summary, select_adapter
        a, _why = select_adapter(cfg.power_preference)
        return adapter_summary(a) if a is not None else None
    except Exception:  # noqa: BLE001 - no wgpu stack: nothing to compare with
        return None


def probe_adapter(cfg: RenderConfig) -> Optional[dict]:
    """The wgpu adapter the wgpu tier would take (its summary), or None (no wgpu).

    Enumerating the adapters imports wgpu and opens every driver: 0.4 s on an idle 2-core
    VM with lavapipe, 1-3.5 s loaded, most of the render stage's start when the tier it
    decides is then the cpu one. The answer is kept in the user cache
    (``$XDG_CACHE_HOME/pointflow/adapter_probe.json``) under a key of what can change it
    (:func:`_adapter_key`: wgpu's install, the driver environment, /dev/dri, /dev/nvidia*,
    the Vulkan drivers installed), so a start on an unchanged machine reads a file.
    ``POINTFLOW_ADAPTER_CACHE=0`` probes every time."""
    use_cache = os.environ.get(ENV_ADAPTER_CACHE, "").strip() not in ("0", "off", "no")
    key = _adapter_key(cfg) if use_cache else None
    if key is not None:
        try:
            data = json.loads(calibration.cache_path(ADAPTER_FILE).read_text())
            if data.get("key") == key and isinstance(data.get("adapter"), dict):
                return data["adapter"]
        except (OSError, ValueError, AttributeError):
            pass
    ad = _probe_adapter_now(cfg)
    if key is not None and ad is not None:  # a failed probe is not remembered: the next start tries again
        try:
            calibration.install(ADAPTER_FILE, {"key": key, "adapter": ad})
        except OSError:
            pass
    return ad


def _prefer_cpu_compute(cfg: RenderConfig, n: int, lines: list[str]) -> bool:
    """``auto``: the compiled cpu raster before a software wgpu adapter when it measured faster."""
    if cfg.raster not in ("auto", "compute"):
        return False
    cands, _ = cpu_method(cfg, explicit=False)
    if cands[0] != "cpu-compute":
        return False
    ad = probe_adapter(cfg)
    if ad is None or ad.get("adapter_type") != "CPU":
        return False
    data, where = cpu_raster_crossover()
    if data is None:
        lines.append(f"wgpu adapter {ad['summary']} is software, but no cpu_raster.json measurement ({where}): GPU tiers first")
        return False
    lim = data.get("faster_up_to_points")
    sp = data.get("speedup") or {}
    told = ", ".join(f"{float(v):.1f}x at {k} points" for k, v in sp.items())
    if lim is not None and n > int(lim):
        lines.append(f"wgpu adapter {ad['summary']} is software; the compiled cpu raster measured faster only up to "
                     f"{lim} points ({told}; from {where}): GPU tiers first for {n} points")
        return False
    lines.append(f"cpu compute first: the wgpu adapter {ad['summary']} is software and the compiled cpu raster "
                 f"measured faster than it ({told}; from {where})")
    return True


def _candidates(cfg: RenderConfig, expected_points: Optional[int], capacity: int, lines: list[str]) -> list[str]:
    env = os.environ.get(ENV_BACKEND, "").strip().lower()
    backend = cfg.backend
    if env:
        if env not in ("auto",) + ORDER:
            raise RenderError(f"${ENV_BACKEND}={env!r}: expected one of auto, {', '.join(ORDER)}")
        lines.append(f"${ENV_BACKEND}={env} overrides render.backend={backend}")
        backend = env
    if backend != "auto":
        lines.append(f"backend {backend} requested explicitly: no other tier is tried")
        return _expand([backend], cfg, True, lines)
    if cfg.raster == "reference":
        lines.append("render.raster=reference: the float64 numpy reference tier only")
        return ["cpu"]
    n = capacity if expected_points is None else int(expected_points)
    xo, src = crossover_points(cfg)
    if n < xo:
        lines.append(f"cpu first: scene of {n} points < crossover {xo} (from {src}); a GPU upload costs more than it saves")
        return _expand(["cpu", "wgpu", "gl"], cfg, False, lines)
    if _prefer_cpu_compute(cfg, n, lines):
        return _expand(["cpu", "wgpu", "gl"], cfg, False, lines)
    lines.append(f"scene of {n} points >= crossover {xo} (from {src}): GPU tiers first")
    return _expand(list(ORDER), cfg, False, lines)


def _expand(tiers: list[str], cfg: RenderConfig, explicit: bool, lines: list[str]) -> list[str]:
    """Replace "cpu" by the cpu tier's raster method(s) (:func:`cpu_method`), saying why once."""
    if "cpu" not in tiers:
        return tiers
    cands, why = cpu_method(cfg, explicit)
    lines.append(f"cpu raster: {why}")
    i = tiers.index("cpu")
    return tiers[:i] + cands + tiers[i + 1:]


def _describe(exc: BaseException) -> str:
    return f"{type(exc).__name__}: {exc}".strip().rstrip(":")


#: while the compiled raster compiles, the tiers tried first (env POINTFLOW_RASTER_MEANWHILE,
#: e.g. ``wgpu,gl,cpu``): the float64 reference, no device to open, drew the demo's first
#: picture 1-1.7 s sooner than wgpu on lavapipe (wgpu then drew ~40% more frames) and agrees
#: with the compiled raster within 0.1% of pixels (bench/bench_first_picture.py)
MEANWHILE = ("cpu",)
ENV_MEANWHILE = "POINTFLOW_RASTER_MEANWHILE"


def _unless_compiling(rest: list[str], lines: list[str]) -> tuple[list[str], Optional[str]]:
    """When the compiled raster's loops are not in numba's disk cache (the stage would wait
    for the compiler): the tiers after it, :data:`MEANWHILE` first, and why (``missing`` or
    ``unwritable``); else ``(rest, None)``: take it."""
    from . import cpu_kernels

    state = cpu_kernels.cache_state()
    if state not in ("missing", "unwritable"):
        return rest, None
    lines.append("cpu-compute: not yet: " + (
        "its loops are not compiled on this machine; they compile in the background"
        if state == "missing" else
        f"numba cannot cache its loops here ({cpu_kernels.cache_dir() or 'no writable location'}; "
        "set NUMBA_CACHE_DIR to a writable directory and run `pointflow warm`)"))
    env = os.environ.get(ENV_MEANWHILE, "").strip()
    meanwhile = [t.strip() for t in env.split(",")] if env else MEANWHILE
    first = [t for t in meanwhile if t in rest]
    return first + [t for t in rest if t not in first], state


def _try(tiers: list[str], cfg: RenderConfig, capacity: int, channels: list[str], lines: list[str],
         make: Optional[Callable[[str], type[Renderer]]] = None) -> Renderer:
    first: Optional[tuple[str, BaseException]] = None
    pending = None  # the compiled cpu raster's loops are not in numba's cache yet
    todo = list(tiers)
    while todo:
        tier = todo.pop(0)
        if tier == "cpu-compute" and make is None:  # looked at only when reached (numba's import)
            todo, pending = _unless_compiling(todo, lines)
            if pending:
                continue
        try:
            cls = (make or _load_class)(tier)
        except (ImportError, AttributeError) as exc:
            lines.append(f"{tier}: skipped: not available ({_describe(exc)})")
            continue
        try:
            r = cls(cfg, capacity, channels)
        except Exception as exc:  # noqa: BLE001 - any start-up failure is a reason to skip
            lines.append(f"{tier}: skipped: {_describe(exc)}")
            first = first or (tier, exc)
            continue
        r.compiled_pending = pending  # type: ignore[attr-defined]  # render/process.py: compile, then switch
        lines.append(f"{r.tier}: chosen" + (" (compiled raster)" if tier == "cpu-compute" else "")
                     + (" meanwhile" if pending == "missing" else ""))
        if getattr(r, "raster", None) and tier != "cpu-compute":  # the wgpu tier's raster method and why
            lines.append(f"{tier}: raster method {r.raster} ({getattr(r, '_raster_why', '')})")
        for line in lines:
            log.info("tier selection: %s", line)
        return r
    for line in lines:
        log.info("tier selection: %s", line)
    detail = f"; first error ({first[0]}): {_describe(first[1])}" if first else ""
    err = RenderError(f"no render tier could start (tried {', '.join(tiers)}){detail}")
    err.reasons = list(lines)  # type: ignore[attr-defined]
    raise err from (first[1] if first else None)


def select_renderer(cfg: RenderConfig, capacity: int, channels: list[str], *,
                    expected_points: Optional[int] = None) -> tuple[Renderer, list[str]]:
    """Start the best tier for this config; returns (renderer, log lines saying why each
    candidate was skipped or chosen). ``expected_points`` (default: ``capacity``) is
    compared with the crossover. Raises RenderError when no tier starts."""
    lines: list[str] = []
    tiers = _candidates(cfg, expected_points, capacity, lines)
    r = _try(tiers, cfg, capacity, channels, lines)
    r.selection_log = list(lines)  # type: ignore[attr-defined]
    return r, lines


def next_tiers(tier: str) -> list[str]:
    """Tiers after ``tier`` in fallback order (wgpu → gl → cpu)."""
    return list(ORDER[ORDER.index(tier) + 1:]) if tier in ORDER else ["cpu"]


def fallback_after(renderer: Renderer, exc: BaseException, cfg: Optional[RenderConfig] = None,
                   capacity: Optional[int] = None, channels: Optional[list[str]] = None) -> Renderer:
    """The next working tier after ``renderer`` failed with ``exc`` (device lost, pipeline
    error). The failed renderer is closed; the reasons are logged and kept on the new
    renderer's ``selection_log``. Raises RenderError when no later tier starts (the cpu
    tier has nothing after it)."""
    cfg = cfg or renderer.cfg
    capacity = renderer.capacity if capacity is None else capacity
    channels = renderer.channels if channels is None else channels
    lines = [f"{renderer.tier}: failed mid-run ({_describe(exc)}); falling back"]
    try:
        renderer.close()
    except Exception as cexc:  # noqa: BLE001 - a lost device may not close cleanly
        lines.append(f"{renderer.tier}: close failed ({_describe(cexc)})")
    if renderer.tier == "cpu" and getattr(renderer, "raster", None) == "compute":
        tiers = ["cpu"]  # the compiled raster failed: the float64 reference is left
    else:
        tiers = next_tiers(renderer.tier)
        if tiers:
            tiers = _expand(tiers, cfg, False, lines)
    if not tiers:
        for line in lines:
            log.error("tier fallback: %s", line)
        raise RenderError(f"{renderer.tier} tier failed and no tier is left after it: {_describe(exc)}") from exc
    r = _try(tiers, cfg, capacity, channels, lines)
    r.selection_log = list(lines)  # type: ignore[attr-defined]
    return r
