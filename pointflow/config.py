"""Pipeline configuration: YAML → typed, validated dataclasses.

Every error names the key path (``render.size[0]``) and what was expected, and is
raised at load time, before any process starts. Transport options are validated by
the transport's own ``options_schema`` (see :mod:`pointflow.ingest.transports`).
"""
from __future__ import annotations

import dataclasses
import os
import secrets
import stat
import tempfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Optional

import yaml

from .cadence.config import ENDPOINTS as CADENCE_ENDPOINTS, CadenceConfig, PolicyConfig
from .frames.config import FramesConfig, check_frames
from .ingest.config import ENDPOINTS as INGEST_ENDPOINTS, IngestConfig, SourceConfig
from .ingest.playback import ENDPOINTS as PLAYBACK_ENDPOINTS, PlaybackConfig, check_playback
from .ingest.transports import resolve_transport
from .record.config import ENDPOINTS as RECORD_ENDPOINTS, RecordConfig, check_record
from .map.config import ENDPOINTS as MAP_ENDPOINTS, MapConfig, check_map
from .serve.config import ServeConfig, check_serve
from .remote.options import SendConfig, check_send, is_loopback_endpoint
from .remote.zenoh_options import RouterConfig, check_router
from .profiling.config import TracingConfig
from .render.config import ENDPOINTS as RENDER_ENDPOINTS, CameraConfig, EdlConfig, OutputConfig, RenderConfig, check_render
from .render.view.protocol import BUILTIN_COLOR
from .ring.config import RingConfig, check_ring
from .stage.supervision import ENDPOINTS as SUPERVISOR_ENDPOINTS, SupervisorConfig
from .stage.endpoints import Endpoint
from .typed import ConfigError, check, check_keys, dataclass_schema, endpoint, load_dataclass

__all__ = ["ConfigError", "PipelineConfig", "load_config", "json_schema", "new_run_dir",
           # the sections, each defined in its package, assembled here
           "SourceConfig", "RingConfig", "IngestConfig", "CadenceConfig", "PolicyConfig", "RenderConfig", "CameraConfig",
           "OutputConfig", "EdlConfig", "EndpointsConfig", "TracingConfig", "SupervisorConfig", "SendConfig",
           "FramesConfig", "RecordConfig", "RouterConfig", "PlaybackConfig"]


# --------------------------------------------------------------------------- sections
#: Every link between stages, each declared beside its stage's section (``ENDPOINTS``).
ENDPOINTS: tuple[Endpoint, ...] = (*SUPERVISOR_ENDPOINTS, *INGEST_ENDPOINTS, *CADENCE_ENDPOINTS, *RENDER_ENDPOINTS,
                                   *RECORD_ENDPOINTS, *PLAYBACK_ENDPOINTS, *MAP_ENDPOINTS)

#: The ``endpoints:`` section: one optional ZeroMQ endpoint per link (``None`` = ``ipc://``
#: in the run dir), made from the declarations, and ``insecure``: allow these (unencrypted)
#: endpoints on a non-loopback tcp:// address.
EndpointsConfig = dataclasses.make_dataclass(
    "EndpointsConfig",
    [(e.name, Optional[str], field(default=None, metadata=check(endpoint))) for e in ENDPOINTS]
    + [("insecure", bool, field(default=False))],
    namespace={"__module__": __name__,
               "__doc__": "ZeroMQ endpoints of the links between stages; ``None`` = ``ipc://`` in the run dir."})


