//! The Vulkan layer of extranerf, on raw `ash` and `gpu-allocator`: the only crate of the engine
//! with `unsafe` code. Every `unsafe` block states the invariant it relies on; the public API is
//! safe.
//!
//! - [`Context`]: instance (with the Khronos validation layer and a debug messenger when
//!   available), device selection (discrete > integrated > virtual > CPU, or `--device` /
//!   `EXTRANERF_DEVICE`), one compute queue, gpu-allocator, a timeline semaphore, and a release
//!   queue that frees resources once the GPU has passed their last use.
//! - [`Buffer`]: typed storage buffers with staged upload/readback.
//! - [`Kernel`]: a compute pipeline from the generated SPIR-V of `extranerf-kernels`, bound by
//!   name through push descriptors.
//! - [`Recorder`]: dispatches (thread counts, folded to 2-D past 65535 workgroups), copies,
//!   automatic hazard barriers, timestamps ([`GpuTimer`]).
//! - [`GpuError`]: one error enum with actionable messages.

mod buffer;
mod context;
mod error;
pub mod files;
mod kernel;
mod recorder;
#[cfg(feature = "wgpu")]
mod shared_buffer;
#[cfg(feature = "wgpu")]
mod wgpu_share;

pub use buffer::{Binding, Buffer, BUFFER_ALIGN};
pub use context::{
    list_devices, Context, ContextDesc, CoopMatrixShape, DeviceInfo, DeviceListing, HeapInfo,
    Ticket, Validation, ValidationLogHandle, ValidationMessage,
};
pub use error::{count_u32, GpuError, Result};
pub use extranerf_kernels as kernels;
pub use kernel::Kernel;
pub use recorder::{fold_groups, GpuTimer, Recorder};
#[cfg(feature = "wgpu")]
pub use shared_buffer::SharedBuffer;
#[cfg(feature = "wgpu")]
pub use wgpu_share::WgpuHandles;
#[cfg(feature = "wgpu")]
pub use {wgpu, wgpu_hal, wgpu_types};
