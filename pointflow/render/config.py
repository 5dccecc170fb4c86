"""The ``render:`` section: tier, size, colour, camera, output, eye-dome lighting (the
loader, pointflow/config.py, assembles it; docs/config.md lists the keys).

Imports nothing of the render package, so the loader can assemble it without loading a tier.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import ClassVar, Literal, Optional, Union

from ..stage.endpoints import Endpoint
from ..typed import Bound, ConfigError, Each, Length, at_least_one, check, non_negative, positive


#: The render stage's links: requests to it (pick, save a frame; REP bound by render), the
#: transforms of a camera that follows a frame (only with ``frames.fixed``: PULL bound by
#: render, every source PUSHes the transforms it sends ingest here too), and the view
#: server's views (only with ``serve:``: ROUTER bound by render, DEALER of the view server).
ENDPOINTS = (Endpoint("render_commands", "render-commands", "requests to render (REP bound by render)"),
             Endpoint("view_transforms", "view-transforms", "sources -> render: transforms (PULL bound by render)"),
             Endpoint("views", "views", "view server <-> render (ROUTER bound by render)"))


@dataclass
class CameraConfig:
    """``position``/``target`` in world coordinates; ``auto`` frames the ring's contents."""

    #: The cross-option rule of _check_semantics, for the JSON Schema too.
    json_schema_extra: ClassVar[dict] = {"if": {"properties": {"mode": {"const": "fixed"}}, "required": ["mode"]},
                                         "then": {"required": ["position", "target"]}}

    mode: Literal["auto", "fixed", "orbit"] = "auto"
    position: Optional[list[float]] = field(default=None, metadata=check(Length(3), message="must be [x, y, z]"))
    target: Optional[list[float]] = field(default=None, metadata=check(Length(3), message="must be [x, y, z]"))
    up: list[float] = field(default_factory=lambda: [0.0, 0.0, 1.0], metadata=check(Length(3), message="must be [x, y, z]"))
    fov_deg: float = field(default=60.0, metadata=check(Bound(0, 180, lo_open=True, hi_open=True)))
    near: float = field(default=0.1, metadata=check(positive))
    far: float = field(default=10_000.0, metadata=check(positive))
    #: Degrees per second the auto/orbit camera turns around the scene (0 = still).
    orbit_deg_per_s: float = 0.0
    #: Elevation of the auto camera above the horizontal, degrees.
    elevation_deg: float = 35.0


@dataclass
class OutputConfig:
    dir: Optional[str] = "out"
    every_n_frames: int = field(default=30, metadata=check(at_least_one))
    #: Keep at most this many PNG files (oldest removed); 0 = all.
    keep_last: int = field(default=0, metadata=check(non_negative))


@dataclass
class EdlConfig:
    """Eye-dome lighting: darkens a pixel by how far its 8 neighbours lie in front of it in
    log2 depth (Potree's EDL; docs/render-tiers.md, "Eye-dome lighting"). Same formula in every tier."""

    enabled: bool = False
    #: Multiplies the 300 of ``shade = exp(-300 * strength * response)``; 0 = no darkening.
    strength: float = field(default=1.0, metadata=check(non_negative))
    #: Distance of the 8 neighbours in pixels (rounded per direction to whole pixels).
    radius_px: float = field(default=1.4, metadata=check(at_least_one))


