// The fused march through 8 x 8 x 8 cooperative matrices: common/march_coop.wgsl.
//!include common/coop8.wgsl
//!include common/march_coop.wgsl
