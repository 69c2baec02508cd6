// The MLP weight gradient through 8 x 8 x 8 cooperative matrices (lavapipe's shape):
// common/mlp_coop.wgsl.
enable f16;
enable wgpu_cooperative_matrix;

const TILE: u32 = 8u;
alias CoopA = coop_mat8x8<f16, A>;
alias CoopB = coop_mat8x8<f16, B>;
alias CoopC = coop_mat8x8<f32, C>;
//!include common/mlp_coop.wgsl
