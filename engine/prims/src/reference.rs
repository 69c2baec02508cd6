//! Plain-Rust definitions of every primitive (f64 where precision matters); the tests compare
//! the kernels against these on random inputs.

/// `data[0..n] = value`.
pub fn fill(data: &mut [u32], n: usize, value: u32) {
    data[..n].iter_mut().for_each(|d| *d = value);
}

/// `start + i` for `i < n` (wrapping).
pub fn iota(n: usize, start: u32) -> Vec<u32> {
    (0..n as u32).map(|i| start.wrapping_add(i)).collect()
}

/// `a * x + y` per element, in f64.
pub fn saxpy(a: f32, x: &[f32], y: &[f32]) -> Vec<f64> {
    x.iter()
        .zip(y)
        .map(|(&x, &y)| a as f64 * x as f64 + y as f64)
        .collect()
}

/// The exact sum in f64 and the sum of magnitudes (for error bounds).
pub fn sum(x: &[f32]) -> (f64, f64) {
    x.iter().fold((0.0, 0.0), |(s, a), &v| {
        (s + v as f64, a + (v as f64).abs())
    })
}

/// Exclusive prefix sum with wrapping u32 arithmetic; returns the scan and the total.
pub fn exclusive_scan(x: &[u32], binarize: bool) -> (Vec<u32>, u32) {
    let mut run = 0u32;
    let out = x
        .iter()
        .map(|&v| {
            let r = run;
            run = run.wrapping_add(if binarize { v.min(1) } else { v });
            r
        })
        .collect();
    (out, run)
}

/// The flagged values (or indices when `values` is `None`), in order.
pub fn compact(flags: &[u32], values: Option<&[u32]>) -> Vec<u32> {
    flags
        .iter()
        .enumerate()
        .filter(|(_, &f)| f != 0)
        .map(|(i, _)| values.map_or(i as u32, |v| v[i]))
        .collect()
}

/// Stable sort of (key, value) pairs by the low `bits` bits of the key.
pub fn radix_sort(keys: &[u32], values: &[u32], bits: u32) -> (Vec<u32>, Vec<u32>) {
    let mask = if bits >= 32 {
        u32::MAX
    } else {
        (1u32 << bits) - 1
    };
    let mut pairs: Vec<(u32, u32)> = keys.iter().copied().zip(values.iter().copied()).collect();
    pairs.sort_by_key(|&(k, _)| k & mask);
    pairs.into_iter().unzip()
}

/// `acc[idx] += value` in f64, skipping indices past `acc.len()`; also returns, per target,
/// the sum of magnitudes added (for error bounds).
pub fn scatter_add(acc: &[f32], indices: &[u32], values: &[f32]) -> (Vec<f64>, Vec<f64>) {
    let mut out: Vec<f64> = acc.iter().map(|&a| a as f64).collect();
    let mut mag: Vec<f64> = acc.iter().map(|&a| (a as f64).abs()).collect();
    for (&i, &v) in indices.iter().zip(values) {
        if let Some(o) = out.get_mut(i as usize) {
            *o += v as f64;
            mag[i as usize] += (v as f64).abs();
        }
    }
    (out, mag)
}

/// A small deterministic generator (SplitMix64) so tests and benches need no extra crate.
#[derive(Clone, Debug)]
pub struct Rng(u64);

impl Rng {
    /// Seeded generator.
    pub fn new(seed: u64) -> Rng {
        Rng(seed)
    }

    /// Next 64 random bits.
    pub fn next_u64(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9e37_79b9_7f4a_7c15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
        z ^ (z >> 31)
    }

    /// Next 32 random bits.
    pub fn next_u32(&mut self) -> u32 {
        (self.next_u64() >> 32) as u32
    }

    /// Uniform in [lo, hi).
    pub fn uniform(&mut self, lo: f32, hi: f32) -> f32 {
        let u = (self.next_u64() >> 40) as f32 / (1u64 << 24) as f32;
        lo + (hi - lo) * u
    }

    /// Uniform integer below `n` (n > 0).
    pub fn below(&mut self, n: u32) -> u32 {
        ((self.next_u32() as u64 * n as u64) >> 32) as u32
    }
}

/// The microbenchmarks' random sequence (`kernels/wgsl/common/micro.wgsl`): lane `lane`'s first
/// state with `share` lanes per sequence.
fn micro_seed(lane: u32, share: u32) -> u32 {
    (lane / share).wrapping_mul(2654435769) ^ 0x6d2b79f5
}

fn micro_next(s: u32) -> u32 {
    s.wrapping_mul(1664525).wrapping_add(1013904223)
}

/// The random table indices lane `lane` of `op` visits, in order.
pub fn micro_indices(op: crate::micro::MicroOp, lane: u32, ops: u32) -> Vec<u32> {
    let shift = 32 - op.log2_entries();
    let mut s = micro_seed(lane, op.share());
    (0..op.kernel_ops(ops))
        .map(|_| {
            s = micro_next(s);
            s >> shift
        })
        .collect()
}

