//! The radiance field's GPU parts.

pub mod activation;
pub mod encodings;
pub mod hash_grid;
pub mod mlp;
pub mod proposal;
