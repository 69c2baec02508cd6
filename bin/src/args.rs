//! Flags that several commands share: the scene split, the march, the depth request.

use std::path::{Path, PathBuf};

use anyhow::bail;
use extranerf_nerf::data::split::SplitKind;
use extranerf_nerf::field::mlp::MlpMode;
use extranerf_nerf::render::march::MarchCuts;
use extranerf_nerf::render::occupancy::OccupancyConfig;
use extranerf_nerf::renderer::March;
use extranerf_nerf::run::{DepthRequest, SceneSpec};

/// `--depth` (or its alias `--depth-dir DIR`); `auto` when neither is given.
pub fn depth_request(depth: &Option<DepthRequest>, depth_dir: &Option<PathBuf>) -> DepthRequest {
    match (depth, depth_dir) {
        (Some(r), _) => r.clone(),
        (None, Some(d)) => DepthRequest::Dir(d.clone()),
        (None, None) => DepthRequest::Auto,
    }
}

/// How `render` and `eval` evaluate the field (`Default` equals the command-line defaults).
#[derive(clap::Args, Debug, Clone)]
pub struct MarchArgs {
    /// fused: one kernel per chunk of rays (samples, hash grid, both MLPs and compositing in
    /// registers, with optional occupancy skipping and early termination). standalone: the
    /// training kernels, which store every sample between stages (no cuts; about as fast on
    /// lavapipe, results/bench_render_lavapipe).
    #[arg(long, value_enum, default_value_t = KernelPath::Fused)]
    pub march: KernelPath,
    /// Occupancy grid cells per axis, built from the field before rendering, so empty space is
    /// skipped (fused only; 0: no grid). Points outside the grid are always evaluated. Off by
    /// default: a BaseNeRF trained on fern fills 99.9% of a 64^3 grid above the threshold (a
    /// density of 0.01; `train --occupancy-res` thresholds by opacity, and fern still fills
    /// 96-97% of its grid), so the grid costs its build (5 s) and saves nothing there
    /// (results/bench_render_lavapipe).
    #[arg(long, default_value_t = MarchArgs::default().occupancy_res)]
    pub occupancy_res: u32,
    /// Jittered density evaluations per occupancy cell; the largest counts.
    #[arg(long, default_value_t = MarchArgs::default().occupancy_passes)]
    pub occupancy_passes: u32,
    /// Density above which a cell counts as occupied (lowered to the mean density when that is
    /// lower, as in Instant-NGP).
    #[arg(long, default_value_t = MarchArgs::default().occupancy_threshold)]
    pub occupancy_threshold: f32,
    /// Skip the colour MLP for samples whose weight is at most this (fused only; 0: exact).
    /// Off by default: on lavapipe a SIMD group holds 8 rays, so one ray's cut saves nothing
    /// unless all 8 take it (measured no faster on fern, results/bench_render_lavapipe).
    #[arg(long, default_value_t = MarchArgs::default().min_weight)]
    pub min_weight: f32,
    /// Stop a ray once its transmittance falls below this (fused only; 0: exact; Instant-NGP
    /// uses 1e-4). Off by default for the same reason as --min-weight.
    #[arg(long, default_value_t = MarchArgs::default().min_transmittance)]
    pub min_transmittance: f32,
    /// MLP arithmetic: coop (cooperative matrices: f16 tiles with f32 accumulation; an error
    /// where the device lacks them), scalar (per-thread f32), or auto (coop on a GPU that
    /// offers a usable tile shape; scalar on CPU devices, where lavapipe's emulated tiles
    /// measured slower).
    #[arg(long, value_name = "KIND", value_enum, default_value_t = MarchArgs::default().mlp)]
    pub mlp: MlpMode,
}

impl Default for MarchArgs {
    fn default() -> Self {
        MarchArgs {
            march: KernelPath::Fused,
            occupancy_res: 0,
            occupancy_passes: 4,
            occupancy_threshold: 0.01,
            min_weight: 0.0,
            min_transmittance: 0.0,
            mlp: MlpMode::Auto,
        }
    }
}