@dataclass
class RenderConfig:
    backend: Literal["auto", "wgpu", "gl", "cpu"] = "auto"
    size: list[int] = field(default_factory=lambda: [1280, 720], metadata=check(
        Length(2), Each(Bound(1, 16384)), message="must be [width, height] with each in 1..16384"))
    color_by: Optional[str] = "intensity"
    colormap: Literal["turbo", "viridis", "grayscale"] = "turbo"
    #: ``auto`` or ``[lo, hi]``.
    color_range: Union[Literal["auto"], list[float]] = field(
        default="auto", metadata=check(Length(2), message="must be 'auto' or [lo, hi] with lo < hi"))
    color: list[float] = field(default_factory=lambda: [1.0, 1.0, 1.0], metadata=check(
        Length(3, 4), Each(Bound(0.0, 1.0)), message="must be 3 or 4 numbers in [0, 1]"))
    background: list[float] = field(default_factory=lambda: [0.02, 0.02, 0.05], metadata=check(
        Length(3, 4), Each(Bound(0.0, 1.0)), message="must be 3 or 4 numbers in [0, 1]"))
    point_size: float = field(default=2.0, metadata=check(positive))
    point_size_space: Literal["screen", "world"] = "screen"
    point_shape: Literal["square", "round"] = "square"
    camera: CameraConfig = field(default_factory=CameraConfig)
    time_window_ms: float = field(default=0.0, metadata=check(non_negative))
    lod_stride: int = field(default=1, metadata=check(at_least_one))
    #: Footprint LOD (off at 0): a batch of ring slots whose box covers few pixels keeps about
    #: this many points per point-sized cell of its box on screen, by a power-of-two stride per
    #: batch (render/batches.py ``lod_masks``; e.g. 2: a far batch draws a half or less of the
    #: points that could show). Every tier draws the same points.
    lod_fill: float = field(default=0.0, metadata=check(non_negative))
    importance_sampling: bool = False
    power_preference: Literal["high-performance", "low-power"] = "high-performance"
    output: OutputConfig = field(default_factory=OutputConfig)
    window: bool = False
    pick_radius: int = field(default=8, metadata=check(non_negative))
    pick_strategy: Literal["nearest", "highest_importance", "recent_first"] = "nearest"
    #: Below this many points ``auto`` uses the cpu tier; ``auto`` reads the measured value.
    cpu_crossover_points: Union[Literal["auto"], int] = field(
        default="auto", metadata=check(non_negative, message="must be >= 0 or 'auto'"))
    gpu_timestamps: bool = True
    #: wgpu tier: ``compute`` (atomic per-pixel keys), ``quads`` (instanced-quad draw) or
    #: ``auto`` (compute where it measured faster; see docs/render-wgpu.md). cpu tier:
    #: ``compute`` (compiled, numba) or ``reference`` (float64 numpy; also what an explicit
    #: ``backend: cpu`` with ``auto`` draws); docs/render-tiers.md.
    raster: Literal["auto", "compute", "quads", "reference"] = "auto"
    #: Eye-dome lighting (depth cue for clouds without normals); off by default.
    edl: EdlConfig = field(default_factory=EdlConfig)


#: The largest screen-space point size, in pixels (a point's raster cost grows with its
#: area: docs/views.md "Safe by default"); the view control messages take the same bound.
MAX_SCREEN_POINT_PX = 32.0


def check_render(r: RenderConfig) -> None:
    """What relates two values of the section (single bounds are on the fields)."""
    if isinstance(r.color_range, list) and not r.color_range[0] < r.color_range[1]:
        raise ConfigError("render.color_range", f"must be 'auto' or [lo, hi] with lo < hi, got {r.color_range!r}")
    if r.point_size_space == "screen" and r.point_size > MAX_SCREEN_POINT_PX:
        raise ConfigError("render.point_size", f"must be at most {MAX_SCREEN_POINT_PX:g} px (screen space), "
                          f"got {r.point_size:g}")
    c = r.camera
    if c.near >= c.far:
        raise ConfigError("render.camera.near", f"must be less than camera.far ({c.far}), got {c.near}")
    if c.mode == "fixed" and (c.position is None or c.target is None):
        raise ConfigError("render.camera.position", "camera.mode fixed needs position and target")
    if r.backend == "wgpu" and r.raster == "reference":
        raise ConfigError("render.raster", "'reference' is a method of the cpu tier; backend wgpu takes auto, "
                          "compute or quads (or use backend: cpu)")
