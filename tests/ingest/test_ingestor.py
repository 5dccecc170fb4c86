"""The Ingestor (ingest's core) on a real shared-memory ring: bounded coalescing queue,
adaptive thinning, channel conversion."""
import numpy as np
import pytest

from pointflow.chunk import PointChunk
from pointflow.ingest.process import Ingestor
from pointflow.ring import PointRing


@pytest.fixture
def ring():
    r = PointRing(10_000, channels=["intensity", "rgb"])
    yield r
    r.close()


def _c(n, v=0.0):
    return PointChunk(positions=np.full((n, 3), v), channels={"intensity": np.full(n, v, np.float32)})


def test_small_chunks_coalesce_and_full_queue_drops_oldest_batch(ring):
    ing = Ingestor(ring, coalesce_points=100, queue_max_batches=3)
    for i in range(20):  # 20 chunks of 25 -> 5 batches of 100; only the newest 3 stay
        assert ing.add_chunk(_c(25, float(i)))
    assert [b.n for b in ing.queue] == [100, 100, 100] and ing.counters.drops["queue_overflow"] == 200
    ing.flush()
    assert ing.pushes == 3 and ing.counters.points_out == 300
    snap = ring.snapshot()
    assert snap.channels["intensity"].tolist() == [float(i) for i in range(8, 20) for _ in range(25)]
    assert ing.counters.points_in == ing.counters.points_out + sum(ing.counters.drops.values())


def test_big_chunks_are_not_copied_into_batches(ring):
    ing = Ingestor(ring, coalesce_points=100)
    for n in (60, 10, 10, 60, 20):
        ing.add_chunk(_c(n))
    assert [b.n for b in ing.queue] == [60, 20, 60, 20]


@pytest.mark.parametrize("fill,step", [(0.5, 1), (0.95, 2), (0.985, 4)])
def test_adaptive_thinning_by_ring_fill(ring, fill, step):
    ring.push(np.zeros((int(fill * ring.capacity), 3)))
    ing = Ingestor(ring, adaptive_thinning=True)
    ing.add_chunk(_c(100))
    kept = 100 // step if step > 1 else 100
    assert ing.queued_points == kept
    assert ing.counters.drops.get("thinned", 0) == 100 - kept


def test_rgb_conversions(ring):
    ing = Ingestor(ring)
    n = 4
    rgb16 = np.array([[65535, 0, 256]] * n, np.uint16)
    rgb_small16 = np.array([[200, 10, 0]] * n, np.uint16)  # 8-bit values stored in 16 bits: kept
    rgbf = np.array([[1.0, 0.5, 0.0]] * n, np.float32)
    for rgb in (rgb16, rgb_small16, rgbf):
        ing.add_chunk(PointChunk(positions=np.zeros((n, 3)), channels={"rgb": rgb}))
    ing.flush()
    got = ring.snapshot().channels["rgb"]
    assert got[:n].tolist() == [[255, 0, 1]] * n
    assert got[n:2 * n].tolist() == [[200, 10, 0]] * n
    assert got[2 * n:].tolist() == [[255, 128, 0]] * n


def test_wrong_channel_width_is_rejected_not_crashing(ring):
    ing = Ingestor(ring)
    assert not ing.add_chunk(PointChunk(positions=np.zeros((3, 3)), channels={"rgb": np.zeros(3, np.uint8)}))
    assert ing.rejected["bad_channel_shape"] == 1 and ing.counters.points_in == 0


def test_small_chunks_with_non_finite_points_are_counted_per_batch(ring):
    """Small chunks are checked for non-finite points once per coalesced batch (in flush):
    the counts stay exact and the finite points of every chunk are stored in order."""
    ing = Ingestor(ring, coalesce_points=100)
    kept = []
    for i in range(12):  # 12 chunks of 10 points: batches of 100 and 20
        pos = np.full((10, 3), float(i))
        if i % 3 == 0:
            pos[i % 10, i % 3] = (np.nan, np.inf, -np.inf)[i % 3]
        kept += [float(i)] * int(np.isfinite(pos).all(axis=1).sum())
        assert ing.add_chunk(PointChunk(positions=pos, channels={"intensity": np.full(10, float(i), np.float32)}))
    all_bad = np.full((10, 3), np.nan)
    assert ing.add_chunk(PointChunk(positions=all_bad, channels={"intensity": np.zeros(10, np.float32)}))
    ing.flush()
    c = ing.counters
    assert c.drops == {"non_finite": 4 + 10}
    assert c.points_in == 130 and c.points_out == len(kept) == 116
    assert ring.snapshot().channels["intensity"].tolist() == kept
    assert ring.stats().total_written == c.points_out
