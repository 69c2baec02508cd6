// 16 x 16 x 16 cooperative matrices, f16 inputs with f32 accumulators (NVIDIA's f16 shape): the
// declarations common/coop_tiles.wgsl asks of the including file. Include it first: a WGSL
// module starts with its enable directives.
enable f16;
enable wgpu_cooperative_matrix;

const TILE: u32 = 16u;
alias CoopA = coop_mat16x16<f16, A>;
alias CoopB = coop_mat16x16<f16, B>;
alias CoopC = coop_mat16x16<f32, C>;
