"""The ``map:`` block: a big static cloud (COPC, LAS/LAZ, PLY, PCD) served by the map stage
and drawn in the same frame as the live ring (docs/map.md). Only :mod:`pointflow.typed` is
imported here, so ``pointflow.config`` can hold a :class:`MapConfig` without an import cycle."""
from __future__ import annotations

import os
from dataclasses import dataclass, field
from typing import Optional, Union

from ..stage.endpoints import Endpoint
from ..typed import ConfigError, Length, at_least_one, check, positive


#: Map stage <-> render (only with ``map:``; docs/map.md): map region versions (PULL bound
#: by render) and the render stage's cameras and acknowledgements (PULL bound by the map stage).
ENDPOINTS = (Endpoint("map", "map", "map stage -> render: region versions (PULL bound by render)"),
             Endpoint("map_camera", "map-camera", "render -> map stage: cameras, acks (PULL bound by the map stage)"))


@dataclass
class MapConfig:
    """``map:``: the files, how many of their points a frame may draw, how much decoded data
    the map stage keeps."""

    #: One file or a list of files (relative to the config file's folder); required.
    path: Union[str, list[str]] = field(metadata=check(Length(1, 4096)))
    #: Points drawn from the map at most (Potree's default is 1 M): nodes are chosen by their
    #: projected size, coarse first, until their points reach this. Also the number of extra
    #: slots the render stage draws after the ring's.
    point_budget: int = field(default=1_000_000, metadata=check(at_least_one))
    #: Decoded nodes kept in the map stage's memory (least recently used go first).
    cache_mb: float = field(default=512.0, metadata=check(positive))
    #: Channels of the map to keep besides x, y, z; null = those the render stage uses
    #: (``color_by``, the ring's channels) that the file has.
    channels: Optional[list[str]] = None
    #: Where level-of-detail indexes are kept (relative to the config file's folder; made at
    #: load); null = the user cache directory.
    cache_dir: Optional[str] = None
    #: The length unit the views label the map with (grid, measures, height legend), e.g.
    #: ``m``, ``ft``, ``US ft``; null = from the files' CRS, else metres (docs/views.md "Units").
    units: Optional[str] = None
    #: Milliseconds the map stage spends loading before it hands over what it has (a
    #: camera move is shown refined step by step, coarse first).
    load_slice_ms: float = field(default=100.0, metadata=check(positive))

    def paths(self) -> list[str]:
        return [self.path] if isinstance(self.path, str) else list(self.path)


def check_map(mc: MapConfig, path: str, base_dir: str = ".") -> None:
    """Load-time checks: at least one file, each one there (resolved against the config's
    folder, in place). A file that is there but broken is the map stage's error, at run time,
    and the live part of the pipeline goes on."""
    paths = mc.paths()
    if not paths or any(not isinstance(p, str) for p in paths):
        raise ConfigError(f"{path}.path", "must name a map file (COPC, LAS, LAZ, PLY or PCD) or a list of them")
    out = []
    for i, p in enumerate(paths):
        key = f"{path}.path" if isinstance(mc.path, str) else f"{path}.path[{i}]"
        if not p.strip():
            raise ConfigError(key, "is empty")
        full = p if os.path.isabs(p) else os.path.normpath(os.path.join(base_dir, os.path.expanduser(p)))
        if not os.path.isfile(full):
            raise ConfigError(key, f"is a directory, not a point file: {full}" if os.path.isdir(full)
                              else f"no such file: {full}")
        why = not_a_point_file(full)
        if why:
            raise ConfigError(key, why)
        out.append(full)
    if len(set(out)) != len(out):
        raise ConfigError(f"{path}.path", "names the same file twice")
    mc.path = out[0] if isinstance(mc.path, str) else out
    if mc.cache_dir is not None:
        mc.cache_dir = _check_cache_dir(mc.cache_dir, f"{path}.cache_dir", base_dir)
    if mc.units is not None and (len(mc.units) > 16 or not mc.units.isprintable()):
        raise ConfigError(f"{path}.units", f"expected a short unit label such as m, ft or US ft, got {mc.units!r}")
    for i, c in enumerate(mc.channels or []):
        if c in ("x", "y", "z"):
            raise ConfigError(f"{path}.channels[{i}]", "x, y, z are always kept; list only channels")


def _check_cache_dir(d: str, key: str, base_dir: str) -> str:
    """The index folder, resolved against the config's folder as ``path`` is, and made now:
    one that cannot be (a file in the way, no permission, /proc) is the key's error at load,
    not an OSError when the map opens."""
    if not isinstance(d, str) or not d.strip():
        raise ConfigError(key, "must name a folder (or be left out: the user cache directory)")
    full = d if os.path.isabs(d) else os.path.normpath(os.path.join(base_dir, os.path.expanduser(d)))
    if os.path.exists(full) and not os.path.isdir(full):
        raise ConfigError(key, f"{full} exists and is not a folder")
    try:
        os.makedirs(full, exist_ok=True)
    except OSError as exc:
        raise ConfigError(key, f"cannot create {full}: {exc.strerror or exc}") from None
    if not os.access(full, os.W_OK | os.X_OK):
        raise ConfigError(key, f"{full} is not writable (the level-of-detail index is written there)")
    return full


#: What a map file's first bytes must be, by its extension (the index build reads the rest).
_MAGIC = {".las": (b"LASF",), ".laz": (b"LASF",), ".ply": (b"ply\n", b"ply\r\n")}


def not_a_point_file(path: str) -> Optional[str]:
    """Why ``path`` cannot be a map file (None: it may be): an extension that is not COPC, LAS,
    LAZ, PLY or PCD, a file that does not read, or first bytes that are not its format's. A file
    that passes and is broken further in is the map stage's error, at run time."""
    ext = os.path.splitext(path)[1].lower()
    if ext not in (".las", ".laz", ".ply", ".pcd"):
        return (f"not a point file (a map is COPC, LAS, LAZ, PLY or PCD): {path}" if ext
                else f"not a point file (no extension; a map is COPC, LAS, LAZ, PLY or PCD): {path}")
    try:
        with open(path, "rb") as f:
            head = f.read(4096)
    except OSError as exc:
        return f"cannot read {path}: {exc.strerror or exc}"
    if ext == ".pcd":
        lines = [ln.strip() for ln in head.split(b"\n") if ln.strip() and not ln.lstrip().startswith(b"#")]
        if not lines or not lines[0].split()[0] in (b"VERSION", b"FIELDS"):
            return f"not a PCD file (no VERSION or FIELDS header line): {path}"
    elif not head.startswith(_MAGIC[ext]):
        kind = "LAS/LAZ" if ext != ".ply" else "PLY"
        return (f"not a {kind} file (it is empty): {path}" if not head else
                f"not a {kind} file (it does not start with {_MAGIC[ext][0]!r}): {path}")
    elif ext in (".las", ".laz"):  # the header's counts and sizes against the file, before laspy trusts them
        from ..formats.base import FormatError
        from ..formats.las import precheck_las

        try:
            precheck_las(path)
        except FormatError as exc:
            return f"{exc.message}: {path}"
        except OSError as exc:
            return f"cannot read {path}: {exc.strerror or exc}"
    return None
