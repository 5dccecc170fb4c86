"""A fork server for the first start of the stages (``supervisor.fork_server``).

Every stage used to be a new interpreter importing numpy, zmq and pointflow by itself:
about 0.25 s of CPU each, and on a loaded 2-core machine the four to six of them starting
together spent 7-9 s each in that step alone (bench/bench_startup.py). Here one clean
interpreter (``python -m pointflow.runtime.forkserver``) imports those modules once (the
stage runtime, the config loader and the modules of the kinds this run has), before any
socket, thread, GPU handle or shared memory exists in it, and forks each stage from that
state: the stages stay fresh processes that share no socket, device or state with the
caller (nothing of the caller's ``__main__`` is ever imported), and start with their imports
done.

The protocol: the supervisor writes one pickled request per stage on the server's stdin
(length-prefixed); the server forks, and reports ``("pid", n)`` and later ``("exit", pid,
code)`` on a pipe of its own (its stdout stays the caller's, so the stages print where a
stage always printed). The server is the stages' parent: it asks for SIGTERM when the
supervisor dies (``PR_SET_PDEATHSIG``, as every stage does), so a killed supervisor takes it
and, through theirs, its stages with it; each forked stage checks that its parent is the
server (:attr:`RunInfo.parent_pid`). Restarts and standbys are started the usual way
(:func:`.launch.spawn_stage`): the server serves the first start, where the time goes.
"""
from __future__ import annotations

import os
import pickle
import select
import signal
import struct
import subprocess
import sys
import threading
from typing import Optional

from .launch import _PKG_PARENT, _ONE_THREAD

_LEN = struct.Struct("!I")


class ForkedStage:
    """A stage forked by the server: the part of :class:`.launch.StageProcess`'s interface
    the supervisor uses. Its exit code comes from the server, which reaps it."""

    standby = False

    def __init__(self, server: "ForkServer", pid: int):
        self._server = server
        self.pid = pid

    @property
    def exitcode(self) -> Optional[int]:
        return self._server.exitcode(self.pid)

    def is_alive(self) -> bool:
        return self.exitcode is None

    def _signal(self, sig: int) -> None:
        if self.exitcode is None:
            try:
                os.kill(self.pid, sig)
            except ProcessLookupError:
                pass

    def terminate(self) -> None:
        self._signal(signal.SIGTERM)

    def kill(self) -> None:
        self._signal(signal.SIGKILL)

    def join(self, timeout: Optional[float] = None) -> None:
        self._server.wait_exit(self.pid, timeout)

    def activate(self, info) -> bool:  # a forked stage is never a standby
        return False


class ForkServer:
    """The supervisor's end: start the server (it imports ``modules``), fork stages from it."""

    def __init__(self, modules: list[str], timeout_s: float = 30.0):
        env = dict(os.environ)
        env["PYTHONPATH"] = os.pathsep.join(p for p in (_PKG_PARENT, env.get("PYTHONPATH", "")) if p)
        for var in _ONE_THREAD:  # as launch.spawn_stage: one BLAS thread (and none to fork over)
            env.setdefault(var, "1")
        r, w = os.pipe()
        try:
            self._p = subprocess.Popen([sys.executable, "-m", "pointflow.runtime.forkserver", str(w), *modules],
                                       stdin=subprocess.PIPE, env=env, close_fds=True, pass_fds=(w,))
        finally:
            os.close(w)
        self._reports = os.fdopen(r, "rb")
        self._cond = threading.Condition()
        self._pids: list[int] = []
        self._exits: dict[int, int] = {}
        self._gone = False  # the server exited (its pipe closed)
        # it imports first: on a loaded machine seconds; one that never says it is ready is not used
        try:
            self.ready = bool(select.select([self._reports], [], [], timeout_s)[0]) and self._read() == ("ready",)
        except Exception:  # noqa: BLE001 - a server killed mid-write: start the stages the usual way
            self.ready = False
        if not self.ready:
            self.close()
            return
        self._reader = threading.Thread(target=self._read_loop, name="pointflow-forkserver", daemon=True)
        self._reader.start()

    def _read(self):
        head = self._reports.read(_LEN.size)
        if len(head) < _LEN.size:
            return None
        return pickle.loads(self._reports.read(_LEN.unpack(head)[0]))

    def _read_loop(self) -> None:
        while True:
            try:
                msg = self._read()
            except (OSError, ValueError, pickle.UnpicklingError, EOFError):
                msg = None
            with self._cond:
                if msg is None:
                    self._gone = True
                elif msg[0] == "pid":
                    self._pids.append(msg[1])
                elif msg[0] == "exit":
                    self._exits[msg[1]] = msg[2]
                self._cond.notify_all()
            if msg is None:
                return

    @property
    def alive(self) -> bool:
        return self.ready and not self._gone and self._p.poll() is None

    def spawn(self, name: str, kind, cfg_dict: dict, base_dir: str, info) -> Optional[ForkedStage]:
        """Fork a stage; None when the server cannot (it is gone): start it the usual way."""
        if not self.alive:
            return None
        payload = pickle.dumps((name, kind, cfg_dict, base_dir, info), protocol=pickle.HIGHEST_PROTOCOL)
        with self._cond:
            n = len(self._pids)
            try:
                self._p.stdin.write(_LEN.pack(len(payload)) + payload)
                self._p.stdin.flush()
            except (OSError, ValueError):
                return None
            if not self._cond.wait_for(lambda: len(self._pids) > n or self._gone, timeout=30):
                return None
            if len(self._pids) <= n:
                return None
            return ForkedStage(self, self._pids[n])

    def exitcode(self, pid: int) -> Optional[int]:
        with self._cond:
            if pid in self._exits:
                return self._exits[pid]
            if not self._gone:
                return None
        # the server is gone (killed): its stages got SIGTERM from the kernel; one that is
        # no longer there exited, how is not known
        try:
            os.kill(pid, 0)
            with open(f"/proc/{pid}/stat") as f:
                if f.read().rpartition(")")[2].split()[0] not in ("Z", "X"):
                    return None
        except (OSError, IndexError):
            pass
        return -signal.SIGTERM

    def wait_exit(self, pid: int, timeout: Optional[float]) -> None:
        with self._cond:
            self._cond.wait_for(lambda: pid in self._exits or self._gone, timeout=timeout)

    def close(self) -> None:
        """End the server (after its stages: a stage whose parent goes gets SIGTERM)."""
        try:
            if self._p.stdin and not self._p.stdin.closed:
                self._p.stdin.close()
        except OSError:
            pass
        try:
            self._p.wait(5)
        except subprocess.TimeoutExpired:
            self._p.kill()
            self._p.wait()
        with self._cond:
            self._gone = True
            self._cond.notify_all()
        reader = getattr(self, "_reader", None)
        if reader is not None and reader is not threading.current_thread():
            reader.join(1)
        try:
            self._reports.close()
        except OSError:
            pass


