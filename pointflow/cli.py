"""``pointflow`` command line: run, profile, validate, info, schema, warm, send, router, keys."""
from __future__ import annotations

import argparse
import json
import logging
import os
import signal
import sys
import time
from typing import Optional

from .config import ConfigError, load_config

log = logging.getLogger("pointflow")


#: Exit code for every configuration or input-path error (nothing was started).
EXIT_CONFIG = 1

#: When the command started (the startup figures of ``--verbose`` count from here).
_T0 = time.monotonic()

DURATION_HELP = ("seconds the pipeline runs, counted from when every stage has reported in (starting the "
                 "stages comes before: interpreters, imports, a GPU device; it is printed as it happens), "
                 "so a run draws for that long however busy the machine; stopping comes after: usually "
                 "under a second, up to 5 s per stage wave when a stage is busy")


def config_error_line(exc: ConfigError, file: Optional[str] = None) -> str:
    """One line (ends in a newline when printed) naming the file and the key."""
    msg = " ".join(str(exc).split())  # a message from a library may span lines
    if file and file not in msg:
        msg = f"{file}: {msg}"
    return f"config error: {msg}"


def _out_dir(path: str) -> str:
    """Create the output directory up front, so a bad ``--out`` is a config error, not a traceback."""
    from .runtime.pipeline import prepare_out_dir

    return prepare_out_dir(path)


def summary_line(stats: dict) -> str:
    """One line: points in, in ring, frames, cadence, drops, CPU (the live view of ``pointflow run``)."""
    from .profiling.report import live_summary

    return live_summary(stats)


def starting_line(cfg, stages: list[str]) -> str:
    """What ``run`` starts, printed before anything is (starting the stages takes seconds:
    interpreters, imports, a GPU device); a line per stage follows as each reports in."""
    kinds = ", ".join(sorted({s.transport for s in cfg.sources}))
    return (f"starting {cfg.name}: {len(cfg.sources)} source{'s' * (len(cfg.sources) != 1)} ({kinds}), "
            f"ring {cfg.ring.max_points:,} points, render {cfg.render.backend} "
            f"{cfg.render.size[0]}x{cfg.render.size[1]}; stages {', '.join(stages)} ...")


def no_frame_reason(stats: dict) -> Optional[str]:
    """Why a run that has a render stage drew no frame, or None when it drew one (the render
    stage then leaves ``last.png``, besides every ``output.every_n_frames``-th frame). Said
    instead of pointing at an output folder with no frame in it."""
    stages = stats.get("stages", {})
    render = stages.get("render")
    if render is None:
        return None
    if render.get("pngs", 0) or render.get("frames", 0):  # a drawn frame is saved as last.png at the end
        return None
    ready = render.get("startup_ms", {}).get("ready")
    raster = render.get("raster")
    if not render.get("ready") or ready is None:
        return "no frame drawn: the render stage was still starting when the run stopped (it had not reported in)"
    if raster == "compiling":  # (not "compiled": a raster ready to draw)
        return f"no frame drawn: the render stage was still compiling its raster ({raster})"
    written = stats.get("accounting", {}).get("ingest_written", 0)
    if not written:
        sent = sum(v.get("points_out", 0) for v in stages.values() if v.get("kind") == "source")
        return f"no frame drawn: no point reached the ring (the sources sent {sent:,})"
    return f"no frame drawn: the render stage got no frame to draw ({written:,} points in the ring)"


def check_duration(args) -> None:
    """``--duration`` is a number of seconds > 0 (a typo such as ``-1`` or ``0`` is refused
    before anything starts)."""
    d = getattr(args, "duration", None)
    if d is not None and not (d > 0 and d != float("inf")):
        raise ConfigError("--duration", f"must be a number of seconds greater than 0, got {d:g}")


class _Stop:
    def __init__(self) -> None:
        self.flag = False
        self.signal: Optional[int] = None

    def __call__(self, signum, _frame) -> None:
        self.flag = True
        self.signal = signum


