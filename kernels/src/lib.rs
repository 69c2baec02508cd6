//! The engine's GPU kernels: WGSL sources under `wgsl/`, compiled to SPIR-V 1.3 by naga when this
//! crate builds (a naga error fails the build with the source span), and the host twins generated
//! from them: per file a `Params` struct mirroring the `var<immediate>` block (size and every
//! offset asserted at compile time), per entry point a [`KernelDesc`] and a `Bindings<B>` struct
//! with one field per storage binding, so kernels are bound by name.
//!
//! This crate has no Vulkan dependency and no `unsafe`.
#![forbid(unsafe_code)]

/// One storage-buffer binding of a kernel (descriptor set 0).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct BindingDesc {
    /// `@binding(N)` in the WGSL.
    pub binding: u32,
    /// Name of the WGSL global.
    pub name: &'static str,
    /// True when the kernel never stores to it.
    pub read_only: bool,
    /// Bytes of the `var<uniform>` block when the binding is a uniform buffer (which the
    /// bound range must cover); 0 for storage buffers.
    pub uniform_bytes: u32,
}

/// A compiled compute entry point and what the engine needs to build its pipeline.
#[derive(Clone, Copy, Debug)]
pub struct KernelDesc {
    /// `file::entry`, used to name the Vulkan objects.
    pub name: &'static str,
    /// Entry point name inside the SPIR-V.
    pub entry: &'static str,
    /// SPIR-V 1.3 words.
    pub spirv: &'static [u32],
    /// `@workgroup_size` of the entry point.
    pub workgroup_size: [u32; 3],
    /// Bytes of the push-constant (`var<immediate>`) block; 0 when there is none.
    pub params_size: u32,
    /// Storage buffers the entry point uses, sorted by binding index.
    pub bindings: &'static [BindingDesc],
    /// Uses subgroup operations (needs compute-stage subgroup arithmetic/ballot support).
    pub needs_subgroups: bool,
    /// Uses `atomicAdd` on `f32` in storage buffers (`shaderBufferFloat32AtomicAdd`).
    pub needs_float32_atomic_add: bool,
    /// Uses f16 arithmetic and f16 storage buffers (needs shaderFloat16 and
    /// storageBuffer16BitAccess).
    pub needs_f16: bool,
    /// Edge of the cooperative-matrix tiles it multiplies (f16 A and B, f32 accumulator;
    /// `VK_KHR_cooperative_matrix`), 0 when it uses none.
    pub coop_tile: u32,
}

/// The generated host twin of one file's `Params` block, for the layout tests.
#[derive(Clone, Copy, Debug)]
pub struct ParamsLayout {
    /// `folder::file`.
    pub file: &'static str,
    /// Size naga computed for the WGSL struct.
    pub naga_size: u32,
    /// `size_of` the Rust twin.
    pub rust_size: usize,
    /// (member, naga offset, Rust `offset_of`).
    pub members: &'static [(&'static str, u32, usize)],
}

include!(concat!(env!("OUT_DIR"), "/kernels.rs"));
