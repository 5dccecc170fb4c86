"""The interface between the wgpu tier's core and its raster methods.

The core (:class:`..renderer.WgpuRenderer`) owns the device, the point data buffers (two
sets, uploaded incrementally), the per-frame ``Params``, the counters and the readback. A
raster method turns that into an image: it is created once with a :class:`Gpu` (everything it
may use, as public fields), then per frame :meth:`RasterMethod.encode` records its passes for a
:class:`FramePlan`; :meth:`RasterMethod.pick_block` answers picks from the last frame and
:meth:`RasterMethod.close` frees what it made. Methods never see the core itself.
"""
from __future__ import annotations

import abc
import math
from dataclasses import dataclass, field
from typing import Any, ClassVar, Optional

import numpy as np

from ...config import RenderConfig
from .. import sources
from ..layout import PARAMS_DTYPE


@dataclass(eq=False)
class Gpu:
    """What the core shares with a raster method."""
    wgpu: Any
    device: Any
    cfg: RenderConfig
    width: int
    height: int
    capacity: int                    #: render capacity (slots the tier draws)
    cmode: int                       #: layout.ColourMode of the tier
    naive_float32: bool
    key64: bool                      #: 64-bit atomics were granted (compute method)
    max_groups: int                  #: workgroups per dispatch dimension
    row_bytes: int                   #: readback pitch (256-byte aligned rows of RGBA8)
    sets: list[list[dict[str, Any]]]  #: per buffer set, per chunk: pos, tms, imp, col storage buffers
    params: Any                      #: the Params uniforms, one per segment (:meth:`params_at`)
    state: Any                       #: per segment 16 counter words (+ draw-indirect args in 0..3)
    rng: Any                         #: colour range reduced on the GPU (ord_f min, max); words 4, 5: see cull.wgsl
    dargs: Any                       #: dispatch-indirect args
    lut: Any                         #: 256 RGBA8 colormap entries
    timestamps: Optional[Any] = None  #: query set of 4 (pass 1 begin/end, pass 2 begin/end) or None
    chunks: list[tuple[int, int]] = field(default_factory=lambda: [(0, 1)])  #: (first slot, slots) per chunk
    max_segments: int = 1            #: segments a frame can have (params/state windows)
    compact: Optional[Any] = None    #: :class:`..compact.CompactPositions` (compute method) or None
    blod: Optional[Any] = None       #: the footprint LOD's mask per batch of slots (u32; batches.lod_masks)

    #: bytes between segments' Params records / state words (a multiple of every offset alignment)
    PARAMS_STRIDE: ClassVar[int] = 512
    STATE_STRIDE: ClassVar[int] = 256

    @property
    def chunk_len(self) -> int:
        """Slots of the largest chunk (the size of per-chunk and per-segment scratch)."""
        return max(n for _, n in self.chunks)

    def params_at(self, i: int) -> dict[str, Any]:
        """Binding resource: segment ``i``'s Params record."""
        return {"buffer": self.params, "offset": i * self.PARAMS_STRIDE, "size": PARAMS_DTYPE.itemsize}

    def state_at(self, i: int) -> dict[str, Any]:
        """Binding resource: segment ``i``'s 16 state words."""
        return {"buffer": self.state, "offset": i * self.STATE_STRIDE, "size": 64}

    @staticmethod
    def window(buf: Any, first: int, entry_bytes: int) -> dict[str, Any]:
        """Binding resource: ``buf`` from entry ``first`` to its end."""
        off = int(first) * int(entry_bytes)
        return {"buffer": buf, "offset": off, "size": buf.size - off}

    @property
    def queue(self) -> Any:
        return self.device.queue

    def buffer(self, size: int, usage: int, label: str) -> Any:
        return self.device.create_buffer(size=max(int(size), 16), usage=usage, label=label)

    def bind(self, layout: Any, resources: list[Any]) -> Any:
        """Bind group of whole buffers (or ready resource dicts) at bindings 0..n-1."""
        entries = []
        for i, x in enumerate(resources):
            res = {"buffer": x, "offset": 0, "size": x.size} if hasattr(x, "map_sync") else x
            entries.append({"binding": i, "resource": res})
        return self.device.create_bind_group(layout=layout, entries=entries)

    def layout(self, kinds: list[str], visibility: int, vis_of: Optional[dict[int, int]] = None) -> Any:
        """Bind group layout of buffers; kinds: 'uniform', 'read' or 'rw' per binding."""
        bt = self.wgpu.BufferBindingType
        t = {"uniform": bt.uniform, "read": bt.read_only_storage, "rw": bt.storage}
        vis_of = vis_of or {}
        return self.device.create_bind_group_layout(entries=[
            {"binding": i, "visibility": vis_of.get(i, visibility), "buffer": {"type": t[k]}}
            for i, k in enumerate(kinds)])

    def compute_pipeline(self, bgl: Any, files: tuple[str, ...], entry: str = "main",
                         label: str = "", **constants: object) -> Any:
        """A compute pipeline of ``files`` (see :mod:`..sources`) with override constants."""
        mod = self.device.create_shader_module(code=sources.source(*files), label=label or entry)
        stage: dict[str, Any] = {"module": mod, "entry_point": entry}
        if constants:
            stage["constants"] = sources.constants(**constants)
        return self.device.create_compute_pipeline(
            layout=self.device.create_pipeline_layout(bind_group_layouts=[bgl]), compute=stage)

    def data(self, s: int, chunk: int = 0) -> list[Any]:
        S = self.sets[s][chunk]
        return [S["pos"], S["tms"], S["imp"], S["col"]]

    def ts_writes(self, first: int) -> dict[str, Any]:
        """``timestamp_writes`` for a pass measured by queries ``first``, ``first + 1``."""
        if self.timestamps is None:
            return {}
        return {"timestamp_writes": {"query_set": self.timestamps, "beginning_of_pass_write_index": first,
                                     "end_of_pass_write_index": first + 1}}


