//! LPIPS v0.1 (Zhang et al. 2018, "The Unreasonable Effectiveness of Deep Features as a
//! Perceptual Metric") with the AlexNet or VGG16 backbone, on the CPU.
//!
//! Inputs in [0, 1] are mapped to [-1, 1] and through the LPIPS scaling layer; the backbone's
//! features at five ReLU taps are unit-normalised over channels per pixel, their squared
//! difference weighted by the learned 1x1 `lin` layers, averaged over space and summed over the
//! taps. Convolutions are im2col + a register-blocked f32 matmul, split over the available cores.

use std::path::Path;

use super::error::{check_images, MetricsError, Result};
use crate::data::DataError;
use crate::safetensors::SafeTensors;

/// The LPIPS backbone.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum LpipsNet {
    /// torchvision AlexNet, taps relu1..relu5 (`lpips_alex_v0.1`).
    Alex,
    /// torchvision VGG16, taps relu1_2, relu2_2, relu3_3, relu4_3, relu5_3 (`lpips_vgg_v0.1`).
    Vgg,
}

impl LpipsNet {
    /// Smallest image width and height the backbone accepts (every tap keeps at least a pixel).
    pub fn min_size(self) -> u32 {
        match self {
            LpipsNet::Alex => 31,
            LpipsNet::Vgg => 16,
        }
    }

    fn label(self) -> &'static str {
        match self {
            LpipsNet::Alex => "LPIPS-alex",
            LpipsNet::Vgg => "LPIPS-vgg",
        }
    }

    fn spec(self) -> Vec<Spec> {
        use Spec::{Conv as C, Pool as P, Tap as T};
        match self {
            LpipsNet::Alex => vec![
                C(0, 3, 64, 11, 4, 2),
                T,
                P(3, 2),
                C(3, 64, 192, 5, 1, 2),
                T,
                P(3, 2),
                C(6, 192, 384, 3, 1, 1),
                T,
                C(8, 384, 256, 3, 1, 1),
                T,
                C(10, 256, 256, 3, 1, 1),
                T,
            ],
            LpipsNet::Vgg => {
                let mut s = Vec::new();
                let blocks: [(usize, &[usize]); 5] = [
                    (0, &[3, 64, 64]),
                    (5, &[64, 128, 128]),
                    (10, &[128, 256, 256, 256]),
                    (17, &[256, 512, 512, 512]),
                    (24, &[512, 512, 512, 512]),
                ];
                for (b, (first, ch)) in blocks.into_iter().enumerate() {
                    if b > 0 {
                        s.push(P(2, 2));
                    }
                    for (i, io) in ch.windows(2).enumerate() {
                        s.push(C(first + 2 * i, io[0], io[1], 3, 1, 1));
                    }
                    s.push(T);
                }
                s
            }
        }
    }
}

/// One step of a backbone.
#[derive(Clone, Copy, Debug)]
enum Spec {
    /// `features.{index}` conv + ReLU: index, in, out channels, kernel, stride, padding.
    Conv(usize, usize, usize, usize, usize, usize),
    /// Max pool: window, stride (no padding, floor).
    Pool(usize, usize),
    /// An LPIPS tap: the current features are compared.
    Tap,
}

#[derive(Debug)]
enum Layer {
    Conv(Conv),
    Pool(usize, usize),
    Tap,
}

/// A feature map, channels last (`h * w * c` values).
#[derive(Clone, Debug)]
struct Map {
    h: usize,
    w: usize,
    c: usize,
    data: Vec<f32>,
}

/// Rows of the matmul micro-tile (output pixels).
const MR: usize = 4;
/// Columns of the micro-tile (output channels).
const NR: usize = 8;
/// Output pixels per im2col block.
const MC: usize = 64;
/// Reduction depth per pass over a block (keeps the weight panel in L1).
const KC: usize = 256;

/// A convolution followed by ReLU, weights packed for the matmul.
#[derive(Debug)]
struct Conv {
    cin: usize,
    cout: usize,
    k: usize,
    stride: usize,
    pad: usize,
    /// Weights as `[cout / NR panels][k * k * cin][NR]`, output channels padded with zeros; the
    /// reduction index is `(ky * k + kx) * cin + ci`, matching the channels-last im2col.
    packed: Vec<f32>,
    /// Bias, padded to a multiple of NR.
    bias: Vec<f32>,
}

