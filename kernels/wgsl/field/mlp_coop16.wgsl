// The tiny MLPs through 16 x 16 x 16 cooperative matrices: common/mlp_coop.wgsl.
//!include common/coop16.wgsl
//!include common/mlp_coop.wgsl
