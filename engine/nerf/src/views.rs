//! Training views: captured photos and virtual views with their per-pixel colour weights and
//! depth targets, how a batch's rays are spread over them, and their packed copy on the device.

use serde::{Deserialize, Serialize};

use extranerf_gpu::{count_u32, Buffer, Context, GpuError, Result};

use crate::data::{unorm8, Camera, Image};
use crate::render::rays::{gpu_camera, GpuCamera};

/// Where a training view comes from, which decides its colour loss.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub enum ViewKind {
    /// A photograph: the configured colour loss (L2 or Huber), scaled by the pixel's weight.
    Captured,
    /// A virtual view (an inpainted render): L1 on colour scaled by the pixel's weight, as
    /// ExtraNeRF supervises with its w(t)-weighted L1 (smooth L1 with
    /// [`crate::trainer::TrainConfig::virtual_l1_core`]). Its rays are sampled at stratum
    /// centres, never jittered: its target is a render made that way, and under jittered
    /// samples a target within the jitter's noise of the field's own render makes the loss
    /// reward a smoother (blurrier) field.
    Virtual,
}

/// One training view.
#[derive(Clone, Debug)]
pub struct View {
    pub camera: Camera,
    pub image: Image,
    /// Per-pixel `(depth, confidence)` target in the ray space's units (view depth in world
    /// space, t in NDC); confidence 0 = no target.
    pub depth: Option<Vec<[f32; 2]>>,
    /// Per-pixel colour weight (finite, >= 0; 0 = the pixel's colour is not supervised);
    /// None = 1 everywhere.
    pub weight: Option<Vec<f32>>,
    pub kind: ViewKind,
}

impl View {
    /// A photograph with every pixel's colour weighted 1.
    pub fn captured(camera: Camera, image: Image, depth: Option<Vec<[f32; 2]>>) -> View {
        View {
            camera,
            image,
            depth,
            weight: None,
            kind: ViewKind::Captured,
        }
    }

    /// Pixels of the view.
    pub fn pixels(&self) -> usize {
        self.image.width as usize * self.image.height as usize
    }
}

/// The signed colour weight that a training pixel carries in its fourth channel (the kernels'
/// encoding, common/ray_loss.wgsl): `w` for captured views, `-w` for virtual views (L1).
pub fn colour_weight(kind: ViewKind, w: f32) -> f32 {
    match kind {
        ViewKind::Captured => w,
        ViewKind::Virtual => -w,
    }
}

/// How a batch's rays are spread over the training views.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum ViewSampling {
    /// Every view equally likely (then every pixel of it).
    Uniform,
    /// This fraction of the rays from virtual views, the rest from captured ones, each kind
    /// spread evenly over its views (all rays from the kind present when only one is).
    VirtualFraction(f32),
}

impl ViewSampling {
    /// Each view's probability of being drawn for a ray (summing to 1).
    pub fn probabilities(&self, views: &[View]) -> Result<Vec<f64>> {
        let n = views.len();
        let virt = views.iter().filter(|v| v.kind == ViewKind::Virtual).count();
        let capt = n - virt;
        match *self {
            ViewSampling::Uniform => Ok(vec![1.0 / n as f64; n]),
            ViewSampling::VirtualFraction(f) => {
                if !(0.0..=1.0).contains(&f) {
                    return Err(GpuError::Usage(format!(
                        "the fraction of rays from virtual views is {f}; give one from 0 to 1"
                    )));
                }
                let f = match (capt, virt) {
                    (_, 0) => 0.0,
                    (0, _) => 1.0,
                    _ => f as f64,
                };
                Ok(views
                    .iter()
                    .map(|v| match v.kind {
                        ViewKind::Captured => (1.0 - f) / capt as f64,
                        ViewKind::Virtual => f / virt as f64,
                    })
                    .collect())
            }
        }
    }
}

/// A batch as the batch kernel drew it ([`crate::trainer::Trainer::draw_batch`]).
#[derive(Clone, Debug, PartialEq)]
pub struct DrawnBatch {
    /// Per ray: the view's index and the pixel's y * width + x.
    pub pixels: Vec<[u32; 2]>,
    /// Per ray: the target colour (composited over the ray's background where the image has
    /// alpha) and its signed colour weight ([`colour_weight`]).
    pub targets: Vec<[f32; 4]>,
    /// Per ray: the depth target and its confidence (0: none).
    pub depths: Vec<[f32; 2]>,
}

