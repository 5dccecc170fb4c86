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


def test_info_words_the_auto_rule_by_ring_size(monkeypatch):
    """Where a crossover splits the ring sizes, each range gets its order and its reason."""
    from pointflow.render.select import auto_summary

    monkeypatch.setenv("POINTFLOW_NO_NUMBA", "1")  # no compiled raster: no software-adapter rule
    monkeypatch.setenv("POINTFLOW_CROSSOVER", "200000")
    two = auto_summary()
    assert two.startswith("cpu > wgpu > gl below 200,000 points (cpu first: ") and "< crossover 200000" in two, two
    assert "; wgpu > gl > cpu from 200,000 points (" in two and "below 0" not in two, two
    monkeypatch.setenv("POINTFLOW_CROSSOVER", "0")
    one = auto_summary()
    assert "at every ring size" in one and "below" not in one, one


def test_info_says_one_true_thing_about_auto(capsys):
    """`pointflow info`'s auto line is the decision a run makes (issue 40): on a software
    adapter where the shipped measurement prefers the compiled cpu raster, the cpu line and
    the auto line both put the cpu tier first; nowhere does it claim wgpu > gl > cpu then."""
    from pointflow.render.config import RenderConfig
    from pointflow.render.select import auto_order, cpu_raster_crossover, probe_adapter

    assert main(["info"]) == 0
    out = capsys.readouterr().out
    auto = next(ln for ln in out.splitlines() if ln.strip().startswith("auto "))
    cpu = next(ln for ln in out.splitlines() if ln.strip().startswith("cpu "))
    first = auto_order(1_000_000)[0][0]
    assert auto.split()[1] == ("cpu" if first.startswith("cpu") else first), auto
    ad = probe_adapter(RenderConfig())
    data, _ = cpu_raster_crossover()
    if ad is not None and ad.get("adapter_type") == "CPU" and data and data.get("faster_up_to_points") is None \
            and "auto prefers it over a software wgpu adapter at every size" in cpu:
        assert "cpu (compiled raster) > wgpu > gl at every ring size" in auto, auto
        assert "wgpu > gl > cpu" not in out, out


def test_duration_counts_from_when_the_pipeline_runs(tmp_path):
    """`--duration N` is N s of a running pipeline: counted from when every stage has reported
    in, so a busy machine's slow start does not eat the run (issue 36, item 4; issue 22 item 8
    counted from the command's start). The run's own stats say so: it stopped at least N s
    after its last stage reported in, whatever the load made of the start."""
    import json

    import yaml

    from pointflow import cli

    from ..helpers import small_config

    n = 2.0
    p = tmp_path / "c.yaml"
    p.write_text(yaml.safe_dump(small_config()))
    out = tmp_path / "out"
    assert main(["run", str(p), "--duration", str(n), "-q", "--out", str(out)]) == 0
    st = json.loads((out / "stats.json").read_text())
    ready_s = max(v["startup_ms"]["ready"] for v in st["stages"].values() if v["startup_ms"]) / 1000
    assert st["elapsed_s"] >= ready_s + n, (st["elapsed_s"], ready_s)
    assert "every stage has reported in" in cli.DURATION_HELP
