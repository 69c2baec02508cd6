// The tiny MLPs through 8 x 8 x 8 cooperative matrices: common/mlp_coop.wgsl.
//!include common/coop8.wgsl
//!include common/mlp_coop.wgsl
