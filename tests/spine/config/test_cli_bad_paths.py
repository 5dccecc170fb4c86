"""Every CLI command that takes a path, given a bad one (missing, empty, a directory, a FIFO,
not UTF-8, unreadable, under a file): one line naming the file, the config-error exit code,
no traceback, nothing started (issue 14.2, 14.7, 14.9)."""
from __future__ import annotations

import ctypes
import os
import subprocess
import sys

import pytest

from pointflow.cli import EXIT_CONFIG, main

COMMANDS = [["validate"], ["run", "--duration", "1", "-q"], ["profile", "--duration", "1", "-q"]]
NOT_UTF8 = {
    "binary": bytes(range(256)) * 4,
    "latin1": "source: {transport: synthetic, name: caf\u00e9}\n".encode("latin-1"),
}


def _bad_path(tmp_path, kind: str) -> str:
    p = tmp_path / f"{kind}.yaml"
    if kind == "missing":
        pass
    elif kind == "empty":
        p.write_bytes(b"")
    elif kind == "directory":
        p.mkdir()
    elif kind == "fifo":
        os.mkfifo(p)  # reading it would block forever
    elif kind == "under_a_file":
        (tmp_path / "plain").write_text("x")
        p = tmp_path / "plain" / "c.yaml"  # ENOTDIR
    elif kind in NOT_UTF8:
        p.write_bytes(NOT_UTF8[kind])
    elif kind == "bad_yaml":
        p.write_text("source: [unclosed\n")
    elif kind == "not_a_mapping":
        p.write_text("- 1\n- 2\n")
    elif kind == "huge":  # e.g. a point cloud passed by mistake (sparse: costs no disk)
        with open(p, "wb") as f:
            f.truncate(64 << 20)
    return str(p)


def _check_one_line(err: str, path: str) -> str:
    assert "Traceback" not in err, err
    assert err.endswith("\n"), repr(err)       # issue 14.9: the line is terminated
    lines = err.splitlines()
    assert len(lines) == 1, err                # one line, even for YAML errors
    assert lines[0].startswith("config error: ") and path in lines[0], err
    return lines[0]


@pytest.mark.parametrize("cmd", COMMANDS, ids=lambda c: c[0])
@pytest.mark.parametrize("kind", ["missing", "empty", "directory", "fifo", "under_a_file", "binary", "latin1",
                                  "bad_yaml", "not_a_mapping", "huge"])
@pytest.mark.timeout(60)  # a FIFO used to block the read forever
def test_bad_config_path_is_one_line_config_error(tmp_path, capsys, monkeypatch, cmd, kind):
    monkeypatch.chdir(tmp_path)  # a run that wrongly started would write out/ here
    path = _bad_path(tmp_path, kind)
    assert main([cmd[0], path, *cmd[1:]]) == EXIT_CONFIG
    out, err = capsys.readouterr()
    line = _check_one_line(err, path)
    assert not (tmp_path / "out").exists()
    if kind in NOT_UTF8:  # names the byte position
        bad = NOT_UTF8[kind]
        pos = next(i for i in range(len(bad)) if _not_utf8_at(bad, i))
        assert f"byte position {pos}" in line and "UTF-8" in line, line


def _not_utf8_at(b: bytes, i: int) -> bool:
    try:
        b[: i + 1].decode("utf-8")
        return False
    except UnicodeDecodeError as e:
        return e.start == i


def _drop_dac_caps() -> None:
    """preexec: root without CAP_DAC_OVERRIDE / CAP_DAC_READ_SEARCH obeys file modes."""
    libc = ctypes.CDLL("libc.so.6", use_errno=True)
    for cap in (1, 2):  # PR_CAPBSET_DROP(CAP_DAC_OVERRIDE), PR_CAPBSET_DROP(CAP_DAC_READ_SEARCH)
        if libc.prctl(24, cap, 0, 0, 0) != 0:
            raise OSError(ctypes.get_errno(), "prctl(PR_CAPBSET_DROP)")


def _cli(args, cwd) -> subprocess.CompletedProcess:
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(sys.path))
    return subprocess.run([sys.executable, "-m", "pointflow.cli", *args], cwd=cwd, env=env, capture_output=True,
                          text=True, timeout=120, preexec_fn=_drop_dac_caps if os.geteuid() == 0 else None)


@pytest.mark.parametrize("cmd", COMMANDS, ids=lambda c: c[0])
def test_unreadable_and_not_utf8_in_a_real_process(tmp_path, cmd):
    """The same through ``python -m pointflow.cli``: exit code, stderr, no traceback."""
    secret = tmp_path / "secret.yaml"
    secret.write_text("source: {transport: synthetic}\n")
    secret.chmod(0)
    r = _cli([cmd[0], str(secret), *cmd[1:]], tmp_path)
    assert r.returncode == EXIT_CONFIG, r.stderr
    line = _check_one_line(r.stderr, str(secret))
    assert "Permission denied" in line
    latin = tmp_path / "latin1.yaml"
    latin.write_bytes(NOT_UTF8["latin1"])
    r = _cli([cmd[0], str(latin), *cmd[1:]], tmp_path)
    assert r.returncode == EXIT_CONFIG, r.stderr
    line = _check_one_line(r.stderr, str(latin))
    pos = NOT_UTF8["latin1"].index(b"\xe9")
    assert "not UTF-8" in line and f"byte position {pos} " in line
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("cmd", COMMANDS[1:], ids=lambda c: c[0])
def test_out_that_is_a_file_is_a_config_error(tmp_path, capsys, cmd):
    cfg = tmp_path / "ok.yaml"
    cfg.write_text("source: {transport: synthetic}\nrender: {backend: cpu}\n")
    out = tmp_path / "a_file"
    out.write_text("x")
    assert main([cmd[0], str(cfg), *cmd[1:], "--out", str(out)]) == EXIT_CONFIG
    err = capsys.readouterr().err
    assert "Traceback" not in err and err.endswith("\n")
    assert f"output directory {out}: exists and is not a directory" in err


def test_run_whose_only_file_cannot_be_read_fails_naming_it(tmp_path):
    """Issue 19.4: a file source none of whose files can be read fails the run (exit 2),
    naming the file and why, instead of drawing an empty scene and exiting 0."""
    bad = tmp_path / "scan.npy"
    bad.write_bytes(b"\x93NUMPY but not really")
    cfg = tmp_path / "c.yaml"
    cfg.write_text(f"source: {{transport: file, options: {{path: {bad}}}}}\n"
                   "render: {backend: cpu, size: [64, 48]}\nsupervisor: {max_restarts: 3}\n")
    proc = subprocess.run([sys.executable, "-m", "pointflow.cli", "run", str(cfg), "--duration", "60", "-q",
                           "--out", str(tmp_path / "out")], cwd=tmp_path, capture_output=True, text=True, timeout=120)
    assert proc.returncode == 2, proc.stderr[-2000:]
    fail = [ln for ln in proc.stderr.splitlines() if "none of its 1 file(s) can be read" in ln]
    assert fail and str(bad) in fail[-1], proc.stderr[-2000:]
    # said once (docs/bad-input.md): the source no longer warns of it before the stage's error
    assert len([ln for ln in proc.stderr.splitlines() if str(bad) in ln]) == 1, proc.stderr[-2000:]
    assert "Traceback" not in proc.stderr
    assert "restarting" not in proc.stderr  # a restart cannot help: none was tried