def _playback_flags(cfg, args) -> None:
    """``--start``/``--rate``/``--loop`` over the YAML's ``playback:`` block, checked like it."""
    import dataclasses

    from .ingest.playback import check_playback

    pb = dataclasses.replace(cfg.playback)
    for flag in ("start", "rate", "loop"):
        v = getattr(args, flag, None)
        if v is not None:
            setattr(pb, flag, v)
    if isinstance(pb.start, str) and not pb.start.strip().endswith("%"):
        try:
            pb.start = float(pb.start)
        except ValueError:
            raise ConfigError("--start", f"must be seconds or a percentage like 25%, got {pb.start!r}") from None
    try:
        check_playback(pb, "playback")
    except ConfigError as exc:
        key = exc.path.rpartition(".")[2]
        given = getattr(args, key, None) is not None
        raise ConfigError(f"--{key}" if given else exc.path, exc.message) from None
    cfg.playback = pb


def _run(args, profile: bool = False) -> int:
    from .runtime.pipeline import Pipeline

    cfg = load_config(args.file)
    if not cfg.sources:  # a file with only a router: block
        raise ConfigError("sources", f"{args.file} has no source, only a router: block; run it with "
                          f"`pointflow router {args.file}`")
    if getattr(args, "record", None):
        from .record.config import with_record_path

        cfg = with_record_path(cfg, args.record)
    if getattr(args, "serve", None):
        from .serve.config import with_serve

        try:
            cfg = with_serve(cfg, args.serve)
        except ValueError as exc:
            if isinstance(exc, ConfigError):
                raise
            raise ConfigError("--serve", str(exc).removeprefix("--serve: ")) from None
    _playback_flags(cfg, args)
    out_dir = _out_dir(args.out or cfg.render.output.dir or "out")
    if args.backend:
        os.environ["POINTFLOW_BACKEND"] = args.backend
    pipe = Pipeline(cfg, out_dir=out_dir)
    tty = sys.stderr.isatty() and not args.quiet
    if not args.quiet:  # at once: starting the stages takes seconds (interpreters, imports, GPU device)
        print(starting_line(cfg, pipe.stages()), file=sys.stderr, flush=True)
    stats, code, signum = _serve(pipe, args, 0.5 if tty else 5.0, summary_line, done=lambda: pipe.stop_requested,
                                 tty=tty, at_once=True)
    if signum is not None:
        log.info("stopped by %s", signal.Signals(signum).name)
    print(summary_line(stats))
    why = no_frame_reason(stats)
    if why is not None:
        print(why)
        print(f"stats.json in {os.path.abspath(out_dir)}")
    else:
        print(f"frames and stats.json in {os.path.abspath(out_dir)}")
    map_error = ((stats.get("stages") or {}).get("map") or {}).get("map_error")
    if map_error and code == 0:  # the live part ran, the map was never shown: not a success
        print(f"error: map not shown: {map_error}", file=sys.stderr, flush=True)
        code = 2
    if cfg.record is not None:
        from .record.inspect import record_summary

        print(record_summary(stats))
    if profile:
        from .profiling.report import format_table, write_profile

        prof = write_profile(out_dir, pipe.collector, stats)
        print(format_table(prof))
        print(f"profile.json, trace.json and latency.png in {os.path.abspath(out_dir)}")
    return code


def _serve(pipe, args, every_s: float, summary, done=lambda: False, tty: bool = False,
           at_once: bool = False) -> tuple[dict, int, "int | None"]:
    """Start ``pipe`` and poll it until Ctrl-C/SIGTERM, ``--duration`` (counted from when every
    stage has reported in) or ``done()``. Unless ``--quiet``, each stage is said as it reports
    in, then ``summary(stats)`` every ``every_s`` (the first ``at_once``; on a terminal,
    ``tty``, as one line written over). The signal handlers are restored and the pipeline
    stopped however it ends. Returns the final stats, the exit code (2 when the pipeline
    failed) and the signal that stopped it."""
    from .runtime.supervisor import PipelineFailed

    stop = _Stop()
    old = {s: signal.signal(s, stop) for s in (signal.SIGINT, signal.SIGTERM)}
    code = 0
    t_end = None
    said: set[str] = set()
    drawn = False  # a progress line is on the terminal (ended with a newline at the end)
    try:
        pipe.start(wait=False)
        t_spawn = time.monotonic()
        while pipe.starting and not stop.flag and not done():
            pipe.poll(0.05)
            if not args.quiet:
                _say_ready(pipe.stats()["stages"], said)
        pipe.poll(0)  # a stage that failed the run while starting: PipelineFailed, no "running"
        if not stop.flag:
            st = pipe.stats()["stages"]
            if not args.quiet:
                _say_ready(st, said)
                late = [n for n, v in st.items() if not (v.get("ready") or v.get("finished"))]
                print(f"running after {time.monotonic() - t_spawn:.1f} s"
                      + (f" (not reported in yet: {', '.join(late)})" if late else "")
                      + (f"; stopping in {args.duration:g} s" if args.duration is not None else ""),
                      file=sys.stderr, flush=True)
            log.debug("started in %.3f s from the command's start", time.monotonic() - _T0)
        t_end = None if args.duration is None else time.monotonic() + args.duration
        last_print = 0.0 if at_once else time.monotonic()
        while not stop.flag and not done() and (t_end is None or time.monotonic() < t_end):
            pipe.poll(0.05 if t_end is None else max(0.0, min(0.05, t_end - time.monotonic())))
            if not args.quiet and time.monotonic() - last_print >= every_s:
                last_print = time.monotonic()
                line = summary(pipe.stats())
                sys.stderr.write(("\r\033[K" + line) if tty else line + "\n")
                sys.stderr.flush()
                drawn = True
    except PipelineFailed:  # the supervisor printed why, once
        code = 2
    finally:
        if tty and drawn:
            sys.stderr.write("\n")
        for s, h in old.items():
            signal.signal(s, h)
        stats = pipe.stop()
    return stats, code, stop.signal


