"""`pointflow validate` refuses what `pointflow run` refuses here, and says what it checked
(issue 22, items 3 and 8)."""
from __future__ import annotations

import re

from pointflow.cli import main
from pointflow.ring import RingLayout
from pointflow.ring.layout import as_channel_specs
from pointflow.ring.space import RingSpaceError, check_shm_space, shm_bytes, shm_free


def _too_many_points() -> int:
    return shm_free() // 12 + 1


def test_validate_refuses_a_ring_that_run_refuses(tmp_path, capsys):
    p = tmp_path / "big.yaml"
    p.write_text(f"source: {{transport: synthetic}}\nring: {{max_points: {_too_many_points()}}}\n")
    assert main(["validate", str(p)]) == 1
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and str(p) in err and "ring.max_points" in err
    assert "bytes free" in err and "this machine" in err and "OK" not in err


def test_validate_of_a_ring_that_fits_says_how_much_shared_memory(tmp_path, capsys):
    p = tmp_path / "ok.yaml"
    p.write_text("source: {transport: synthetic}\nring: {max_points: 1000}\n")
    assert main(["validate", str(p)]) == 0
    out = capsys.readouterr().out
    assert "OK" in out and "shared memory" in out and "render auto" in out


def test_the_bytes_per_point_in_the_message_add_up_to_the_total():
    n = _too_many_points()
    layout = RingLayout(n, as_channel_specs(["intensity"]))
    try:
        check_shm_space(layout)
    except RingSpaceError as exc:
        per_point = int(re.search(r"(\d+) bytes per point", str(exc)).group(1))
        assert abs(per_point * n - exc.need) <= per_point + shm_bytes(RingLayout(1, layout.channels)), str(exc)
        fits = int(re.search(r"about ([\d,]+) fit", str(exc)).group(1).replace(",", ""))
        check_shm_space(RingLayout(max(1, int(fits * 0.99)), layout.channels))  # what it says fits does
    else:
        raise AssertionError("not refused")


def test_validate_of_a_send_config_reports_the_link_not_a_render_backend(tmp_path, capsys):
    p = tmp_path / "sensor.yaml"
    p.write_text("source: {transport: synthetic}\nsend: {compression: lz4, socket: push}\n")
    assert main(["validate", str(p)]) == 0
    out = capsys.readouterr().out
    assert "pointflow send" in out and "push" in out and "tcp://127.0.0.1:5556" in out and "lz4" in out
    assert "render" not in out and "ring" not in out


def test_info_words_the_auto_rule_without_below_zero():
    from pointflow.cli import auto_rule

    zero = auto_rule(0, "bench/results/crossover.json")
    assert "below 0" not in zero and "every ring size" in zero and "crossover.json" in zero
    assert "fewer than 200,000 points" in auto_rule(200_000, "built-in default")


def test_duration_counts_from_when_the_pipeline_runs(tmp_path):
    """`--duration N` is N s of a running pipeline: counted from when every stage has reported
    in, so a busy machine's slow start does not eat the run (issue 36, item 4; issue 22 item 8
    counted from the command's start). The run's own stats say so: it stopped at least N s
    after its last stage reported in, whatever the load made of the start."""
    import json

    import yaml

    from pointflow import cli

    from .helpers import small_config

    n = 2.0
    p = tmp_path / "c.yaml"
    p.write_text(yaml.safe_dump(small_config()))
    out = tmp_path / "out"
    assert main(["run", str(p), "--duration", str(n), "-q", "--out", str(out)]) == 0
    st = json.loads((out / "stats.json").read_text())
    ready_s = max(v["startup_ms"]["ready"] for v in st["stages"].values() if v["startup_ms"]) / 1000
    assert st["elapsed_s"] >= ready_s + n, (st["elapsed_s"], ready_s)
    assert "every stage has reported in" in cli.DURATION_HELP
