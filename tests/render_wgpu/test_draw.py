"""What the draw pass puts on screen: footprints, colours, depth, sizes, upload."""
import numpy as np
import pytest

from pointflow.render import colormap
from pointflow.render.camera import Camera, project_to_pixels

from .helpers import cfg, frame, lit

pytestmark = pytest.mark.gpu

W, H = 320, 240
CAM = Camera(eye=[0.0, -10.0, 0.0], target=[0.0, 0.0, 0.0], near=1.0, far=100.0)


def _centre_px(p, cam=CAM):
    px, py, _, _ = project_to_pixels(np.asarray([p], np.float64), cam.view_proj(W, H), W, H)
    return float(px[0]), float(py[0])


def test_square_footprint_and_exact_colour(make_renderer):
    r = make_renderer(cfg(point_size=4.0, color=[1.0, 0.5, 0.25], background=[0.0, 0.0, 0.0]), 1)
    r.render(frame(np.zeros((1, 3))), CAM)
    img = r.read_image()
    ys, xs = np.nonzero(lit(img))
    assert (xs.min(), xs.max(), ys.min(), ys.max()) == (158, 161, 118, 121)   # centres in [158, 162) x [118, 122)
    assert (img[ys, xs] == [255, 128, 64, 255]).all()                         # round(c * 255)
    assert (img[0, 0] == [0, 0, 0, 255]).all()


