// 8 x 8 x 8 cooperative matrices, f16 inputs with f32 accumulators (lavapipe's shape): the
// declarations common/coop_tiles.wgsl asks of the including file. Include it first: a WGSL
// module starts with its enable directives.
enable f16;
enable wgpu_cooperative_matrix;

const TILE: u32 = 8u;
alias CoopA = coop_mat8x8<f16, A>;
alias CoopB = coop_mat8x8<f16, B>;
alias CoopC = coop_mat8x8<f32, C>;