/// Fixed-point bits of the batch kernel's cumulative image probabilities (render/batch.wgsl).
const CDF_BITS: u32 = 24;

/// The batch kernel's cumulative bounds for probabilities `p` (render/batch.wgsl): image i owns
/// \[cdf\[i - 1\], cdf\[i\]) of [0, 2^24); the last bound is 2^24 and a zero probability gives an
/// empty share.
pub fn image_cdf(p: &[f64]) -> Result<Vec<u32>> {
    let total: f64 = p.iter().sum();
    if p.is_empty() || p.iter().any(|v| !(v.is_finite() && *v >= 0.0)) || total <= 0.0 {
        return Err(GpuError::Usage(format!(
            "view sampling probabilities must be finite, non-negative and not all zero: {p:?}"
        )));
    }
    let scale = (1u64 << CDF_BITS) as f64;
    let mut acc = 0.0;
    let mut cdf: Vec<u32> = p
        .iter()
        .map(|v| {
            acc += v / total;
            (acc * scale).round().min(scale) as u32
        })
        .collect();
    // Rounding must not leave the top of the range unowned: the last image with a share ends it.
    let top = 1u32 << CDF_BITS;
    let last = p.iter().rposition(|v| *v > 0.0).unwrap_or(p.len() - 1);
    for c in &mut cdf[last..] {
        *c = top;
    }
    Ok(cdf)
}

/// Bindings of the pixel store that the batch kernel takes (render/batch.wgsl).
pub const STORE_BINDINGS: usize = 8;

/// The depth block marker of a view without depth targets (render/batch.wgsl `NO_DEPTH`).
const NO_DEPTH: u32 = u32::MAX;

/// A view's colour and depth blocks in the pixel store (render/batch.wgsl `Place`): binding and
/// first element of the colour block, of the depth block ([`NO_DEPTH`]: none), then width,
/// height, the view's index and padding.
type Place = [u32; 8];

/// One pixel's colour word: rgb and alpha as rgba8 (WGSL's `pack4x8unorm`).
pub fn pack_rgba8(rgb: &[f32], alpha: f32) -> u32 {
    u32::from_le_bytes([
        unorm8(rgb[0]),
        unorm8(rgb[1]),
        unorm8(rgb[2]),
        unorm8(alpha),
    ])
}

/// The training views on the device: cameras, the compact pixel store (rgba8 colour, signed
/// f32 colour weight, and f32 depth targets for the views that have them), spread over as
/// many bindings as the device's binding limit needs, and the images' sampling table.
#[derive(Debug)]
pub struct TrainData {
    pub(crate) cameras: Buffer<GpuCamera>,
    pub(crate) places: Buffer<Place>,
    pub(crate) store: Vec<Buffer<[u32; 2]>>,
    pub(crate) cdf: Buffer<u32>,
    pub(crate) n_images: u32,
    pixels: u64,
}

/// Packs blocks of elements into bindings of at most `capacity` elements, first fit in order;
/// returns per block its (binding, first element) and the bindings' lengths.
fn pack_blocks(blocks: &[usize], capacity: usize) -> (Vec<(u32, u32)>, Vec<usize>) {
    let mut used: Vec<usize> = Vec::new();
    let mut at = Vec::with_capacity(blocks.len());
    for &n in blocks {
        let b = match used.iter().position(|&u| u + n <= capacity) {
            Some(b) => b,
            None => {
                used.push(0);
                used.len() - 1
            }
        };
        at.push((b as u32, used[b] as u32));
        used[b] += n;
    }
    (at, used)
}

impl TrainData {
    /// Uploads `views`, every view equally likely per ray.
    pub fn new(ctx: &Context, views: &[View]) -> Result<TrainData> {
        TrainData::with_sampling(ctx, views, ViewSampling::Uniform)
    }