# ---------------------------------------------------------------------------- the server
def _send(fd: int, msg) -> None:
    data = pickle.dumps(msg, protocol=pickle.HIGHEST_PROTOCOL)
    os.write(fd, _LEN.pack(len(data)) + data)


def _read_exact(fd: int, n: int) -> bytes:
    """``n`` bytes from ``fd`` (unbuffered: ``select`` on it stays true to what is unread)."""
    out = b""
    while len(out) < n:
        part = os.read(fd, n - len(out))
        if not part:
            return out
        out += part
    return out


def _read_request(fd: int) -> Optional[tuple]:
    head = _read_exact(fd, _LEN.size)
    if len(head) < _LEN.size:
        return None
    return pickle.loads(_read_exact(fd, _LEN.unpack(head)[0]))


def _child(req: tuple, report_fd: int, server_pid: int) -> None:
    """In the forked stage: drop the server's pipes, check the parent, run the stage."""
    code = 1
    try:
        os.close(report_fd)
        devnull = os.open(os.devnull, os.O_RDONLY)
        os.dup2(devnull, 0)
        os.close(devnull)
        signal.signal(signal.SIGCHLD, signal.SIG_DFL)
        import ctypes

        ctypes.CDLL("libc.so.6", use_errno=True).prctl(1, 15)  # PR_SET_PDEATHSIG, SIGTERM
        name, kind, cfg_dict, base_dir, info = req
        if os.getppid() != server_pid:  # the server died before the signal was armed
            os._exit(1)
        info.parent_pid = server_pid
        from .stage import stage_main

        stage_main(name, kind, cfg_dict, base_dir, info)
        code = 0
    except SystemExit as exc:
        code = exc.code if isinstance(exc.code, int) else (0 if exc.code is None else 1)
    except BaseException:  # noqa: BLE001 - a stage that cannot start: its exit code says so
        import traceback

        traceback.print_exc()
        code = 1
    finally:
        try:
            sys.stdout.flush()
            sys.stderr.flush()
        finally:
            os._exit(code)


def _warm(req: tuple) -> bool:
    """Load the first request's config here, so what that imports is done once, before the forks."""
    try:
        from ..config import load_config

        load_config(req[2], base_dir=req[3])
        import gc

        gc.freeze()
    except Exception:  # noqa: BLE001 - the stage loads it again and reports what fails
        pass
    return True


def _serve(report_fd: int, modules: list[str]) -> None:
    import ctypes

    ctypes.CDLL("libc.so.6", use_errno=True).prctl(1, 15)  # PR_SET_PDEATHSIG: the supervisor died
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C is the supervisor's to handle
    supervisor = os.getppid()
    from .rundir import ensure_runtime_dir

    ensure_runtime_dir()
    import importlib

    for m in ["pointflow.runtime.stage", *modules]:
        try:
            importlib.import_module(m)
        except Exception:  # noqa: BLE001 - the stage imports it again and reports what fails
            pass
    if os.getppid() != supervisor:
        os._exit(1)
    import gc

    gc.freeze()  # what is imported stays shared: no collection in a stage touches (copies) its pages
    _send(report_fd, ("ready",))
    me = os.getpid()
    stdin = sys.stdin.fileno()
    children: set[int] = set()
    open_ = True
    warmed = False
    while open_ or children:
        if open_:
            ready, _, _ = select.select([stdin], [], [], 0.05)
            if ready:
                req = _read_request(stdin)
                if req is None:
                    open_ = False  # the supervisor is done with us: serve the exits left
                else:
                    if not warmed:  # what loading this config imports (transports, plugins), once
                        warmed = _warm(req)
                    pid = os.fork()
                    if pid == 0:
                        _child(req, report_fd, me)
                    children.add(pid)
                    _send(report_fd, ("pid", pid))
        else:
            select.select([], [], [], 0.05)
        while children:
            try:
                pid, status = os.waitpid(-1, os.WNOHANG)
            except ChildProcessError:
                children.clear()
                break
            if pid == 0:
                break
            children.discard(pid)
            _send(report_fd, ("exit", pid, os.waitstatus_to_exitcode(status)))


if __name__ == "__main__":
    _serve(int(sys.argv[1]), sys.argv[2:])
