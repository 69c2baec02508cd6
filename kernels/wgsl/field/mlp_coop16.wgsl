// The MLP weight gradient through 16 x 16 x 16 cooperative matrices (NVIDIA's f16 shape):
// common/mlp_coop.wgsl.
enable f16;
enable wgpu_cooperative_matrix;

const TILE: u32 = 16u;
alias CoopA = coop_mat16x16<f16, A>;
alias CoopB = coop_mat16x16<f16, B>;
alias CoopC = coop_mat16x16<f32, C>;
//!include common/mlp_coop.wgsl