@dataclass
class PipelineConfig:
    sources: list[SourceConfig]
    name: str = "pointflow"
    ring: RingConfig = field(default_factory=RingConfig)
    ingest: IngestConfig = field(default_factory=IngestConfig)
    cadence: CadenceConfig = field(default_factory=CadenceConfig)
    policy: PolicyConfig = field(default_factory=PolicyConfig)
    render: RenderConfig = field(default_factory=RenderConfig)
    endpoints: EndpointsConfig = field(default_factory=EndpointsConfig)  # type: ignore[valid-type]
    tracing: TracingConfig = field(default_factory=TracingConfig)
    supervisor: SupervisorConfig = field(default_factory=SupervisorConfig)
    #: Where ``pointflow send`` publishes the sources (docs/remote.md); unused by ``run``.
    send: Optional[SendConfig] = None
    #: Put every point in one fixed frame at ingest (docs/frames.md); absent = points as sent.
    frames: FramesConfig = field(default_factory=FramesConfig)
    #: Record what ingest accepted to MCAP (docs/record.md); also ``pointflow run --record PATH``.
    record: Optional[RecordConfig] = None
    #: A big static cloud drawn with the live points (docs/map.md): the map stage serves it.
    map: Optional[MapConfig] = None
    #: The Zenoh router ``pointflow router`` runs (docs/remote.md); a file may hold only this.
    router: Optional[RouterConfig] = None
    #: How replaying sources (file, rosbag) start: ``start``, ``rate``, ``loop``, ``paused``
    #: (``pointflow run --start/--rate/--loop``); steer them later with ``Pipeline.playback``.
    playback: PlaybackConfig = field(default_factory=PlaybackConfig)
    #: A view to start from (``Pipeline.save_view`` writes one): ``camera`` (fit, or
    #: eye/target/up/fov_deg) and ``style``; applied over ``render`` at load (render/view/protocol.py).
    view: Optional[dict[str, Any]] = None
    #: The view server (docs/views.md): a page and a WebSocket; also ``pointflow run --serve [HOST:]PORT``.
    serve: Optional[ServeConfig] = None
    #: Where the YAML came from (for relative paths in options); not a YAML key.
    base_dir: str = field(default=".", metadata={"internal": True})

    # ------------------------------------------------------------------ derived
    def ring_channels(self) -> list[str]:
        """Only the channels this pipeline uses (render colour, importance, extras)."""
        names: list[str] = []
        cb = self.render.color_by
        if cb and cb not in BUILTIN_COLOR:
            names.append(cb)
        imp = self.ring.importance_field
        if imp and imp != "auto" and imp not in names:
            names.append(imp)
        if self.ring.classification_weights and "classification" not in names:
            names.append("classification")
        for c in self.ring.extra_channels:
            if c not in names:
                names.append(c)
        for c in (self.record.channels or []) if self.record is not None else []:
            if c not in names:
                names.append(c)
        if len(self.sources) > 1 and "source_index" not in names:  # per-source visibility (docs/api.md)
            names.append("source_index")
        return names

    def resolved_endpoints(self, run_dir: str) -> Any:
        """The :data:`EndpointsConfig` of a run: each link's own or ``ipc://`` in ``run_dir``."""
        e = self.endpoints
        return EndpointsConfig(**{x.name: getattr(e, x.name) or f"ipc://{os.path.join(run_dir, x.socket)}.sock"
                                  for x in ENDPOINTS})

    def to_dict(self) -> dict:
        d = dataclasses.asdict(self)
        d.pop("base_dir", None)
        return d