def _say_ready(stages: dict, said: set) -> None:
    """One line per stage as it reports in: its name and how long its start took."""
    for name, v in stages.items():
        if name in said or not (v.get("ready") or v.get("finished")):
            continue
        said.add(name)
        ms = v.get("startup_ms", {}).get("ready")
        print(f"ready: {name}" + (f" ({ms / 1000:.1f} s)" if ms is not None else " (in this process)"),
              file=sys.stderr, flush=True)


def _send(args) -> int:
    """``pointflow send``: run only the sources and publish them on ``send.endpoint``; ends
    when every source has ended, after ``--duration``, or on Ctrl-C."""
    from .remote.sender import send_summary
    from .runtime.pipeline import Pipeline

    cfg = load_config(args.file)
    if cfg.send is None:
        raise ConfigError("send", f"{args.file} has no 'send:' section saying where to publish "
                          "(endpoint, keys; see docs/remote.md and configs/remote-send.yaml)")
    out_dir = args.out
    pipe = Pipeline(cfg, out_dir=out_dir, role="send")

    def sources_done() -> bool:
        """Every source ended and the sender has taken all they sent (it may still be
        waiting for subscribers, with the chunks queued in its socket)."""
        st = pipe.stats()["stages"]
        srcs = [v for v in st.values() if v.get("kind") == "source"]
        snd = st.get("sender", {})
        taken = snd.get("points_in", 0) + snd.get("rejected_messages", 0)
        return all(v.get("finished") for v in srcs) and taken >= sum(v.get("points_out", 0) for v in srcs)

    stats, code, _ = _serve(pipe, args, 5.0, send_summary, done=sources_done)
    print(send_summary(stats))
    if out_dir:
        print(f"stats.json in {os.path.abspath(out_dir)}")
    return code


def _router(args) -> int:
    """``pointflow router``: run the config's Zenoh router (docs/remote.md) until
    ``--duration``, Ctrl-C or SIGTERM, printing its sessions every ``stats_every_s``."""
    from .remote.router_process import router_summary
    from .runtime.pipeline import Pipeline

    cfg = load_config(args.file)
    if cfg.router is None:
        raise ConfigError("router", f"{args.file} has no 'router:' section (listen endpoints, tls; see "
                          "docs/remote.md and configs/zenoh-router.yaml)")
    pipe = Pipeline(cfg, out_dir=args.out, role="router")
    stats, code, signum = _serve(pipe, args, cfg.router.stats_every_s, router_summary)
    if signum is not None:
        log.info("stopped by %s", signal.Signals(signum).name)
    print(router_summary(stats), flush=True)
    if args.out:
        print(f"stats.json in {os.path.abspath(args.out)}")
    return code


