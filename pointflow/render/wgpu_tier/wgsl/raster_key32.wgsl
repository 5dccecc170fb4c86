// Key layout of the compute method with 32-bit atomics: two passes; the depth pass writes
// atomicMax(~bits(depth)) per pixel, then the index pass (INDEX_PASS) writes
// atomicMax(~logical) where the point's depth equals the pixel's winner.
@group(0) @binding(6) var<storage, read_write> keys: array<atomic<u32>>;
override INDEX_PASS: bool = false;

struct Key { d: u32, l: u32 };

fn make_key(dbits: u32, logical: u32) -> Key {
  return Key(~dbits, ~logical);
}

fn write_key(i: u32, key: Key) {
  if (INDEX_PASS) {
    if (atomicLoad(&keys[i]) == key.d) { atomicMax(&ikeys[i], key.l); }
  } else {
    // read first: skips the atomic where a nearer point is already there
    if (atomicLoad(&keys[i]) < key.d) { atomicMax(&keys[i], key.d); }
  }
}
