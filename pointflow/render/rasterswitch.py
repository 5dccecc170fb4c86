"""The render stage's switch to the compiled cpu raster once its loops are compiled.

Why: the compiled raster's loops take ~18 s to compile on an idle 2-core machine (30-50 s
under load). When they are not in numba's disk cache, tier selection takes the next tier
(``compiled_pending`` on the renderer, :mod:`.select`); this starts the compiler in a process
of its own (:func:`pointflow.jitcache.start_compiler`, detached: it finishes filling the cache
even when the run ends first), watches it between frames, and hands the stage a compiled
renderer when the cache holds every loop. The stage swaps it in between two frames.

The state shows in the render stage's stats as ``raster``: ``compiled`` (the compiled raster
draws), ``compiling`` (it will; ``raster_meanwhile`` names the tier drawing until then),
``reference`` (the float64 numpy raster draws, nothing on its way) or ``gpu`` (a GPU tier);
after a switch ``raster_switched_after_s`` (since the stage started) and
``raster_switched_at_frame`` (frames drawn before it).
"""
from __future__ import annotations

import time
from typing import Any, Optional

from .base import Renderer

#: how often the stage looks at the compiler (a lock probe and an index read)
POLL_S = 0.5


def raster_of(renderer: Renderer) -> str:
    """``compiled``, ``reference`` or ``gpu``: what draws with this renderer."""
    if renderer.tier == "cpu":
        return "compiled" if getattr(renderer, "raster", None) == "compute" else "reference"
    return "gpu"


class RasterSwitch:
    """Compile beside the stage, switch when ready (see the module docstring)."""

    def __init__(self, renderer: Renderer, log):
        self.log = log
        self.t0 = time.monotonic()
        self.where: Optional[str] = None
        self.proc: Any = None
        self.switched_after_s: Optional[float] = None
        self.switched_at_frame = 0  # frames drawn before the switch (the stage sets it)
        self._next = 0.0
        pending = getattr(renderer, "compiled_pending", None)
        self.raster = raster_of(renderer)
        self.meanwhile = renderer.tier
        if pending == "unwritable":
            from . import cpu_kernels

            log.warning("render: numba cannot cache the compiled raster's loops (%s); drawing with %s "
                        "(set NUMBA_CACHE_DIR to a writable directory and run `pointflow warm`)",
                        cpu_kernels.cache_dir() or "no writable location", renderer.tier)
        elif pending == "missing":
            self._start(renderer)

    def _start(self, renderer: Renderer) -> None:
        from .. import jitcache
        from . import cpu_kernels
        from .cpu_compute import COMPILE_TARGET

        self.where = cpu_kernels.cache_dir()
        if self.where is None:
            return
        self.raster = "compiling"
        if cpu_kernels.cache_state() == jitcache.READY:  # compiled since (a standby's renderer): switch at once
            return
        if jitcache.compiling(self.where):
            self.log.info("render: raster kernels are being compiled by another run (%s); drawing with %s meanwhile",
                          self.where, renderer.tier)
            return
        try:
            self.proc = jitcache.start_compiler(COMPILE_TARGET, self.where)
        except OSError as exc:
            self.log.warning("render: could not start the raster compiler (%s); drawing with %s", exc, renderer.tier)
            self.raster = raster_of(renderer)
            return
        self.log.info("render: compiling raster kernels in the background (first run on this machine; cache %s, "
                      "compiler pid %d); drawing with %s meanwhile", self.where, self.proc.pid, renderer.tier)

    def stats(self) -> dict:
        compiling = self.raster == "compiling"
        d: dict[str, Any] = {"raster": self.raster, "raster_meanwhile": self.meanwhile if compiling else None}
        if self.proc is not None:
            d["raster_compiler_pid"] = self.proc.pid
        if self.switched_after_s is not None:
            d["raster_switched_after_s"] = round(self.switched_after_s, 2)
            d["raster_switched_at_frame"] = self.switched_at_frame
        return d

    def follow(self, renderer: Renderer) -> None:
        """The stage drew with a new renderer (a style, a fallback): say what draws now."""
        if self.raster != "compiling" or raster_of(renderer) == "compiled":
            self.raster = raster_of(renderer)
        self.meanwhile = renderer.tier
        if self.raster != "compiling" and getattr(renderer, "compiled_pending", None) == "missing":
            self._start(renderer)  # a fallback renderer chosen while the loops were not compiled

    def poll(self, renderer: Renderer, capacity: int, channels: list[str]) -> Optional[Renderer]:
        """A compiled renderer to draw the next frame with, once the cache is filled; else None."""
        if self.raster != "compiling":
            return None
        now = time.monotonic()
        if now < self._next:
            return None
        self._next = now + POLL_S
        from .. import jitcache
        from . import cpu_kernels

        assert self.where is not None
        if (self.proc is not None and self.proc.poll() is None) or jitcache.compiling(self.where):
            return None
        if cpu_kernels.cache_state() != jitcache.READY:
            res = jitcache.last_result(self.where) or {}
            code = self.proc.returncode if self.proc is not None else None
            self.log.warning("render: the compiled raster could not be compiled (%s); drawing with %s",
                             res.get("message") or f"compiler exit code {code}", renderer.tier)
            self.raster = raster_of(renderer)
            return None
        from .cpu_compute import CpuComputeRenderer

        try:
            new = CpuComputeRenderer(renderer.cfg, capacity, channels)
        except Exception as exc:  # noqa: BLE001 - keep drawing with what draws
            self.log.warning("render: the compiled raster could not start (%s); drawing with %s", exc, renderer.tier)
            self.raster = raster_of(renderer)
            return None
        self.switched_after_s = now - self.t0
        self.raster = "compiled"
        self.log.info("render: raster kernels compiled; switching from %s to the compiled raster (%.1f s after start)",
                      renderer.tier, self.switched_after_s)
        return new