impl Conv {
    /// From PyTorch's `[cout, cin, k, k]` weights.
    fn new(w: &[f32], mut bias: Vec<f32>, cin: usize, cout: usize, k: usize) -> Conv {
        let kk = k * k * cin;
        let npad = cout.div_ceil(NR) * NR;
        let mut packed = vec![0.0; npad * kk];
        for (co, wo) in w.chunks_exact(cin * k * k).enumerate() {
            for (ci, wi) in wo.chunks_exact(k * k).enumerate() {
                for (t, &v) in wi.iter().enumerate() {
                    packed[((co / NR) * kk + t * cin + ci) * NR + co % NR] = v;
                }
            }
        }
        bias.resize(npad, 0.0);
        Conv {
            cin,
            cout,
            k,
            stride: 1,
            pad: 0,
            packed,
            bias,
        }
    }

    fn out_len(&self, n: usize) -> usize {
        (n + 2 * self.pad - self.k) / self.stride + 1
    }

    fn forward(&self, x: &Map) -> Map {
        let (h, w) = (self.out_len(x.h), self.out_len(x.w));
        let m = h * w;
        let mut data = vec![0.0; m * self.cout];
        let threads = std::thread::available_parallelism()
            .map_or(1, |n| n.get())
            .min(m.div_ceil(MC));
        let per = m.div_ceil(threads.max(1)) * self.cout;
        if threads <= 1 {
            self.run(x, w, 0, &mut data);
        } else {
            std::thread::scope(|s| {
                for (t, chunk) in data.chunks_mut(per).enumerate() {
                    s.spawn(move || self.run(x, w, t * per / self.cout, chunk));
                }
            });
        }
        Map {
            h,
            w,
            c: self.cout,
            data,
        }
    }

    /// Output pixels `p0..` (as many as `out` holds) of an output `ow` pixels wide.
    fn run(&self, x: &Map, ow: usize, p0: usize, out: &mut [f32]) {
        let kk = self.k * self.k * self.cin;
        let npad = self.bias.len();
        let mut a = vec![0.0; MC * kk];
        let mut c = vec![0.0; MC * npad];
        for (bi, oblock) in out.chunks_mut(MC * self.cout).enumerate() {
            let mb = oblock.len() / self.cout;
            let tiles = mb.div_ceil(MR);
            self.im2col(x, ow, p0 + bi * MC, mb, &mut a[..tiles * MR * kk]);
            for row in c.chunks_exact_mut(npad) {
                row.copy_from_slice(&self.bias);
            }
            for kc in (0..kk).step_by(KC) {
                let ke = (kc + KC).min(kk);
                for p in 0..npad / NR {
                    let bp = &self.packed[(p * kk + kc) * NR..(p * kk + ke) * NR];
                    for t in 0..tiles {
                        let ap = &a[(t * kk + kc) * MR..(t * kk + ke) * MR];
                        let mut acc = [[0.0; NR]; MR];
                        for (r, acc) in acc.iter_mut().enumerate() {
                            acc.copy_from_slice(&c[(t * MR + r) * npad + p * NR..][..NR]);
                        }
                        micro_kernel(ap, bp, &mut acc);
                        for (r, acc) in acc.iter().enumerate() {
                            c[(t * MR + r) * npad + p * NR..][..NR].copy_from_slice(acc);
                        }
                    }
                }
            }
            for (o, cr) in oblock.chunks_exact_mut(self.cout).zip(c.chunks_exact(npad)) {
                o.iter_mut().zip(cr).for_each(|(o, &v)| *o = v.max(0.0));
            }
        }
    }

