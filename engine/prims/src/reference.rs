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
