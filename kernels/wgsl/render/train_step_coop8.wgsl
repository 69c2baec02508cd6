// The fused training step through 8 x 8 x 8 cooperative matrices: common/step_coop.wgsl.
//!include common/coop8.wgsl
//!include common/step_coop.wgsl
