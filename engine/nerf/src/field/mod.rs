//! The radiance field's GPU parts.

pub mod hash_grid;
pub mod mlp;
