// The fused training step through 16 x 16 x 16 cooperative matrices: common/step_coop.wgsl.
//!include common/coop16.wgsl
//!include common/step_coop.wgsl
