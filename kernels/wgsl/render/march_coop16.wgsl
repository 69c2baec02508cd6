// The fused march through 16 x 16 x 16 cooperative matrices: common/march_coop.wgsl.
//!include common/coop16.wgsl
//!include common/march_coop.wgsl