    /// Patches of output pixels `p0..p0 + mb` into `a` as `[tile][k * k * cin][MR]`; taps in
    /// the padding and rows past `mb` are zero.
    fn im2col(&self, x: &Map, ow: usize, p0: usize, mb: usize, a: &mut [f32]) {
        let (k, cin) = (self.k, self.cin);
        let kk = k * k * cin;
        a.fill(0.0);
        for i in 0..mb {
            let (oy, ox) = ((p0 + i) / ow, (p0 + i) % ow);
            let at = &mut a[(i / MR) * kk * MR..][..kk * MR];
            let r = i % MR;
            for ky in 0..k {
                let Some(iy) = (oy * self.stride + ky)
                    .checked_sub(self.pad)
                    .filter(|&y| y < x.h)
                else {
                    continue;
                };
                for kx in 0..k {
                    let Some(ix) = (ox * self.stride + kx)
                        .checked_sub(self.pad)
                        .filter(|&v| v < x.w)
                    else {
                        continue;
                    };
                    let src = &x.data[(iy * x.w + ix) * cin..][..cin];
                    let dst = &mut at[(ky * k + kx) * cin * MR..][..cin * MR];
                    for (d, &s) in dst.chunks_exact_mut(MR).zip(src) {
                        d[r] = s;
                    }
                }
            }
        }
    }
}

/// `acc += a * b` for an `MR x depth` packed slice of A and a `depth x NR` one of B.
#[inline(always)]
fn micro_kernel(a: &[f32], b: &[f32], acc: &mut [[f32; NR]; MR]) {
    for (av, bv) in a.chunks_exact(MR).zip(b.chunks_exact(NR)) {
        for (acc, &ar) in acc.iter_mut().zip(av) {
            for (c, &bj) in acc.iter_mut().zip(bv) {
                *c += ar * bj;
            }
        }
    }
}

/// Max pool without padding, floor mode; the input is at least `k` x `k`.
fn max_pool(x: &Map, k: usize, s: usize) -> Map {
    let (h, w) = ((x.h - k) / s + 1, (x.w - k) / s + 1);
    let mut data = vec![f32::NEG_INFINITY; h * w * x.c];
    for (i, o) in data.chunks_exact_mut(x.c).enumerate() {
        let (oy, ox) = (i / w, i % w);
        for iy in oy * s..oy * s + k {
            for ix in ox * s..ox * s + k {
                let src = &x.data[(iy * x.w + ix) * x.c..][..x.c];
                o.iter_mut().zip(src).for_each(|(o, &v)| *o = o.max(v));
            }
        }
    }
    Map { h, w, c: x.c, data }
}

/// The LPIPS scaling layer: `x = ((2 v - 1) - shift) / scale` per channel.
const SHIFT: [f32; 3] = [-0.030, -0.088, -0.188];
const SCALE: [f32; 3] = [0.458, 0.448, 0.450];

fn weights_error(e: DataError) -> MetricsError {
    match e {
        DataError::Io { path, error } => MetricsError::Io { path, error },
        DataError::Malformed { path, problem } | DataError::Image { path, problem } => {
            MetricsError::Weights { path, problem }
        }
    }
}

/// An LPIPS model: backbone and linear layers.
#[derive(Debug)]
pub struct Lpips {
    net: LpipsNet,
    layers: Vec<Layer>,
    /// Per tap, the `lin` weights (one per channel).
    lins: Vec<Vec<f32>>,
}

impl Lpips {
    /// Loads the v0.1 weights of `net` from a safetensors file (`features.{i}.weight` / `.bias`
    /// of the torchvision backbone, `lin{0..4}.weight` of shape `[1, C, 1, 1]`).
    pub fn load(path: &Path, net: LpipsNet) -> Result<Lpips> {
        let t = SafeTensors::read(path).map_err(weights_error)?;
        Self::build(net, |name, shape| {
            t.get(name, shape, path)
                .map(|t| t.data.clone())
                .map_err(weights_error)
        })
    }

