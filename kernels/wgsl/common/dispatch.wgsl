// Dispatch helpers shared by every kernel. The host (`Recorder::dispatch`) takes a thread count
// and folds more than 65535 workgroups into a 2-D grid; kernels recover the linear workgroup
// index here and must ignore indices past their element count.

fn linear_group(wid: vec3<u32>, nwg: vec3<u32>) -> u32 {
    return wid.y * nwg.x + wid.x;
}