    /// Uploads `views`, drawn per ray as `sampling` says.
    pub fn with_sampling(
        ctx: &Context,
        views: &[View],
        sampling: ViewSampling,
    ) -> Result<TrainData> {
        TrainData::with_binding_limit(ctx, views, sampling, ctx.info().max_storage_buffer_range)
    }

    /// [`TrainData::with_sampling`] as if one binding held at most `limit` bytes (the tests
    /// spread small scenes over several bindings with it).
    pub fn with_binding_limit(
        ctx: &Context,
        views: &[View],
        sampling: ViewSampling,
        limit: u64,
    ) -> Result<TrainData> {
        if views.is_empty() {
            return Err(GpuError::Usage("no training views".into()));
        }
        let probabilities = sampling.probabilities(views)?;
        // Colour blocks, then depth blocks, each whole in one binding.
        let mut blocks = Vec::new();
        for (i, v) in views.iter().enumerate() {
            let (cam, img) = (&v.camera, &v.image);
            let px = v.pixels();
            if (cam.width, cam.height) != (img.width, img.height) {
                return Err(GpuError::Usage(format!(
                    "view {i}: camera is {}x{} but its image {} is {}x{}",
                    cam.width,
                    cam.height,
                    cam.image.display(),
                    img.width,
                    img.height
                )));
            }
            let len_err = |what: &str, n: usize| {
                GpuError::Usage(format!(
                    "view {i} ({}): {n} {what} for {px} pixels",
                    cam.image.display()
                ))
            };
            if img.rgb.len() != px * 3 {
                return Err(len_err("colour values (3 per pixel)", img.rgb.len()));
            }
            // Per-pixel values: the right count, each valid.
            let check = |what: &str, values: Option<&Vec<f32>>, ok: fn(f32) -> bool, rule: &str| {
                let Some(values) = values else {
                    return Ok(());
                };
                if values.len() != px {
                    return Err(len_err(&format!("{what}s"), values.len()));
                }
                match values.iter().position(|&x| !ok(x)) {
                    Some(bad) => Err(GpuError::Usage(format!(
                        "view {i} ({}): {what} {} at pixel {bad}; {rule}",
                        cam.image.display(),
                        values[bad]
                    ))),
                    None => Ok(()),
                }
            };
            check(
                "alpha",
                img.alpha.as_ref(),
                |x| (0.0..=1.0).contains(&x),
                "alpha must be in [0, 1]",
            )?;
            check(
                "colour weight",
                v.weight.as_ref(),
                |x| x.is_finite() && x >= 0.0,
                "weights must be finite and >= 0",
            )?;
            match &v.depth {
                Some(d) if d.len() != px => return Err(len_err("depth targets", d.len())),
                _ => {}
            }
            blocks.push(px);
        }
        let with_depth: Vec<usize> = (0..views.len())
            .filter(|&i| views[i].depth.is_some())
            .collect();
        blocks.extend(with_depth.iter().map(|&i| views[i].pixels()));
        let pixels: u64 = views.iter().map(|v| v.pixels() as u64).sum();
        // Elements (8 bytes) per binding: the limit, and u32 indices.
        let capacity = (limit / 8).min(u32::MAX as u64) as usize;
        if let Some(b) = blocks.iter().position(|&n| n > capacity) {
            let i = if b < views.len() {
                b
            } else {
                with_depth[b - views.len()]
            };
            return Err(GpuError::Usage(format!(
                "view {i} ({}): its {} train pixels need {} bytes, more than one storage \
                 binding of this device holds ({limit} bytes); downscale it (--factor)",
                views[i].camera.image.display(),
                blocks[b],
                blocks[b] as u64 * 8
            )));
        }
        let (at, used) = pack_blocks(&blocks, capacity);
        if used.len() > STORE_BINDINGS {
            let bytes = blocks.iter().map(|&n| n as u64 * 8).sum::<u64>();
            return Err(GpuError::Usage(format!(
                "the training pixels need {bytes} bytes ({pixels} pixels, 8 bytes each, and 8 \
                 more per pixel of views with depth targets) in {} bindings of at most {limit} \
                 bytes, but the batch kernel takes {STORE_BINDINGS}; train on fewer or smaller \
                 views (--factor)",
                used.len()
            )));
        }
        let mut store: Vec<Vec<[u32; 2]>> = used.iter().map(|&n| Vec::with_capacity(n)).collect();
        let mut places: Vec<Place> = Vec::with_capacity(views.len());
        for (i, v) in views.iter().enumerate() {
            let (b, first) = at[i];
            debug_assert_eq!(store[b as usize].len(), first as usize);
            let img = &v.image;
            let sign = colour_weight(v.kind, 1.0);
            let chunk = &mut store[b as usize];
            for (k, c) in img.rgb.chunks_exact(3).enumerate() {
                let a = img.alpha.as_ref().map_or(1.0, |a| a[k]);
                let w = v.weight.as_ref().map_or(1.0, |w| w[k]);
                chunk.push([pack_rgba8(c, a), (sign * w).to_bits()]);
            }
            places.push([b, first, NO_DEPTH, 0, img.width, img.height, i as u32, 0]);
        }
        for (j, &i) in with_depth.iter().enumerate() {
            let (b, first) = at[views.len() + j];
            let d = views[i].depth.as_ref().expect("views with depth");
            debug_assert_eq!(store[b as usize].len(), first as usize);
            store[b as usize].extend(d.iter().map(|p| [p[0].to_bits(), p[1].to_bits()]));
            places[i][2] = b;
            places[i][3] = first;
        }
        count_u32(pixels, "training pixels")?;
        let cams: Vec<GpuCamera> = views.iter().map(|v| gpu_camera(&v.camera)).collect();
        let store = store
            .iter()
            .enumerate()
            .map(|(b, s)| Buffer::from_slice(ctx, &format!("train pixels {b}"), s))
            .collect::<Result<Vec<_>>>()?;
        Ok(TrainData {
            cameras: Buffer::from_slice(ctx, "train cameras", &cams)?,
            places: Buffer::from_slice(ctx, "train image places", &places)?,
            store,
            cdf: Buffer::from_slice(ctx, "train image sampling", &image_cdf(&probabilities)?)?,
            n_images: views.len() as u32,
            pixels,
        })
    }