/// What lane `lane` of microbenchmark `op` writes for `ops` requested operations, in f64:
/// `weights` (64 x 64 row-major, then 64 biases) and `inputs` (per lane 4 points x 64) as
/// given to [`crate::micro::Micro::new`]. The atomics write no lane result: see
/// [`micro_atomic_counts`].
pub fn micro_lane(
    op: crate::micro::MicroOp,
    lane: u32,
    ops: u32,
    weights: &[f32],
    inputs: &[f32],
) -> f64 {
    use crate::micro::{MicroOp, DENSE_GROUP, DENSE_WIDTH, FMA_C, FMA_M};
    // The table's entry e is e mod 8, read at the op's width.
    let entry = |e: u32| (e % 8) as f64;
    let n = op.kernel_ops(ops);
    let w = DENSE_WIDTH as usize;
    let point = |q: usize| -> Vec<f64> {
        let at = (lane as usize * DENSE_GROUP as usize + q) * w;
        inputs[at..at + w].iter().map(|&v| v as f64).collect()
    };
    let layer = |a: &[f64]| -> Vec<f64> {
        (0..w)
            .map(|o| {
                let z = (0..w)
                    .map(|j| weights[o * w + j] as f64 * a[j])
                    .sum::<f64>()
                    + weights[w * w + o] as f64;
                z.max(0.0)
            })
            .collect()
    };
    let back = |d: &[f64]| -> Vec<f64> {
        (0..w)
            .map(|j| (0..w).map(|o| weights[o * w + j] as f64 * d[o]).sum())
            .collect()
    };
    match op {
        MicroOp::Index => micro_indices(op, lane, ops)
            .iter()
            .map(|&i| (i & 7) as f64)
            .sum(),
        MicroOp::Read4 | MicroOp::Read4Near => {
            micro_indices(op, lane, ops).iter().map(|&i| entry(i)).sum()
        }
        MicroOp::ReadPair | MicroOp::ReadPairBranch | MicroOp::Read8 => {
            micro_indices(op, lane, ops)
                .iter()
                .map(|&i| entry(2 * i) + 2.0 * entry(2 * i + 1))
                .sum()
        }
        MicroOp::Read16 => micro_indices(op, lane, ops)
            .iter()
            .map(|&i| {
                (0..4)
                    .map(|c| (c + 1) as f64 * entry(4 * i + c))
                    .sum::<f64>()
            })
            .sum(),
        MicroOp::SameAddress => {
            // small[e] = e mod 5 for the 64 floats (16 vec4s), read in turn.
            let base = (lane & 7) as f64 * 10.0;
            base + (0..n)
                .map(|k| {
                    let v = k % 16;
                    (0..4)
                        .map(|c| (c + 1) as f64 * ((4 * v + c) % 5) as f64)
                        .sum::<f64>()
                })
                .sum::<f64>()
        }
        // Each op adds (1, 2, 3, 4) to one of the lane's vec4s; the lane sums its region.
        MicroOp::Workgroup | MicroOp::Storage => 10.0 * n as f64,
        MicroOp::Atomic { .. } | MicroOp::AtomicPrefetched | MicroOp::AtomicU32 => 0.0,
        MicroOp::Fma => {
            let x = (lane & 63) as f64 / 64.0;
            (0..32)
                .map(|c| {
                    let mut a = (x + c as f64) as f32 as f64;
                    for _ in 0..n / 32 {
                        a = a * FMA_M as f64 + FMA_C as f64;
                    }
                    a
                })
                .sum()
        }
        MicroOp::Dense1 => {
            let mut a = point(0);
            for _ in 0..n {
                a = layer(&a);
            }
            a.iter().sum()
        }
        MicroOp::Dense4 | MicroOp::Dense4Back => (0..DENSE_GROUP as usize)
            .map(|q| {
                let mut a = point(q);
                for _ in 0..n {
                    a = if op == MicroOp::Dense4 {
                        layer(&a)
                    } else {
                        back(&a)
                    };
                }
                a.iter().sum::<f64>()
            })
            .sum(),
    }
}

/// The atomics' target after one run of [`crate::micro::MicroOp::Atomic`] from zero: each
/// entry's count of adds (entries not listed stay 0).
pub fn micro_atomic_counts(
    op: crate::micro::MicroOp,
    lanes: u32,
    ops: u32,
) -> std::collections::BTreeMap<u32, u32> {
    let mut counts = std::collections::BTreeMap::new();
    for lane in 0..lanes {
        for i in micro_indices(op, lane, ops) {
            *counts.entry(i).or_insert(0) += 1;
        }
    }
    counts
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn scan_wraps_and_binarizes() {
        assert_eq!(
            exclusive_scan(&[3, 0, u32::MAX, 2], false),
            (vec![0, 3, 3, 2], 4)
        );
        assert_eq!(exclusive_scan(&[3, 0, 7, 1], true), (vec![0, 1, 1, 2], 3));
    }

    #[test]
    fn sort_is_stable_on_masked_keys() {
        let (k, v) = radix_sort(&[0x15, 0x05, 0x13, 0x01], &[0, 1, 2, 3], 4);
        assert_eq!(k, vec![0x01, 0x13, 0x15, 0x05]);
        assert_eq!(v, vec![3, 2, 0, 1]);
    }

    #[test]
    fn compact_keeps_order() {
        assert_eq!(compact(&[0, 2, 0, 1], None), vec![1, 3]);
        assert_eq!(compact(&[1, 0, 1], Some(&[7, 8, 9])), vec![7, 9]);
    }

    #[test]
    fn scatter_skips_out_of_range() {
        let (o, m) = scatter_add(&[1.0, 0.0], &[0, 5, 0, 1], &[2.0, 9.0, -1.0, 4.0]);
        assert_eq!(o, vec![2.0, 4.0]);
        assert_eq!(m, vec![4.0, 4.0]);
    }
}
