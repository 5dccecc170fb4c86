"""The compute raster method: depth-key resolution, dispatch split, method choice, picking."""
import numpy as np
import pytest

from pointflow.render.base import RenderError
from pointflow.render.camera import Camera, project_to_pixels
from pointflow.render.cpu import CpuRenderer
from pointflow.render.wgpu_tier import resolve_pick

from gpu_util import require_adapter

from .helpers import cfg, frame, lit

pytestmark = pytest.mark.gpu

RED, BLUE = (255, 0, 0), (0, 0, 255)


@pytest.fixture
def make_any():
    """WgpuRenderers with the config's own raster setting (not parametrised)."""
    adapter = require_adapter()
    from pointflow.render.wgpu_tier import WgpuRenderer
    made = []

    def make(c, capacity, channels=(), **kw):
        r = WgpuRenderer(c, capacity, list(channels), adapter=adapter, **kw)
        made.append(r)
        return r
    yield make
    for r in made:
        r.close()


@pytest.fixture(params=[True, False], ids=["key64", "key32x2"])
def make_compute(request, make_any):
    """Compute-method renderers with each key variant."""
    def make(c, capacity, channels=(), **kw):
        c.raster = "compute"
        r = make_any(c, capacity, channels, key64=request.param, **kw)
        assert ("64-bit" in r.info()["compute_keys"]) == request.param
        return r
    return make


def _rgb_frame(pts, colours, **kw):
    return frame(pts, channels={"rgb": np.asarray(colours, np.uint8)}, **kw)