    /// The model from a tensor source called with each name and expected shape.
    fn build(
        net: LpipsNet,
        mut get: impl FnMut(&str, &[usize]) -> Result<Vec<f32>>,
    ) -> Result<Lpips> {
        let mut layers = Vec::new();
        let mut lins = Vec::new();
        let mut channels = 3;
        for s in net.spec() {
            layers.push(match s {
                Spec::Conv(i, cin, cout, k, stride, pad) => {
                    let w = get(&format!("features.{i}.weight"), &[cout, cin, k, k])?;
                    let b = get(&format!("features.{i}.bias"), &[cout])?;
                    channels = cout;
                    Layer::Conv(Conv {
                        stride,
                        pad,
                        ..Conv::new(&w, b, cin, cout, k)
                    })
                }
                Spec::Pool(k, stride) => Layer::Pool(k, stride),
                Spec::Tap => {
                    lins.push(get(
                        &format!("lin{}.weight", lins.len()),
                        &[1, channels, 1, 1],
                    )?);
                    Layer::Tap
                }
            });
        }
        Ok(Lpips { net, layers, lins })
    }

    /// The backbone.
    pub fn net(&self) -> LpipsNet {
        self.net
    }

    /// Backbone features at the taps of an image that passed the size checks.
    fn features(&self, img: &[f32], width: usize, height: usize) -> Vec<Map> {
        let data = img
            .iter()
            .enumerate()
            .map(|(i, &v)| (2.0 * v - 1.0 - SHIFT[i % 3]) / SCALE[i % 3])
            .collect();
        let mut x = Map {
            h: height,
            w: width,
            c: 3,
            data,
        };
        let mut taps = Vec::with_capacity(self.lins.len());
        for layer in &self.layers {
            match layer {
                Layer::Conv(c) => x = c.forward(&x),
                Layer::Pool(k, s) => x = max_pool(&x, *k, *s),
                Layer::Tap => taps.push(x.clone()),
            }
        }
        taps
    }