@pytest.mark.parametrize("size", [1.0, 7.0, 128.0])
def test_round_footprint_matches_rule(make_renderer, size):
    r = make_renderer(cfg(point_size=size, point_shape="round", color=[1, 1, 1]), 1)
    p = [0.137, 0.0, -0.071]
    r.render(frame(np.array([p])), CAM)
    m = lit(r.read_image())
    cx, cy = _centre_px(p)
    yy, xx = np.mgrid[0:H, 0:W]
    want = (xx + 0.5 - cx) ** 2 + (yy + 0.5 - cy) ** 2 <= (size / 2) ** 2
    assert abs(int(m.sum()) - int(want.sum())) <= max(2, want.sum() // 100)
    assert (m & ~want).sum() <= max(2, want.sum() // 100)


def test_large_square_points_are_not_capped(make_renderer):
    r = make_renderer(cfg(point_size=200.0, color=[1, 1, 1]), 1)
    r.render(frame(np.zeros((1, 3))), CAM)
    ys, xs = np.nonzero(lit(r.read_image()))
    assert xs.max() - xs.min() + 1 == 200 and ys.max() - ys.min() + 1 == 200


def test_world_size_points_shrink_with_distance(make_renderer):
    r = make_renderer(cfg(point_size=0.5, point_size_space="world", color=[1, 1, 1]), 2)
    pts = np.array([[-2.0, 0.0, 0.0], [2.0, 20.0, 0.0]])      # second point 3x further away
    r.render(frame(pts), CAM)
    m = lit(r.read_image())
    near_w = m[:, :W // 2].any(axis=0).sum()
    far_w = m[:, W // 2:].any(axis=0).sum()
    f = CAM.proj(W, H)[1, 1]
    assert abs(near_w - 0.5 * f * H / 2 / 10) <= 1.5
    assert abs(far_w - 0.5 * f * H / 2 / 30) <= 1.5


def test_nearer_point_wins_regardless_of_order(make_renderer):
    for order in ([0, 1], [1, 0]):
        pts = np.array([[0.0, 0.0, 0.0], [0.0, -5.0, 0.0]])[order]   # same pixel, one nearer
        rgb = np.array([[255, 0, 0], [0, 255, 0]], np.uint8)[order]
        r = make_renderer(cfg(point_size=3.0, color_by="rgb"), 2, ["rgb"])
        r.render(frame(pts, channels={"rgb": rgb}), CAM)
        img = r.read_image()
        assert (img[120, 160, :3] == [0, 255, 0]).all()


def test_colormap_and_rgb_colours_exact(make_renderer):
    n = 9
    pts = np.zeros((n, 3))
    pts[:, 0] = np.linspace(-3.2, 3.2, n)
    vals = np.array([-1.0, 0.0, 0.1, 0.33, 0.5, 0.77, 0.999, 1.0, np.nan], np.float32)
    for cmap in ("turbo", "viridis", "grayscale"):
        r = make_renderer(cfg(point_size=3.0, color_by="intensity", colormap=cmap, color=[0.2, 0.4, 0.6]),
                          n, ["intensity"])
        r.render(frame(pts, channels={"intensity": vals}, ranges={"intensity": (0.0, 1.0)}), CAM)
        img = r.read_image()
        want = colormap.lut(cmap)[np.maximum(colormap.lut_index(vals, 0.0, 1.0), 0)].copy()
        want[-1] = [51, 102, 153, 255]                   # NaN -> the single colour
        for i, p in enumerate(pts):
            cx, cy = _centre_px(p)
            assert (img[int(cy), int(cx)] == want[i]).all(), (cmap, i, img[int(cy), int(cx)], want[i])
    rgb = np.random.default_rng(0).integers(0, 256, size=(n, 3), dtype=np.uint8)
    r = make_renderer(cfg(point_size=3.0, color_by="rgb"), n, ["rgb"])
    r.render(frame(pts, channels={"rgb": rgb}), CAM)
    img = r.read_image()
    for i, p in enumerate(pts):
        cx, cy = _centre_px(p)
        assert (img[int(cy), int(cx), :3] == rgb[i]).all()


def test_z_colour_auto_range_computed_on_gpu(make_renderer):
    pts = np.array([[-2.0, 0.0, -1.0], [0.0, 0.0, 0.0], [2.0, 0.0, 3.0], [0.0, 0.0, 1e9]])
    pts[3] = np.nan                                           # non-finite: not part of the range
    r = make_renderer(cfg(point_size=3.0, color_by="z", colormap="viridis"), 4)
    f = frame(pts, origin=(100.0, 200.0, 50.0))
    cam = CAM.translated([100.0, 200.0, 50.0])
    r.render(f, cam)
    img = r.read_image()
    want = colormap.lut("viridis")[colormap.lut_index(pts[:3, 2], -1.0, 3.0)]
    for i in range(3):
        cx, cy = _centre_px(pts[i])
        assert (img[int(cy), int(cx)] == want[i]).all()


def test_incremental_upload_is_proportional_to_new_points(make_renderer):
    """Bytes per tick follow the dirty ranges, not the ring size, and the image equals a
    fresh full upload of the same ring contents."""
    rng = np.random.default_rng(7)
    per_tick = {}
    for cap in (50_000, 200_000):
        r = make_renderer(cfg(color_by="intensity"), cap, ["intensity"])
        pts = rng.uniform(-4, 4, size=(cap, 3))
        inten = rng.uniform(0, 1, cap).astype(np.float32)
        f = frame(pts, channels={"intensity": inten}, ranges={"intensity": (0.0, 1.0)})
        first = r.render(f, CAM).uploaded_bytes
        assert first == cap * 16                          # positions 12 B + intensity 4 B
        new = cap // 100
        head = 0
        sizes = []
        for tick in range(6):
            a = head
            f.positions[a:a + new] = rng.uniform(-4, 4, size=(new, 3)).astype(np.float32)
            f.channels["intensity"][a:a + new] = rng.uniform(0, 1, new).astype(np.float32)
            head = (head + new) % cap
            f.head, f.dirty = head, [(a, a + new)]
            sizes.append(r.render(f, CAM).uploaded_bytes)
        # one set of point buffers (renderer.DATA_SETS): each range is uploaded once
        assert all(s == new * 16 for s in sizes), sizes
        per_tick[cap] = sizes[-1] / new
        img = r.read_image()
        fresh = make_renderer(cfg(color_by="intensity"), cap, ["intensity"])
        f.dirty = None
        fresh.render(f, CAM)
        assert np.array_equal(img, fresh.read_image())    # incremental == full upload
        assert lit(img).mean() > 0.05
    assert per_tick[50_000] == per_tick[200_000]          # bytes per new point: independent of ring size


def test_equal_depth_ties_go_to_lower_logical_index(make_renderer):
    """Compaction is a prefix sum in logical order (no atomics order), so equal-depth ties are
    deterministic and follow the shared rule, also when the ring wraps."""
    cam = Camera(eye=[0.0, 0.0, 10.0], target=[0.0, 0.0, 0.0], up=[0.0, 1.0, 0.0], near=1.0, far=100.0)
    n, cap, head = 3000, 4096, 3000            # wraps: logical order != slot order
    rng = np.random.default_rng(5)
    pts = np.column_stack([rng.uniform(-3, 3, n), rng.uniform(-2, 2, n), np.zeros(n)])  # all at one depth
    pts[1500:] = pts[:1500]                    # every point has a twin drawn later, same place
    rgb = np.zeros((n, 3), np.uint8)
    rgb[:1500] = [255, 0, 0]
    rgb[1500:] = [0, 255, 0]
    r = make_renderer(cfg(point_size=3.0, color_by="rgb"), cap, ["rgb"])
    for _ in range(3):
        r.render(frame(pts, capacity=cap, head=head, channels={"rgb": rgb}), cam)
        img = r.read_image()
        assert not (img[..., 1] == 255).any()  # the older twin (lower logical index) always wins
        assert (img[..., 0] == 255).sum() > 1000
