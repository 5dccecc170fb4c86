"""≥ 10,000 malformed messages interleaved with valid ones, through real ZeroMQ into a real
ingest process: nothing crashes, every valid point arrives, the accounting is exact."""
import json

import numpy as np

from pointflow import wire
from pointflow.chunk import ChunkError, PointChunk, new_trace_id
from pointflow.ingest.jsonchunk import parse_json_chunk

from .stage_util import IngestStage, base_config

N_BAD = 10_000


def _mutations(rng, good_frames, packed):
    """Malformed messages of every kind the issue lists, plus random byte mutations (of a
    chunk as a frame per array, ``good_frames``, and packed into one data frame, ``packed``)."""
    hdr = json.loads(bytes(good_frames[0]))
    body = packed[1]
    pos = bytes(good_frames[1])
    ch = bytes(good_frames[2])

    def h(**kw):
        d = dict(hdr)
        d.update(kw)
        return json.dumps(d).encode()

    kinds = [
        lambda: [b"{not json"],                                            # malformed JSON
        lambda: [json.dumps([1, 2, 3]).encode()],                          # JSON of the wrong shape
        lambda: [json.dumps({"points": [{"x": 1}]}).encode()],
        lambda: [json.dumps({"x": [1, 2], "y": [1], "z": [1, 2]}).encode()],  # lengths differ
        lambda: [h(channels=[{"name": "intensity", "dtype": "float32", "shape": [hdr["n"] + 1]}]), pos, ch],
        lambda: [h(channels=[{"name": "intensity", "dtype": "complex64", "shape": [hdr["n"]]}]), pos, ch],
        lambda: [h(n=-5), pos, ch],                                        # negative count
        lambda: [h(n=10**15), pos, ch],                                    # absurd count
        lambda: [good_frames[0], pos[: len(pos) // 2], ch],                # truncated frame
        lambda: [good_frames[0], pos + b"\0" * 12, ch],                    # more bytes than promised
        lambda: [h(n=5_000_001, positions={"dtype": "float64", "shape": [5_000_001, 3]}), pos, ch],  # too large
        lambda: [rng.bytes(int(rng.integers(0, 200)))],                    # garbage
        lambda: [rng.bytes(30), rng.bytes(50), rng.bytes(7)],
        lambda: [good_frames[0]],                                          # header only (not JSON chunk)
        lambda: [good_frames[0], pos],                                     # missing channel frame
        lambda: [packed[0], body[: len(body) - 4]],                        # packed: truncated
        lambda: [packed[0], body + b"\0" * 8],                             # packed: too long
        lambda: [packed[0], body, ch],                                     # packed: a frame too many
        lambda: [packed[0].replace(b'"packed":true', b'"packed":1'), body],  # packed: not true
    ]

    def random_mutation():
        frames = [bytearray(bytes(f)) for f in (good_frames if rng.random() < 0.5 else packed)]
        f = frames[int(rng.integers(0, 1))]  # mutate the header
        for _ in range(int(rng.integers(1, 4))):
            if f:
                f[int(rng.integers(0, len(f)))] = int(rng.integers(0, 256))
        return [bytes(x) for x in frames]

    i = 0
    while True:
        i += 1
        yield kinds[i % len(kinds)]() if i % 4 else random_mutation()


def _decodes(frames):
    """The chunk a message holds if it is well-formed, else None."""
    try:
        if len(frames) == 1:
            c = parse_json_chunk(frames[0], 5_000_000)
        else:
            c = wire.decode(frames, 5_000_000)
        c.validate(5_000_000)
    except ChunkError:
        return None
    v = c.channels.get("intensity")
    if v is None:  # a flipped byte renamed the channel: valid, but nothing for the ring's channel
        c.channels["intensity"] = np.full(c.n, np.nan, np.float32)
    elif v.ndim == 2 and v.shape[1] != 1:
        return None  # ingest rejects it (bad_channel_shape)
    else:
        c.channels["intensity"] = v.reshape(-1)
    return c


def test_fuzz_ten_thousand_bad_messages_exact_accounting():
    st = IngestStage(base_config(max_points=2_000_000))
    try:
        rng = np.random.default_rng(1234)
        template = PointChunk(positions=rng.uniform(-5, 5, (64, 3)),
                              channels={"intensity": np.arange(64, dtype=np.float32)}, trace_id=1)
        good_frames = [bytes(memoryview(f)) for f in wire.encode(template, pack=False)]
        packed = [bytes(memoryview(f)) for f in wire.encode(template)]
        assert len(packed) == 2 and len(good_frames) == 3
        bad = _mutations(rng, good_frames, packed)
        valid_points = 0
        valid_chunks = 0
        non_finite = 0
        sent_bad = 0
        lucky = 0
        expected_intensity = []
        while sent_bad < N_BAD:
            for _ in range(int(rng.integers(1, 5))):
                m = next(bad)
                st.push.send_multipart(m)
                ok = _decodes(m)
                if ok is None:
                    sent_bad += 1
                else:  # a random byte flip can leave a valid chunk (a digit of seq changed)
                    lucky += 1
                    valid_points += ok.n
                    expected_intensity.append(ok.channels["intensity"].astype(np.float32))
            n = int(rng.integers(0, 300))
            p = rng.uniform(-100, 100, (n, 3))
            if n and rng.random() < 0.1:  # some valid chunks carry NaN/Inf points
                k = int(rng.integers(1, n + 1))
                p[rng.choice(n, k, replace=False), int(rng.integers(0, 3))] = rng.choice([np.nan, np.inf, -np.inf])
            inten = (valid_chunks * 1000 + np.arange(n)).astype(np.float32)
            c = PointChunk(positions=p, channels={"intensity": inten}, seq=valid_chunks, trace_id=new_trace_id())
            fin = np.isfinite(p).all(axis=1)
            non_finite += int((~fin).sum())
            expected_intensity.append(inten[fin])
            if rng.random() < 0.2:  # some valid chunks come as JSON
                st.push.send(json.dumps({"positions": p.tolist(),
                                         "channels": {"intensity": inten.tolist()}}).encode())
            else:
                wire.send(st.push, c)
            valid_points += n
            valid_chunks += 1
        valid_chunks += lucky
        total_msgs = sent_bad + valid_chunks
        stats = st.wait_stats(lambda s: s.get("messages_in") == total_msgs and s.get("queued_points") == 0, timeout=180)
        assert st.proc.is_alive()
        # every malformed message rejected, every valid chunk accepted
        assert stats["rejected_messages"] == sent_bad, stats["rejected"]
        assert stats["chunks_accepted"] == valid_chunks
        assert {"bad_json", "bad_shape", "length_mismatch", "bad_dtype", "bad_count", "truncated",
                "size_mismatch", "too_large", "bad_header", "bad_frame_count"} <= set(stats["rejected"])
        # exact point accounting
        assert stats["points_in"] == valid_points
        assert stats["drops"].get("non_finite", 0) == non_finite
        assert stats["points_in"] == stats["points_out"] + sum(stats["drops"].values())
        assert stats["points_out"] == valid_points - non_finite
        rs = st.ring.stats()
        assert rs.total_written == stats["points_out"] and rs.dropped_points == 0
        # and the valid points are the ones in the ring, in order
        snap = st.ring.snapshot()
        assert np.array_equal(snap.channels["intensity"], np.concatenate(expected_intensity), equal_nan=True)
    finally:
        st.close()
