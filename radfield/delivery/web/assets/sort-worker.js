// The depth order of the primitives for one view, as render() orders them
// (core/render/rasterize.py: depth = (w2c applied to the means).z, a stable argsort front to back).
//
// Runs as a module Web Worker (the page posts {means} once, then {id, w2cRow} per view and gets
// {id, order, ms} back); the page also imports `depthOrder` to time it in window.radfield.bench.
//
// The depth is rounded to float32 (as render() computes it in the model's float32) and sorted by
// an LSD radix sort on its bits, so equal float32 depths keep the primitives' index order, as the
// stable argsort does. The order returned is front to back, render()'s compositing order.

// Sortable unsigned key of a float32's bits: flip all bits of negatives, the sign bit of positives.
function floatKeys(depth, keys) {
  const bits = new Uint32Array(depth.buffer, depth.byteOffset, depth.length);
  for (let i = 0; i < bits.length; i++) {
    const b = bits[i];
    keys[i] = b & 0x80000000 ? ~b >>> 0 : (b | 0x80000000) >>> 0;
  }
}

// Scratch buffers kept between calls (one view after another has the same size).
let scratch = null;

function buffers(n) {
  if (!scratch || scratch.n !== n) {
    scratch = { n, depth: new Float32Array(n), keys: new Uint32Array(n), keys2: new Uint32Array(n),
                idx: new Uint32Array(n), idx2: new Uint32Array(n), counts: new Uint32Array(2048) };
  }
  return scratch;
}

// means: Float32Array (P*3); row: the third row of world-to-camera [r0, r1, r2, t] (camera z).
// Returns a new Uint32Array of primitive ids, near to far.
export function depthOrder(means, row) {
  const n = means.length / 3;
  const s = buffers(n);
  const [r0, r1, r2, t] = row;
  for (let i = 0; i < n; i++) s.depth[i] = means[3 * i] * r0 + means[3 * i + 1] * r1 + means[3 * i + 2] * r2 + t;
  floatKeys(s.depth, s.keys);
  for (let i = 0; i < n; i++) s.idx[i] = i;
  // three passes of 11 bits (a stable counting sort each): ascending keys, ties in index order
  let keys = s.keys, keys2 = s.keys2, idx = s.idx, idx2 = s.idx2;
  for (let shift = 0; shift < 32; shift += 11) {
    const counts = s.counts;
    counts.fill(0);
    for (let i = 0; i < n; i++) counts[(keys[i] >>> shift) & 0x7ff]++;
    let sum = 0;
    for (let b = 0; b < 2048; b++) {
      const c = counts[b];
      counts[b] = sum;
      sum += c;
    }
    for (let i = 0; i < n; i++) {
      const at = counts[(keys[i] >>> shift) & 0x7ff]++;
      keys2[at] = keys[i];
      idx2[at] = idx[i];
    }
    [keys, keys2] = [keys2, keys];
    [idx, idx2] = [idx2, idx];
  }
  return idx.slice();
}

// In a worker: answer the page's messages.
if (typeof WorkerGlobalScope !== "undefined" && self instanceof WorkerGlobalScope) {
  let means = null;
  self.onmessage = (event) => {
    const msg = event.data;
    if (msg.means) {
      means = msg.means;
      return;
    }
    const start = performance.now();
    const order = depthOrder(means, msg.row);
    self.postMessage({ id: msg.id, order, ms: performance.now() - start }, [order.buffer]);
  };
}
