//! Training views: captured photos and virtual views with their per-pixel colour weights and
//! depth targets, how a batch's rays are spread over them, and their packed copy on the device.

use serde::{Deserialize, Serialize};

use extranerf_gpu::{count_u32, Buffer, Context, GpuError, Result};

use crate::data::{Camera, Image};
use crate::render::rays::{gpu_camera, GpuCamera};

/// Where a training view comes from, which decides its colour loss.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub enum ViewKind {
    /// A photograph: the configured colour loss (L2 or Huber), scaled by the pixel's weight.
    Captured,
    /// A virtual view (an inpainted render): L1 on colour scaled by the pixel's weight, as
    /// ExtraNeRF supervises with its w(t)-weighted L1.
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
    /// Per ray: the target colour and its signed colour weight ([`colour_weight`]).
    pub targets: Vec<[f32; 4]>,
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

/// The training views on the device: cameras, packed pixels (with their signed colour
/// weights), depth targets and the images' sampling table.
#[derive(Debug)]
pub struct TrainData {
    pub(crate) cameras: Buffer<GpuCamera>,
    pub(crate) info: Buffer<[u32; 4]>,
    pub(crate) rgb: Buffer<[f32; 4]>,
    pub(crate) depth: Buffer<[f32; 2]>,
    pub(crate) cdf: Buffer<u32>,
    pub(crate) n_images: u32,
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
        if views.is_empty() {
            return Err(GpuError::Usage("no training views".into()));
        }
        let probabilities = sampling.probabilities(views)?;
        let mut info = Vec::new();
        let mut rgb = Vec::new();
        let mut depth = Vec::new();
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
            info.push([rgb.len() as u32, img.width, img.height, i as u32]);
            match &v.weight {
                None => {
                    let w = colour_weight(v.kind, 1.0);
                    rgb.extend(img.rgb.chunks_exact(3).map(|c| [c[0], c[1], c[2], w]));
                }
                Some(w) if w.len() == px => {
                    if let Some(bad) = w.iter().position(|x| !(x.is_finite() && *x >= 0.0)) {
                        return Err(GpuError::Usage(format!(
                            "view {i} ({}): colour weight {} at pixel {bad}; weights must be finite and >= 0",
                            cam.image.display(),
                            w[bad]
                        )));
                    }
                    rgb.extend(
                        img.rgb
                            .chunks_exact(3)
                            .zip(w)
                            .map(|(c, &w)| [c[0], c[1], c[2], colour_weight(v.kind, w)]),
                    );
                }
                Some(w) => {
                    return Err(GpuError::Usage(format!(
                        "view {i} ({}): {} colour weights for {px} pixels",
                        cam.image.display(),
                        w.len()
                    )))
                }
            }
            match &v.depth {
                Some(d) if d.len() == px => depth.extend_from_slice(d),
                Some(d) => {
                    return Err(GpuError::Usage(format!(
                        "view {i}: {} depth targets for {px} pixels",
                        d.len()
                    )))
                }
                None => depth.extend(std::iter::repeat_n([0.0, 0.0], px)),
            }
        }
        count_u32(rgb.len() as u64, "training pixels")?;
        let cams: Vec<GpuCamera> = views.iter().map(|v| gpu_camera(&v.camera)).collect();
        Ok(TrainData {
            cameras: Buffer::from_slice(ctx, "train cameras", &cams)?,
            info: Buffer::from_slice(ctx, "train image info", &info)?,
            rgb: Buffer::from_slice(ctx, "train pixels", &rgb)?,
            depth: Buffer::from_slice(ctx, "train depth targets", &depth)?,
            cdf: Buffer::from_slice(ctx, "train image sampling", &image_cdf(&probabilities)?)?,
            n_images: views.len() as u32,
        })
    }
}