    /// The LPIPS distance of two `width` x `height` interleaved RGB images in [0, 1]: 0 for
    /// identical images, symmetric. Errors on mismatched sizes and images smaller than
    /// [`LpipsNet::min_size`].
    pub fn distance(&self, a: &[f32], b: &[f32], width: u32, height: u32) -> Result<f64> {
        check_images(a, b, width, height, self.net.min_size(), self.net.label())?;
        let (w, h) = (width as usize, height as usize);
        let (fa, fb) = (self.features(a, w, h), self.features(b, w, h));
        let mut d = 0.0;
        for ((x, y), lin) in fa.iter().zip(&fb).zip(&self.lins) {
            let inv_norm = |p: &[f32]| {
                1.0 / (p.iter().map(|&v| v as f64 * v as f64).sum::<f64>().sqrt() + 1e-10)
            };
            let mut sum = 0.0;
            for (p, q) in x.data.chunks_exact(x.c).zip(y.data.chunks_exact(y.c)) {
                let (np, nq) = (inv_norm(p), inv_norm(q));
                sum += p
                    .iter()
                    .zip(q)
                    .zip(lin)
                    .map(|((&u, &v), &l)| l as f64 * (u as f64 * np - v as f64 * nq).powi(2))
                    .sum::<f64>();
            }
            d += sum / (x.h * x.w) as f64;
        }
        Ok(d)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::metrics::tests::noise;
    use crate::metrics::MetricsError;

    fn conv_direct(
        x: &Map,
        w: &[f32],
        b: &[f32],
        cout: usize,
        k: usize,
        s: usize,
        p: usize,
    ) -> Map {
        let oh = (x.h + 2 * p - k) / s + 1;
        let ow = (x.w + 2 * p - k) / s + 1;
        let mut data = Vec::new();
        for oy in 0..oh {
            for ox in 0..ow {
                for co in 0..cout {
                    let mut acc = b[co] as f64;
                    for ci in 0..x.c {
                        for ky in 0..k {
                            for kx in 0..k {
                                let (iy, ix) = (
                                    (oy * s + ky) as isize - p as isize,
                                    (ox * s + kx) as isize - p as isize,
                                );
                                if iy >= 0 && ix >= 0 && (iy as usize) < x.h && (ix as usize) < x.w
                                {
                                    let v = x.data[(iy as usize * x.w + ix as usize) * x.c + ci];
                                    acc += v as f64 * w[((co * x.c + ci) * k + ky) * k + kx] as f64;
                                }
                            }
                        }
                    }
                    data.push(acc.max(0.0) as f32);
                }
            }
        }
        Map {
            h: oh,
            w: ow,
            c: cout,
            data,
        }
    }

    #[test]
    fn conv_matches_direct_loop() {
        // (in h, w, cin, cout, k, stride, pad): odd sizes, cout not a multiple of NR, K > KC,
        // enough pixels for several blocks and threads.
        for (seed, &(h, w, cin, cout, k, s, p)) in [
            (37, 29, 3, 10, 11, 4, 2),
            (20, 23, 5, 16, 3, 1, 1),
            (9, 11, 40, 9, 5, 1, 2),
            (4, 4, 1, 3, 3, 2, 0),
        ]
        .iter()
        .enumerate()
        {
            let seed = seed as u64 * 10;
            let x = Map {
                h,
                w,
                c: cin,
                data: noise(h * w * cin, seed).iter().map(|v| v - 0.5).collect(),
            };
            let wt: Vec<f32> = noise(cout * cin * k * k, seed + 1)
                .iter()
                .map(|v| v - 0.5)
                .collect();
            let b: Vec<f32> = noise(cout, seed + 2).iter().map(|v| v - 0.3).collect();
            let got = Conv {
                stride: s,
                pad: p,
                ..Conv::new(&wt, b.clone(), cin, cout, k)
            }
            .forward(&x);
            let want = conv_direct(&x, &wt, &b, cout, k, s, p);
            assert_eq!((got.h, got.w, got.c), (want.h, want.w, want.c));
            for (g, e) in got.data.iter().zip(&want.data) {
                assert!((g - e).abs() < 1e-4 * (1.0 + e.abs()), "{g} vs {e}");
            }
        }
    }

    #[test]
    fn max_pool_floor_mode() {
        let x = Map {
            h: 5,
            w: 4,
            c: 2,
            data: (0..40).map(|v| ((v * 7) % 13) as f32).collect(),
        };
        let y = max_pool(&x, 3, 2);
        assert_eq!((y.h, y.w), (2, 1));
        let at = |y: usize, x_: usize, c: usize| x.data[(y * 4 + x_) * 2 + c];
        for c in 0..2 {
            let m = (0..3)
                .flat_map(|i| (0..3).map(move |j| (i, j)))
                .map(|(i, j)| at(2 + i, j, c))
                .fold(f32::MIN, f32::max);
            assert_eq!(y.data[2 + c], m);
        }
    }

    /// A model with small random weights (the real ones come from the shared data; see the
    /// integration tests for the goldens).
    fn random_model(net: LpipsNet) -> Lpips {
        let mut seed = 100;
        Lpips::build(net, |_, shape| {
            seed += 1;
            let n: usize = shape.iter().product();
            let fan_in = (n / shape[0]) as f32;
            Ok(noise(n, seed)
                .iter()
                .map(|v| (v - 0.45) * (6.0 / fan_in).sqrt())
                .collect())
        })
        .unwrap()
    }

    #[test]
    fn random_models_are_zero_on_equal_symmetric_and_check_sizes() {
        for net in [LpipsNet::Alex, LpipsNet::Vgg] {
            let m = random_model(net);
            let s = net.min_size();
            let n = (3 * s * s) as usize;
            let (a, b) = (noise(n, 7), noise(n, 8));
            assert_eq!(m.distance(&a, &a, s, s).unwrap(), 0.0);
            let d = m.distance(&a, &b, s, s).unwrap();
            assert!(d.is_finite() && d > 0.0, "{d}");
            assert_eq!(d, m.distance(&b, &a, s, s).unwrap());
            let small = (3 * (s - 1) * s) as usize;
            let e = m.distance(&a[..small], &b[..small], s, s - 1).unwrap_err();
            assert!(matches!(e, MetricsError::TooSmall { .. }), "{e}");
            let e = m.distance(&a, &b, s + 1, s).unwrap_err();
            assert!(matches!(e, MetricsError::SizeMismatch { .. }), "{e}");
        }
    }

    #[test]
    fn missing_weights_name_the_file() {
        let p = std::env::temp_dir().join("extranerf-no-such-lpips.safetensors");
        let e = Lpips::load(&p, LpipsNet::Alex).unwrap_err();
        assert!(e.to_string().contains(&p.display().to_string()), "{e}");
    }
}
