// Key layout of the compute method with 64-bit atomics (shader-int64-atomic-min-max): the
// whole key ~(bits(depth) << 32 | logical) in one atomicMax (the buffer is cleared to 0, so
// the largest stored value is the nearest point, ties to the lower logical index).
@group(0) @binding(6) var<storage, read_write> keys: array<atomic<u64>>;
const INDEX_PASS: bool = false;

struct Key { k: u64 };

fn make_key(dbits: u32, logical: u32) -> Key {
  return Key(~((u64(dbits) << 32u) | u64(logical)));
}

// read the key before the atomic: skips the atomic where a nearer point is already there
fn write_key(i: u32, key: Key) {
  if (atomicLoad(&keys[i]) < key.k) { atomicMax(&keys[i], key.k); }
}