def _centre(img):
    h, w = img.shape[:2]
    return tuple(int(v) for v in img[h // 2, w // 2, :3])


@pytest.mark.parametrize("near_first", [True, False])
def test_two_points_1cm_apart_at_500m_resolve_to_the_nearer(make_compute, near_first):
    """The key holds the float32 view depth (2^-24 relative, 0.03 mm at 500 m), so 1 cm at
    500 m with near 0.1 / far 10,000 is resolved whatever the logical order; a z/w depth
    buffer cannot (its float32 steps there are ~6 cm)."""
    cam = Camera(eye=[0.0, 0.0, 0.0], target=[0.0, 1.0, 0.0], near=0.1, far=10_000.0)
    near, far = [0.0, 500.0, 0.0], [0.0, 500.01, 0.0]
    pts = [near, far] if near_first else [far, near]
    cols = [RED, BLUE] if near_first else [BLUE, RED]
    r = make_compute(cfg(size=[64, 64], color_by="rgb", point_size=3.0), 2, ["rgb"])
    r.render(_rgb_frame(pts, cols), cam)
    assert _centre(r.read_image()) == RED


def test_far_background_point_never_wins_through_quantisation(make_compute):
    """Pairs on one ray over the whole depth range (0.1 .. 10,000), the far one always the
    lower logical index (it would win a quantised tie): the nearer one must win every time."""
    cam = Camera(eye=[0.0, 0.0, 0.0], target=[0.0, 1.0, 0.0], near=0.1, far=10_000.0)
    rng = np.random.default_rng(5)
    r = make_compute(cfg(size=[32, 32], color_by="rgb", point_size=2.0), 2, ["rgb"])
    depths = np.exp(rng.uniform(np.log(0.2), np.log(9000.0), 40))
    for d in depths:
        for rel in (1e-5, 1e-3, 0.5):
            far = d * (1 + rel)
            r.render(_rgb_frame([[0.0, far, 0.0], [0.0, d, 0.0]], [BLUE, RED]), cam)
            assert _centre(r.read_image()) == RED, (d, far)


def test_equal_depth_ties_to_lower_logical_index_with_wrapped_slots(make_compute):
    cam = Camera(eye=[0.0, -10.0, 0.0], target=[0.0, 0.0, 0.0], near=1.0, far=100.0)
    r = make_compute(cfg(size=[32, 32], color_by="rgb", point_size=4.0), 5, ["rgb"])
    # logical 0 in slot 3, logical 1 in slot 4, logical 2 in slot 0: all at the same place
    r.render(_rgb_frame([[0, 0, 0]] * 3, [BLUE, RED, RED], capacity=5, head=3), cam)
    assert _centre(r.read_image()) == BLUE


def test_dispatch_split_beyond_max_workgroups_draws_the_same(make_renderer, raster):
    """A grid capped at 2 workgroups per dimension (2-D dispatch) draws exactly what one
    row of workgroups draws, with and without a budget."""
    rng = np.random.default_rng(6)
    n = 40_000          # 10 compute workgroups of 4096 points, 157 quads workgroups of 256
    pts = rng.uniform(-3, 3, size=(n, 3))
    cam = Camera(eye=[0.0, -12.0, 2.0], target=[0.0, 0.0, 0.0], near=1.0, far=100.0)
    inten = rng.uniform(0, 1, n).astype(np.float32)
    c = cfg(color_by="intensity")
    a = make_renderer(c, n, ["intensity"])
    b = make_renderer(c, n, ["intensity"], max_groups=2)
    for budget in (None, 9000):
        f = frame(pts, channels={"intensity": inten}, budget=budget, seed=3)
        sa, sb = a.render(f, cam), b.render(f, cam)
        ia, ib = a.read_image(), b.read_image()
        assert lit(ia).mean() > 0.05
        assert np.array_equal(ia, ib)
        assert sa.drawn == sb.drawn and (budget is None or sa.drawn <= budget)
        assert np.array_equal(a.debug_survivors(), b.debug_survivors())


def test_compute_chunks_use_its_workgroup_size(make_renderer, raster):
    """The dispatch limit bounds a chunk (one dispatch per segment) by the method's points per
    workgroup; the ring is split, not capped."""
    r = make_renderer(cfg(), 1000)
    r._limits = {"max-storage-buffer-binding-size": 1 << 30, "max-buffer-size": 1 << 30,
                 "max-compute-workgroups-per-dimension": 4}
    per_group = 4096 if raster.startswith("compute") else 256
    table = r._chunk_plan(10 ** 6)
    assert max(n for _, n in table) == 16 * per_group and sum(n for _, n in table) == 10 ** 6
    assert "dispatches 4^2 workgroups" in r._chunk_why


def test_auto_chooses_by_the_measured_crossover_and_says_why(make_any, monkeypatch, tmp_path):
    """auto: compute for screen-size points up to the measured size and from the measured
    ring size per pixel on; quads otherwise, with the reason in info()."""
    make_renderer = make_any
    monkeypatch.delenv("POINTFLOW_RASTER", raising=False)
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    (tmp_path / "pointflow").mkdir()
    (tmp_path / "pointflow" / "raster_crossover.json").write_text(
        '{"max_compute_point_px": 8, "min_compute_points_per_pixel": 0.05}')
    big = 320 * 240   # cfg() is 320x240: 0.05 per pixel = 3840 points
    r = make_renderer(cfg(raster="auto", point_size=2.0), big)
    info = r.info()
    assert info["raster"] == "compute" and "raster_crossover.json" in info["raster_choice"]
    assert "64-bit" in info["compute_keys"]            # lavapipe has shader-int64-atomic-min-max
    small = make_renderer(cfg(raster="auto", point_size=2.0), 1000)
    assert small.info()["raster"] == "quads" and "per pixel" in small.info()["raster_choice"]
    w = make_renderer(cfg(raster="auto", point_size_space="world", point_size=0.2), big)
    assert w.info()["raster"] == "quads" and "world-size" in w.info()["raster_choice"]
    wide = make_renderer(cfg(raster="auto", point_size=12.0), big)
    assert wide.info()["raster"] == "quads" and "12.0 px > 8 px" in wide.info()["raster_choice"]
    assert wide.info()["compute_keys"] is None
    forced = make_renderer(cfg(raster="compute", point_size=64.0), 10)
    assert forced.info()["raster"] == "compute"        # explicit: any size (slower above the limit)
    monkeypatch.setenv("POINTFLOW_RASTER", "quads")
    assert make_renderer(cfg(raster="compute"), 10).info()["raster"] == "quads"
    monkeypatch.setenv("POINTFLOW_RASTER", "bogus")
    with pytest.raises(RenderError, match="POINTFLOW_RASTER"):
        make_renderer(cfg(raster="compute"), 10)


def test_raster_key_is_validated_at_config_load():
    from pointflow.config import ConfigError, load_config
    with pytest.raises(ConfigError, match="render.raster"):
        load_config({"source": {"transport": "synthetic"}, "render": {"raster": "triangles"}})


def _cpu_block_pick(cpu, f, cam, x, y, radius, strategy):
    """What the cpu tier's per-pixel winners give under the wgpu pick rule (circle of
    ``radius`` around (x, y); distance, then depth, then slot)."""
    W, H = cpu.width, cpu.height
    X, Y, ri = int(np.floor(x)), int(np.floor(y)), int(np.ceil(radius))
    x0, x1, y0, y1 = max(X - ri, 0), min(X + ri + 1, W), max(Y - ri, 0), min(Y + ri + 1, H)
    block = cpu._slot_at.reshape(H, W)[y0:y1, x0:x1]
    ids = (block + 1).astype(np.uint32)
    attrs = np.zeros(block.shape + (4,), np.float32)
    s = np.maximum(block, 0)
    _, _, _, w = project_to_pixels(f.positions[s.ravel()].astype(np.float64), cam.view_proj(W, H, f.origin), W, H)
    attrs[..., 0] = w.reshape(block.shape)
    attrs[..., 1] = f.importance[s]
    t = f.t_ingest_ms[s]
    attrs[..., 2] = t.astype(np.float32)
    attrs[..., 3] = t - attrs[..., 2]
    return resolve_pick(ids, attrs, x0, y0, x, y, radius, strategy)


@pytest.mark.parametrize("strategy", ["nearest", "highest_importance", "recent_first"])
def test_compute_pick_matches_the_cpu_tier_winners(make_compute, strategy):
    rng = np.random.default_rng(7)
    n = 3000
    pts = rng.uniform(-4, 4, size=(n, 3))
    imp = rng.uniform(0, 1, n).astype(np.float32)
    t = rng.uniform(0, 1000, n)
    cam = Camera(eye=[0.0, -12.0, 3.0], target=[0.0, 0.0, 0.0], near=1.0, far=100.0)
    c = cfg(point_size=2.0, pick_radius=6, pick_strategy=strategy)
    r = make_compute(c, n + 7)
    f = frame(pts, capacity=n + 7, head=n, importance=imp, t_ms=t, now_ms=1000.0)
    r.render(f, cam)
    cpu = CpuRenderer(c, n + 7, [])
    cpu.render(f, cam)
    assert np.array_equal(r.read_image(), cpu.read_image())
    hits = 0
    for x, y in rng.uniform([0, 0], [320, 240], size=(60, 2)):
        want = _cpu_block_pick(cpu, f, cam, x, y, 6.0, strategy)
        assert r.pick(x, y) == want, (x, y)
        hits += want is not None
    assert hits > 20


def test_tier_selection_log_names_the_raster_method(monkeypatch):
    require_adapter()
    from pointflow.render.select import select_renderer
    monkeypatch.delenv("POINTFLOW_RASTER", raising=False)
    monkeypatch.delenv("POINTFLOW_BACKEND", raising=False)
    r, lines = select_renderer(cfg(backend="wgpu", raster="compute"), 100, [])
    try:
        assert any(line.startswith("wgpu: raster method compute (render.raster=compute") for line in lines), lines
    finally:
        r.close()