# --------------------------------------------------------------------------- loader
def _check_semantics(cfg: PipelineConfig) -> None:
    # Single-option bounds are declared on the fields (check(...)) and reach the JSON
    # Schema; only what relates two values is checked here.
    check_render(cfg.render)
    if not cfg.sources and cfg.router is None:
        raise ConfigError("sources", "at least one source is required")
    if cfg.router is not None:
        check_router(cfg.router, "router", cfg.base_dir)
    check_ring(cfg.ring)
    seen = set()
    named = {s.name for s in cfg.sources if s.name}
    for i, s in enumerate(cfg.sources):
        p = f"sources[{i}]"
        if not s.name and s.transport == "api" and "api" not in named:
            s.name = "api"  # the name Pipeline.send(source="api") feeds by default
            named.add("api")
        if not s.name:
            s.name = f"source{i}" if len(cfg.sources) > 1 else "source"
        if s.name in seen:
            raise ConfigError(f"{p}.name", f"duplicate source name {s.name!r}")
        seen.add(s.name)
        try:
            tcls = resolve_transport(s.transport)
        except ConfigError as exc:
            raise ConfigError(f"{p}.transport", str(exc)) from None
        s.options = tcls.validate_options(s.options, f"{p}.options", base_dir=cfg.base_dir)
    if cfg.send is not None:
        check_send(cfg.send, "send", cfg.base_dir)
    check_frames(cfg.frames, "frames")
    for i, s in enumerate(cfg.sources):
        if s.frame_id is not None and not s.frame_id.strip():
            raise ConfigError(f"sources[{i}].frame_id", "must be a frame name or null")
    if cfg.record is not None:
        check_record(cfg.record, "record")
    if cfg.map is not None:
        check_map(cfg.map, "map", cfg.base_dir)
        for i, src in enumerate(cfg.sources):
            if src.name == "map":  # the stage table is keyed by name
                raise ConfigError(f"sources[{i}].name", "'map' is the map stage's name: call the source otherwise")
    if cfg.serve is not None:
        check_serve(cfg.serve, "serve", cfg.base_dir)
    e = cfg.endpoints
    check_playback(cfg.playback, "playback")
    if cfg.view is not None:
        _apply_view(cfg)
    for key in (x.name for x in ENDPOINTS):
        ep = getattr(e, key)
        if ep and not e.insecure and not is_loopback_endpoint(ep):
            raise ConfigError(f"endpoints.{key}", f"{ep} is reachable from other hosts and the links between "
                              "stages have no encryption or authentication. To take points from another machine, "
                              "run `pointflow send` there and a zmq source with CURVE keys here (docs/remote.md); "
                              "or set endpoints.insecure: true")


#: ``render.color_by`` values that are not channels of the data (the view protocol's).
COLOR_BY_BUILTIN = BUILTIN_COLOR


def _check_color_by(cfg: PipelineConfig) -> None:
    """A ``color_by`` channel that no source has is refused when every source declares its
    channels (synthetic, file; ``Transport.declared_channels``); otherwise ingest names a
    source whose points lack it, once, and they are drawn in ``render.color``. The default,
    ``intensity``, is never refused: an xyz-only file is drawn in ``render.color``. With a
    ``map:`` block the map's channels count too: they are known once it opens."""
    cb = cfg.render.color_by
    if not cb or cb in COLOR_BY_BUILTIN or cb == RenderConfig.color_by or not cfg.sources \
            or getattr(cfg, "map", None) is not None:
        return
    have: set[str] = set()
    for s in cfg.sources:
        declared = None if s.external else resolve_transport(s.transport).declared_channels(s.options, cfg.base_dir)
        if declared is None:
            return  # known only when the points arrive
        have |= declared
    if cb not in have:
        import difflib

        v = cfg.view
        key = ("view.style.color_by" if isinstance(v, dict) and isinstance(v.get("style"), dict)
               and v["style"].get("color_by") == cb else "render.color_by")

        near = difflib.get_close_matches(cb, sorted(have) + list(COLOR_BY_BUILTIN), n=1)
        raise ConfigError(key, f"no source has a channel {cb!r}"
                          + (f" (did you mean {near[0]!r}?)" if near else "")
                          + f"; the sources' channels: {', '.join(sorted(have)) or 'none'}; or one of "
                          + ", ".join(COLOR_BY_BUILTIN[:3]) + ", or null for the single colour render.color")