def _keys(args) -> int:
    from .remote.keys import KeyFileError, create_keypair

    if args.tls:
        from .remote.tls import TlsFileError, make_certificate

        try:
            made = make_certificate(args.name, args.dir, args.host, overwrite=args.force)
        except TlsFileError as exc:
            print(f"error: {exc}", file=sys.stderr)
            return 1
        print(("CA:          {ca} (new; give a copy to every host)" if made.ca_created else
               "CA:          {ca} (reused; it signed this certificate)").format(ca=made.ca))
        print(f"CA key:      {made.ca_key}  (signs certificates; keep it off the hosts, mode 0600)")
        print(f"certificate: {made.certificate}  (names: {', '.join(made.names)})")
        print(f"private key: {made.private_key}  (keep it on {args.name}; mode 0600)")
        return 0
    if args.host:
        print("error: --host names the hosts of a TLS certificate; add --tls", file=sys.stderr)
        return 1

    try:
        pub, sec = create_keypair(args.name, args.dir, overwrite=args.force)
    except KeyFileError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1
    print(f"public key: {pub}  (give this file to the peer)")
    print(f"secret key: {sec}  (keep it on this host; mode 0600)")
    return 0


def _validate(args) -> int:
    """What ``run`` (or, for a config with ``send:``, ``send``) would refuse here, refused here too."""
    cfg = load_config(args.file)
    if not cfg.sources:  # only a router: block
        r = cfg.router
        print(f"{args.file}: OK for `pointflow router` (listen {', '.join(r.listen)}"
              + (f", connect {', '.join(r.connect)}" if r.connect else "")
              + (", TLS" + (" with mutual authentication" if r.tls.mutual else "") if r.tls else ", no TLS") + ")")
    elif cfg.send is not None:  # a sensor host's file: `pointflow send` runs no ring, cadence or render
        s = cfg.send
        extras = [x for x in (s.compression if s.compression != "none" else "",
                              f"quantise {s.quantise:g} m" if s.quantise else "",
                              ("TLS" if s.zenoh.tls else "no TLS") if s.engine == "zenoh" else
                              "CURVE" if s.curve_secret_key else "no encryption") if x]
        if s.engine == "zenoh":  # docs/remote.md, "The Zenoh engine"
            where = ", ".join([f"listening on {x}" for x in s.zenoh.listen] + [f"connecting to {x}" for x in s.zenoh.connect])
            link = f"zenoh {s.zenoh.mode} publishing {s.key}/<source>, {where or 'no endpoints'}"
        else:
            link = f"{s.socket} {'bound on' if s.bind else 'connecting to'} {s.endpoint}"
        print(f"{args.file}: OK for `pointflow send` ({len(cfg.sources)} source(s), {link}, {', '.join(extras)})")
    else:
        need = _check_ring_space(cfg)
        print(f"{args.file}: OK ({len(cfg.sources)} source(s), ring {cfg.ring.max_points:,} points "
              f"({need / 2**20:,.0f} MiB of shared memory, free on this machine), "
              f"render {cfg.render.backend} {cfg.render.size[0]}x{cfg.render.size[1]})")
    if args.verbose:
        print(json.dumps(cfg.to_dict(), indent=2))
    return 0


def _check_ring_space(cfg) -> int:
    """The shared-memory check ``run`` makes before it starts anything (same message); the
    bytes the ring and its two slabs need."""
    from .ring.config import check_ring_space

    return check_ring_space(cfg.ring, cfg.ring_channels(),
                            note=" (checked on this machine, where `pointflow run` would refuse it)")


def _info(args) -> int:
    from .ingest.transports import available_transports

    print("transports:")
    for name, where in sorted(available_transports().items()):
        print(f"  {name:12s} {where}")
    print("render backends:")
    for name, status in probe_backends().items():
        print(f"  {name:12s} {status}")
    try:
        import wgpu

        print("wgpu adapters:")
        for a in wgpu.gpu.enumerate_adapters_sync():
            print(f"  {a.summary}")
    except Exception as exc:  # noqa: BLE001
        print(f"wgpu adapters: none ({type(exc).__name__}: {exc})")
    return 0


def probe_backends() -> dict[str, str]:
    """What each render tier would find here (without opening a window)."""
    out: dict[str, str] = {}
    try:
        import wgpu

        adapters = wgpu.gpu.enumerate_adapters_sync()
        out["wgpu"] = "available: " + "; ".join(a.summary for a in adapters) if adapters else "no adapter"
    except Exception as exc:  # noqa: BLE001 - report whatever broke
        out["wgpu"] = f"unavailable ({type(exc).__name__}: {exc})"
    try:
        import moderngl

        ctx = moderngl.create_standalone_context(backend="egl")
        out["gl"] = f"available: {ctx.info['GL_RENDERER']} (EGL)"
        ctx.release()
    except Exception as exc:  # noqa: BLE001
        out["gl"] = f"unavailable ({type(exc).__name__}: {exc})"
    try:
        from .render.select import cpu_summary

        out["cpu"] = "available: " + cpu_summary()
    except Exception:  # noqa: BLE001
        out["cpu"] = "available (numpy)"
    try:
        from .render.select import auto_summary

        out["auto"] = auto_summary()  # the decision a run makes, so it agrees with the cpu line
    except Exception as exc:  # noqa: BLE001
        out["auto"] = f"unknown ({type(exc).__name__}: {exc})"
    return out