impl MarchArgs {
    /// The evaluation path.
    pub fn march(&self) -> anyhow::Result<March> {
        Ok(match self.march {
            KernelPath::Standalone => March::Standalone,
            KernelPath::Fused => {
                for (flag, v) in [
                    ("--min-weight", self.min_weight),
                    ("--min-transmittance", self.min_transmittance),
                ] {
                    if !(0.0..1.0).contains(&v) {
                        bail!("{flag} {v}: use a value in [0, 1)");
                    }
                }
                March::Fused(MarchCuts {
                    min_weight: self.min_weight,
                    min_transmittance: self.min_transmittance,
                })
            }
        })
    }

    /// The occupancy grid for a model, if one is wanted: one cascade covers NDC's cube; world
    /// scenes get cascades out to the far bound (`autoconfig::occupancy_cascades`).
    pub fn occupancy(
        &self,
        model: &extranerf_nerf::model::ModelConfig,
    ) -> anyhow::Result<Option<OccupancyConfig>> {
        if self.march == KernelPath::Standalone || self.occupancy_res == 0 {
            return Ok(None);
        }
        if !(1..=512).contains(&self.occupancy_res) || self.occupancy_passes == 0 {
            bail!(
                "--occupancy-res {} / --occupancy-passes {}: use 0-512 cells per axis and at least one pass",
                self.occupancy_res,
                self.occupancy_passes
            );
        }
        if !(self.occupancy_threshold >= 0.0 && self.occupancy_threshold.is_finite()) {
            bail!(
                "--occupancy-threshold {}: use a density >= 0",
                self.occupancy_threshold
            );
        }
        Ok(Some(OccupancyConfig {
            res: self.occupancy_res,
            cascades: extranerf_nerf::autoconfig::occupancy_cascades(model),
            threshold: self.occupancy_threshold,
            ..OccupancyConfig::default()
        }))
    }

    /// The settings as JSON, for metrics files.
    pub fn json(&self) -> serde_json::Value {
        serde_json::json!({
            "march": self.march.name(),
            "occupancy_res": self.occupancy_res,
            "occupancy_passes": self.occupancy_passes,
            "occupancy_threshold": self.occupancy_threshold,
            "min_weight": self.min_weight,
            "min_transmittance": self.min_transmittance,
            "mlp": self.mlp.name(),
        })
    }
}

/// Which views of a scene train and which are held out, and the image size.
#[derive(clap::Args, Debug, Clone)]
pub struct SplitArgs {
    /// How the scene's views divide into training and held-out views: holdout (every 8th view
    /// held out for evaluation, all the others train: a capture's own split), all (every view
    /// trains, none is held out), the benchmarks extrapolation (ExtraNeRF: 6 central views
    /// train, the 8 farthest are held out) and fewshot (RegNeRF: every 8th held out,
    /// --fewshot-views spread over the rest), or given (the data set's split files:
    /// NeRF-synthetic's transforms_train.json trains, transforms_test.json is held out)
    /// [default: given when the scene has transforms_train.json, else holdout].
    #[arg(long, value_enum)]
    pub split: Option<SplitKind>,
    /// Training views of the few-shot split.
    #[arg(long, default_value_t = 3)]
    pub fewshot_views: usize,
    /// LLFF downsampling factor (reads images_N; sets the intrinsics).
    #[arg(long, default_value_t = 8)]
    pub factor: u32,
}

impl SplitArgs {
    /// The split for the scene in `dir`: the one given, else its default
    /// ([`SplitKind::default_for`]).
    pub fn kind(&self, dir: &Path) -> SplitKind {
        self.split.unwrap_or_else(|| SplitKind::default_for(dir))
    }

    /// The scene spec of `dir` with these views (depth supervision from the COLMAP sparse
    /// points when `sparse_depth`).
    pub fn spec(&self, dir: PathBuf, sparse_depth: bool) -> SceneSpec {
        SceneSpec {
            split: self.kind(&dir),
            dir,
            fewshot_views: self.fewshot_views,
            factor: self.factor,
            sparse_depth,
            depth_dir: None,
            mvs_depth: None,
            capture_depth: false,
        }
    }
}

/// `train --step` and `render --march`: one fused kernel, or the standalone chain.
#[derive(clap::ValueEnum, Clone, Copy, Debug, PartialEq, Eq)]
pub enum KernelPath {
    /// One kernel for the whole chain.
    Fused,
    /// One kernel per stage, every sample stored between them.
    Standalone,
}

impl KernelPath {
    /// The name in reports.
    pub fn name(self) -> &'static str {
        match self {
            KernelPath::Fused => "fused",
            KernelPath::Standalone => "standalone",
        }
    }
}