def _apply_view(cfg: PipelineConfig) -> None:
    """Check the ``view:`` block and start the render config from it (so the ring keeps the
    channel it colours by)."""
    from .render.view.protocol import ControlError, load_view_block

    try:
        v = load_view_block(cfg.view, "view")
    except ControlError as exc:
        raise ConfigError(exc.key, exc.message) from None
    r = cfg.render
    st = v["style"]
    simple = {k: st[k] for k in ("color_by", "colormap", "color_range", "point_size", "point_shape", "time_window_ms")
              if k in st}
    edl = dataclasses.replace(r.edl, **{f: st[k] for k, f in (("edl", "enabled"), ("edl_strength", "strength"))
                                        if k in st})
    r = dataclasses.replace(r, edl=edl, **simple)
    names = [s.name for s in cfg.sources]
    for i, name in enumerate(v["hidden_sources"]):
        if name not in names:
            raise ConfigError(f"view.hidden_sources[{i}]", f"no source named {name!r}; sources: {', '.join(names)}")
    if v["camera"] is not None:
        c = v["camera"]
        r.camera = dataclasses.replace(r.camera, mode="fixed", position=c["eye"], target=c["target"],
                                       up=c.get("up", r.camera.up), fov_deg=c.get("fov_deg", r.camera.fov_deg))
    elif cfg.view.get("camera") == "fit":
        r.camera = dataclasses.replace(r.camera, mode="auto", position=None, target=None)
    cfg.render = r


def load_config(data: dict | str | os.PathLike, *, base_dir: str | None = None) -> PipelineConfig:
    """Load from a dict, a YAML file path. ``source:`` (one) and ``sources:`` (list) both work."""
    if isinstance(data, (str, os.PathLike)):
        path = Path(data)
        data = yaml_load(_read_text(path), path)
        base_dir = base_dir or str(path.resolve().parent)
    if data is None:
        data = {}
    if not isinstance(data, dict):
        raise ConfigError("", f"top level must be a mapping, got {type(data).__name__}")
    data = dict(data)
    check_keys(data, ["source"] + [f.name for f in dataclasses.fields(PipelineConfig) if not f.metadata.get("internal")], "")
    if "source" in data:
        if "sources" in data:
            raise ConfigError("source", "give either 'source' or 'sources', not both")
        data["sources"] = [data.pop("source")]
    if "sources" not in data and "router" in data:
        data["sources"] = []  # a router's file (`pointflow router`) needs no source
    if "sources" not in data and "map" in data:
        # a map on its own (docs/map.md): an idle api source, so the pipeline has its ring
        # (Pipeline.send can still add live points to it)
        data["sources"] = [{"transport": "api", "name": "api"}]
    if "sources" not in data:
        raise ConfigError("sources", "required key is missing (a 'source:' mapping or a 'sources:' list)")
    cfg = load_dataclass(PipelineConfig, data, "")
    cfg.base_dir = base_dir or os.getcwd()
    _check_semantics(cfg)
    _check_color_by(cfg)
    return cfg


#: A config file larger than this is refused unread.
MAX_CONFIG_BYTES = 16 << 20


#: Point files a new user may hand to ``pointflow run``, by suffix ...
_POINT_SUFFIXES = ((".copc.laz", "COPC"), (".las", "LAS"), (".laz", "LAZ"), (".ply", "PLY"), (".pcd", "PCD"),
                   (".npy", "NPY"), (".npz", "NPZ"), (".bin", "KITTI .bin"), (".csv", "CSV"), (".xyz", "XYZ"))
#: ... or by their first bytes (a point file renamed, or with no suffix)
_POINT_MAGIC = ((b"LASF", "LAS/LAZ"), (b"ply\n", "PLY"), (b"ply\r\n", "PLY"), (b"# .PCD", "PCD"),
                (b"\x93NUMPY", "NPY"), (b"PK\x03\x04", "NPZ"))


def point_file_kind(path: Path) -> Optional[str]:
    """"LAS", "PLY", ... when ``path`` is a point file (by its suffix or its first bytes), else None."""
    name = path.name.lower()
    for suffix, kind in _POINT_SUFFIXES:
        if name.endswith(suffix):
            return kind
    try:
        with open(path, "rb") as f:
            head = f.read(8)
    except OSError:
        return None
    return next((kind for magic, kind in _POINT_MAGIC if head.startswith(magic)), None)