def version_line() -> str:
    """``pointflow --version``: the package version and the Python running it."""
    from . import __version__

    return f"pointflow {__version__} (Python {sys.version.split()[0]}, {os.path.dirname(os.path.abspath(__file__))})"


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="pointflow", description="Stream live point clouds to the GPU.")
    p.add_argument("-v", "--verbose", action="store_true", help="debug logging")
    p.add_argument("--version", action="version", version=version_line())
    sub = p.add_subparsers(dest="cmd", required=True)
    for name, help_ in (("run", "run a pipeline"), ("profile", "run a pipeline and write profile.json, trace.json, latency.png")):
        r = sub.add_parser(name, help=help_)
        r.add_argument("file", help="pipeline YAML")
        r.add_argument("--duration", type=float, default=None if name == "run" else 10.0,
                       help=DURATION_HELP + ("; default: until Ctrl-C" if name == "run" else "; default 10"))
        r.add_argument("--out", default=None, help="output directory (default: render.output.dir)")
        r.add_argument("--backend", choices=["auto", "wgpu", "gl", "cpu"], default=None, help="override render.backend")
        r.add_argument("-q", "--quiet", action="store_true", help="no live progress line")
        r.add_argument("--record", metavar="FILE.mcap", default=None,
                       help="record what ingest accepts to this MCAP file (docs/record.md)")
        r.add_argument("--serve", metavar="[HOST:]PORT", default=None,
                       help="serve the live view to a browser (docs/views.md); prints the view: URL to open")
        r.add_argument("--start", default=None, metavar="SECONDS|PCT%",
                       help="replays (file, rosbag) start here: seconds into the recording, or e.g. 25%%")
        r.add_argument("--rate", type=float, default=None, help="replays run this many times as fast as recorded")
        r.add_argument("--loop", action="store_true", default=None, help="replays start again at the end")
    v = sub.add_parser("validate", help="check a pipeline YAML without running it")
    v.add_argument("file")
    v.add_argument("--verbose", action="store_true", help="print the resolved config")
    sub.add_parser("info", help="list render backends, adapters and transports")
    sub.add_parser("schema", help="print the JSON Schema of the pipeline YAML (for editors)")
    sub.add_parser("warm", help="compile the numba loops (cpu raster, frames) for this machine, ahead of the first run")
    snd = sub.add_parser("send", help="run only the sources of a config and publish them on its send: endpoint")
    snd.add_argument("file", help="YAML with sources and a send: section")
    snd.add_argument("--duration", type=float, default=None,
                     help="seconds the sources run, counted from when every one has reported in; "
                          "default: until the sources end or Ctrl-C")
    snd.add_argument("--out", default=None, help="write stats.json here")
    snd.add_argument("-q", "--quiet", action="store_true", help="no progress lines")
    rt = sub.add_parser("router", help="run the Zenoh router of a config's router: section (docs/remote.md)")
    rt.add_argument("file", help="YAML with a router: section")
    rt.add_argument("--duration", type=float, default=None, help="seconds the router runs once it is up; default: until Ctrl-C")
    rt.add_argument("--out", default=None, help="write stats.json here")
    rt.add_argument("-q", "--quiet", action="store_true", help="no periodic session lines")
    ins = sub.add_parser("inspect", help="topics, messages, points and time range of an MCAP recording")
    ins.add_argument("file", help="an .mcap file")
    ins.add_argument("--recover", metavar="OUT.mcap", default=None,
                     help="rewrite a file cut short by a crash, with its summary, to OUT.mcap")
    k = sub.add_parser("keys", help="write a CURVE key pair NAME.key (public) and NAME.key_secret; with --tls a "
                                    "TLS certificate NAME.pem and key NAME-key.pem signed by DIR/ca.pem")
    k.add_argument("name")
    k.add_argument("--dir", default="keys", help="folder to write into (default: keys)")
    k.add_argument("--force", action="store_true", help="overwrite an existing pair")
    k.add_argument("--tls", action="store_true", help="a TLS certificate for Zenoh links instead (makes the CA "
                                                       "DIR/ca.pem the first time, reuses it after)")
    k.add_argument("--host", action="append", default=[], metavar="NAME_OR_IP",
                   help="with --tls: a host name or IP address the certificate is valid for (repeat; "
                        "default: localhost and 127.0.0.1)")
    return p