    /// Training pixels stored.
    pub fn pixels(&self) -> u64 {
        self.pixels
    }

    /// Training views.
    pub fn views(&self) -> usize {
        self.n_images as usize
    }

    /// Bindings the pixel store is spread over.
    pub fn bindings(&self) -> usize {
        self.store.len()
    }

    /// Device bytes of the pixel store, cameras and sampling table.
    pub fn device_bytes(&self) -> u64 {
        self.store.iter().map(Buffer::size_bytes).sum::<u64>()
            + self.cameras.size_bytes()
            + self.places.size_bytes()
            + self.cdf.size_bytes()
    }

    /// The store's binding `b`, or its first binding for the kernel's unused slots.
    pub(crate) fn store_binding(&self, b: usize) -> extranerf_gpu::Binding<'_> {
        self.store.get(b).unwrap_or(&self.store[0]).binding()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn blocks_pack_first_fit_within_capacity() {
        let (at, used) = pack_blocks(&[6, 6, 3, 4, 1], 10);
        assert_eq!(at, vec![(0, 0), (1, 0), (0, 6), (1, 6), (0, 9)]);
        assert_eq!(used, vec![10, 10]);
        let (at, used) = pack_blocks(&[10, 10], 10);
        assert_eq!(at, vec![(0, 0), (1, 0)]);
        assert_eq!(used, vec![10, 10]);
    }

    #[test]
    fn rgba8_packs_as_wgsl_pack4x8unorm() {
        assert_eq!(pack_rgba8(&[0.0, 1.0, 0.5], 1.0), 0xff80ff00);
        // Clamped; 1/255 steps round to nearest.
        assert_eq!(
            pack_rgba8(&[-1.0, 2.0, 3.0 / 255.0 + 0.001], 0.0),
            0x0003ff00
        );
        for k in 0..=255u32 {
            let v = k as f32 / 255.0;
            assert_eq!(pack_rgba8(&[v, v, v], v), k | k << 8 | k << 16 | k << 24);
        }
    }
}