def point_file_error(path: Path, kind: str) -> ConfigError:
    """A point file given where a pipeline config belongs: say so, and how to show it."""
    big = f" or, for a big static file, a `map: {{path: {path.name}}}` block beside a source (docs/map.md)"
    return ConfigError("", f"{path}: a {kind} point file, not a pipeline config (YAML); to show it, run a config "
                           f"that reads it, e.g. a YAML file beside it holding `source: {{transport: file, options: "
                           f"{{path: {path.name}}}}}` (streamed through the ring, like configs/autzen.yaml)"
                           + (big if kind in ("COPC", "LAS", "LAZ", "LAS/LAZ", "PLY", "PCD") else "")
                           + "; from Python: pointflow.show(positions)")


def _read_text(path: Path) -> str:
    """The config file as text; every failure is a one-line ConfigError naming the file."""
    try:
        st = os.stat(path)
        if stat.S_ISDIR(st.st_mode):
            raise ConfigError("", f"cannot read config file {path}: it is a directory")
        if not stat.S_ISREG(st.st_mode):  # a FIFO or device would block or never end
            raise ConfigError("", f"cannot read config file {path}: not a regular file")
        kind = point_file_kind(path)
        if kind is not None:  # before the size limit and UTF-8: a point file is neither too big nor mis-encoded
            raise point_file_error(path, kind)
        if st.st_size > MAX_CONFIG_BYTES:  # e.g. a point cloud given by mistake: not read into memory
            raise ConfigError("", f"{path}: {st.st_size:,} bytes is not a pipeline config (a YAML file of at most "
                                  f"{MAX_CONFIG_BYTES:,} bytes)")
        raw = path.read_bytes()
    except OSError as exc:
        raise ConfigError("", f"cannot read config file {path}: {exc.strerror or exc}") from None
    try:
        return raw.decode("utf-8")
    except UnicodeDecodeError as exc:
        line = raw.count(b"\n", 0, exc.start) + 1
        col = exc.start - (raw.rfind(b"\n", 0, exc.start) + 1) + 1
        raise ConfigError("", f"{path}: not UTF-8 text: byte 0x{raw[exc.start]:02x} at byte position {exc.start} "
                              f"(line {line}, column {col}); save the file as UTF-8") from None


def yaml_load(text: str, path: Path | str) -> Any:
    """``yaml.safe_load`` whose errors are one line: file, line, column and the problem."""
    try:
        return yaml.safe_load(text)
    except yaml.YAMLError as exc:
        if isinstance(exc, yaml.reader.ReaderError):
            ch = exc.character if isinstance(exc.character, int) else ord(exc.character)
            raise ConfigError("", f"{path}: invalid YAML: character #x{ch:04x} at character position "
                                  f"{exc.position} is not allowed in YAML ({exc.reason})") from None
        mark = getattr(exc, "problem_mark", None)
        where = f" at line {mark.line + 1}, column {mark.column + 1}" if mark is not None else ""
        what = getattr(exc, "problem", None) or " ".join(str(exc).split())
        ctx = getattr(exc, "context", None)
        raise ConfigError("", f"{path}: invalid YAML{where}: {what}" + (f" ({ctx})" if ctx else "")) from None


def new_run_dir() -> str:
    """A private directory for ipc:// sockets (owner-only)."""
    root = os.environ.get("XDG_RUNTIME_DIR") or tempfile.gettempdir()
    d = os.path.join(root, f"pointflow-{os.getpid()}-{secrets.token_hex(4)}")
    os.makedirs(d, mode=0o700)
    return d


# --------------------------------------------------------------------------- JSON Schema
def json_schema() -> dict:
    """A JSON Schema of the pipeline YAML, for editors (``pointflow schema``). Transport
    options are checked by each transport at load time and are free-form here."""
    s = dataclass_schema(PipelineConfig)
    s["$schema"] = "https://json-schema.org/draft/2020-12/schema"
    s["title"] = "pointflow pipeline"
    s["properties"]["source"] = s["properties"]["sources"]["items"]
    s.pop("required", None)
    s["oneOf"] = [{"required": ["source"]}, {"required": ["sources"]},
                  {"required": ["router"], "not": {"anyOf": [{"required": ["source"]}, {"required": ["sources"]}]}}]
    return s