#: Exit code when the reader of our output went away (``| head -1``, ``| grep -q``): 128 + SIGPIPE,
#: what a shell reports for any writer whose reader left (``yes | head -1``).
EXIT_PIPE = 128 + int(signal.SIGPIPE)


def main(argv: Optional[list[str]] = None) -> int:
    """The ``pointflow`` command. A reader that stops early ends it quietly: the pipeline (if
    any) is stopped as on Ctrl-C, nothing more is printed, and the exit code is :data:`EXIT_PIPE`."""
    try:
        try:
            return _main(argv)
        finally:  # also after --help/--version (SystemExit): a closed pipe shows here, not at exit
            sys.stdout.flush()
            sys.stderr.flush()
    except BrokenPipeError:
        _drop_closed_output()
        return EXIT_PIPE


def _drop_closed_output() -> None:
    """Point stdout and stderr at /dev/null, so the interpreter's last flush of what is still
    buffered for a closed pipe neither fails nor prints."""
    try:
        devnull = os.open(os.devnull, os.O_WRONLY)
    except OSError:
        return
    for stream in (sys.stdout, sys.stderr):
        try:
            os.dup2(devnull, stream.fileno())
        except (OSError, ValueError, AttributeError):
            pass
    os.close(devnull)


def parse_args(parser: argparse.ArgumentParser, argv: Optional[list[str]]) -> argparse.Namespace:
    """``parser.parse_args``, except that an unknown flag after a command is refused by that
    command's parser (its usage, not the top level's), with the closest flag it has."""
    import difflib

    argv = list(sys.argv[1:] if argv is None else argv)
    args, extra = parser.parse_known_args(argv)
    if extra:
        sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
        before = argv.index(extra[0]) < argv.index(args.cmd) if extra[0] in argv and args.cmd in argv else False
        cmd = parser if before else sub.choices[args.cmd]
        flags = [o for a in cmd._actions for o in a.option_strings if o.startswith("--")]
        near = difflib.get_close_matches(extra[0].split("=")[0], flags, n=1, cutoff=0.75)
        cmd.error(f"unrecognized arguments: {' '.join(extra)}" + (f" (did you mean {near[0]}?)" if near else ""))
    return args


def _main(argv: Optional[list[str]] = None) -> int:
    global _T0
    _T0 = time.monotonic()
    # before any graphics library loads: without a valid XDG_RUNTIME_DIR (ssh, cron,
    # containers) each adapter probe prints "error: XDG_RUNTIME_DIR is invalid or not set"
    from .runtime.rundir import ensure_runtime_dir

    ensure_runtime_dir()
    args = parse_args(build_parser(), argv)
    from .stage.console import setup_logging

    setup_logging(logging.DEBUG if args.verbose and args.cmd != "validate" else logging.INFO,
                  "%(asctime)s %(name)s %(levelname)s %(message)s")
    try:
        check_duration(args)
        if args.cmd == "run":
            return _run(args)
        if args.cmd == "profile":
            return _run(args, profile=True)
        if args.cmd == "validate":
            return _validate(args)
        if args.cmd == "info":
            return _info(args)
        if args.cmd == "send":
            return _send(args)
        if args.cmd == "router":
            return _router(args)
        if args.cmd == "keys":
            return _keys(args)
        if args.cmd == "inspect":
            from .record.inspect import inspect_main

            return inspect_main(args.file, args.recover)
        if args.cmd == "warm":
            from .jitcache import warm_all

            return 0 if warm_all(lambda line: print(f"warm: {line}", flush=True)) else 1
        if args.cmd == "schema":
            from .config import json_schema

            print(json.dumps(json_schema(), indent=2))
            return 0
    except ConfigError as exc:
        print(config_error_line(exc, getattr(args, "file", None)), file=sys.stderr, flush=True)
        return EXIT_CONFIG
    return 0


if __name__ == "__main__":
    sys.exit(main())
