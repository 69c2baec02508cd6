//! What goes wrong computing a metric, and the checks of the images every metric makes.

use std::path::PathBuf;

/// What went wrong computing a metric or loading its weights.
#[derive(Debug, thiserror::Error)]
pub enum MetricsError {
    /// The two images have different numbers of values.
    #[error("the images differ in size: {a} vs {b} values")]
    LengthMismatch {
        /// Values in the first image.
        a: usize,
        /// Values in the second image.
        b: usize,
    },
    /// An image has no values.
    #[error("the images are empty")]
    Empty,
    /// A pixel mask does not have one entry per RGB pixel.
    #[error("a mask of {mask} pixels does not fit an RGB image of {len} values")]
    MaskMismatch {
        /// Values in the image.
        len: usize,
        /// Entries in the mask.
        mask: usize,
    },
    /// The values do not make an RGB image of the stated size.
    #[error("{len} values do not make a {width}x{height} RGB image ({} expected)", 3 * *width as u64 * *height as u64)]
    SizeMismatch {
        /// Values given.
        len: usize,
        /// Stated width.
        width: u32,
        /// Stated height.
        height: u32,
    },
    /// The image is smaller than the metric's window or network needs.
    #[error("a {width}x{height} image is too small for {metric}: at least {min}x{min} is needed")]
    TooSmall {
        /// Width.
        width: u32,
        /// Height.
        height: u32,
        /// Smallest width and height accepted.
        min: u32,
        /// The metric.
        metric: &'static str,
    },
    /// A weights file is missing or unreadable.
    #[error("{path}: {error}")]
    Io {
        /// The file.
        path: PathBuf,
        /// The OS error (in the message, not a separate source, so a chain does not print it
        /// twice).
        error: std::io::Error,
    },
    /// A set of feature vectors cannot be used (rows, values, or too few for the subsets).
    #[error("KID features ({set}): {problem}")]
    Features {
        /// Which set: real, fake or both.
        set: &'static str,
        /// What is wrong.
        problem: String,
    },
    /// A weights file is malformed or lacks what the network needs.
    #[error("{path}: {problem}")]
    Weights {
        /// The file.
        path: PathBuf,
        /// What is wrong.
        problem: String,
    },
}

/// Result alias of the metrics module.
pub type Result<T, E = MetricsError> = std::result::Result<T, E>;

pub(crate) fn check_pair(a: &[f32], b: &[f32]) -> Result<()> {
    if a.len() != b.len() {
        return Err(MetricsError::LengthMismatch {
            a: a.len(),
            b: b.len(),
        });
    }
    if a.is_empty() {
        return Err(MetricsError::Empty);
    }
    Ok(())
}

/// Checks a pair of `width` x `height` RGB images of at least `min` x `min` pixels.
pub(crate) fn check_images(
    a: &[f32],
    b: &[f32],
    width: u32,
    height: u32,
    min: u32,
    metric: &'static str,
) -> Result<()> {
    check_pair(a, b)?;
    if a.len() as u64 != 3 * width as u64 * height as u64 {
        return Err(MetricsError::SizeMismatch {
            len: a.len(),
            width,
            height,
        });
    }
    if width < min || height < min {
        return Err(MetricsError::TooSmall {
            width,
            height,
            min,
            metric,
        });
    }
    Ok(())
}