@dataclass
class FramePlan:
    """One frame as the core planned it (also what picking and the tests look back at)."""
    set: int                 #: buffer set
    n_threads: int           #: logical indices walked (oldest first)
    groups: int              #: workgroups over them
    gx: int                  #: grid split (groups_x), gy rows
    gy: int
    budget_on: bool          #: the budget passes run
    budget_n: Optional[int]  #: the frame's budget
    head: int
    capacity: int
    params: np.ndarray = field(repr=False)  #: the Params record written this frame (segment 0's)
    segments: list[Any] = field(default_factory=list)  #: :class:`..chunks.Segment` s in logical order
    #: the runs of the segments left after batch culling (:func:`..chunks.runs`); empty: none culled
    runs: list[Any] = field(default_factory=list)

    @property
    def walk(self) -> list[Any]:
        """What the passes over points walk, in logical order: the runs that survive batch
        culling, or the segments. (Per-pixel passes run per segment.)"""
        return self.runs or self.segments


class RasterMethod(abc.ABC):
    """One way of rasterising the survivors (``render.raster``)."""
    name: ClassVar[str]
    #: logical indices one workgroup of the cull/raster pass covers (bounds a chunk's length)
    points_per_group: ClassVar[int] = 256
    #: the widest per-slot storage array of the method, and the entries of slack per chunk
    #: (they set how many slots a chunk may hold, see :mod:`..chunks`)
    slot_bytes: ClassVar[int] = 12
    pad_slots: ClassVar[int] = 0
    #: workgroup numbers run over the whole ring (group_base, groups_total of all segments)
    #: rather than over each segment
    global_groups: ClassVar[bool] = False

    @classmethod
    def wanted_features(cls, cfg: RenderConfig, key64: Optional[bool]) -> tuple[str, ...]:
        """Optional adapter features the method uses when all are offered."""
        return ()

    def __init__(self, gpu: Gpu):
        self.gpu = gpu

    def plan(self, n_threads: int, budget: Optional[int]) -> tuple[int, int, int, bool]:
        """(groups, gx, gy, budget_on) for a frame walking ``n_threads`` logical indices."""
        groups = max(1, math.ceil(n_threads / self.points_per_group))
        gx = min(groups, self.gpu.max_groups)
        return groups, gx, math.ceil(groups / gx), budget is not None

    @abc.abstractmethod
    def encode(self, enc: Any, plan: FramePlan) -> None:
        """Record the frame's passes (the core has written Params, state and rng)."""

    @abc.abstractmethod
    def copy_image(self, enc: Any, dst: Any) -> None:
        """Record a copy of the last image into ``dst`` (rows of ``gpu.row_bytes``)."""

    @abc.abstractmethod
    def pick_block(self, plan: FramePlan, x0: int, y0: int, bw: int, bh: int) -> tuple[np.ndarray, np.ndarray]:
        """(ids = slot + 1 or 0, attrs = depth, importance, t_hi, t_lo) of the block's
        front-most points in the last frame (syncs the GPU)."""

    @abc.abstractmethod
    def survivors(self, plan: FramePlan) -> np.ndarray:
        """Tests only (syncs the GPU): sorted slots the last frame draws."""

    def info(self) -> dict[str, Any]:
        return {}

    @abc.abstractmethod
    def close(self) -> None:
        """Free the method's buffers and textures."""


def destroy_all(objs) -> None:
    """Destroy buffers/textures, ignoring ones already gone (a lost device)."""
    for o in objs:
        if o is not None:
            try:
                o.destroy()
            except Exception:
                pass
