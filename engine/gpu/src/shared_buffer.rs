//! A wgpu buffer's range bound by the engine's kernels (the device shared with burn).

use ash::vk;

use crate::buffer::Binding;
use crate::context::Context;
use crate::error::{GpuError, Result};

/// A range of a wgpu buffer on a shared device ([`crate::ContextDesc::share_with_wgpu`]),
/// bindable by the engine's kernels: burn's tensors are read and written in place, with no copy
/// through the host. The wgpu buffer is kept alive while this lives; its owner (burn) must not
/// reuse the range meanwhile, and the two sides must not run at the same time (let burn sync
/// before the engine records, and the engine's run finish before burn continues).
#[derive(Debug)]
pub struct SharedBuffer {
    raw: vk::Buffer,
    offset: u64,
    bytes: u64,
    last_use: std::sync::atomic::AtomicU64,
    name: String,
    ctx: usize,
    _buffer: wgpu::Buffer,
}

impl SharedBuffer {
    /// Bytes `offset .. offset + bytes` of `buffer`, which must live on `ctx`'s shared device.
    /// The offset must be a multiple of the device's `minStorageBufferOffsetAlignment`.
    pub fn new(
        ctx: &Context,
        buffer: &wgpu::Buffer,
        offset: u64,
        bytes: u64,
        name: &str,
    ) -> Result<SharedBuffer> {
        let Some(handles) = ctx.wgpu() else {
            return Err(GpuError::Usage(format!(
                "`{name}`: the context was not created to share its device with wgpu"
            )));
        };
        let align = ctx.info().min_storage_buffer_offset_alignment.max(1);
        if !offset.is_multiple_of(align) || offset.saturating_add(bytes) > buffer.size() {
            return Err(GpuError::Usage(format!(
                "`{name}`: range {offset}..+{bytes} of a {}-byte wgpu buffer (offsets on multiples of {align})",
                buffer.size()
            )));
        }
        // SAFETY: the raw handle is only read; the buffer stays alive (held below), and
        // belongs to the shared device (checked against the device below).
        let raw = unsafe {
            buffer
                .as_hal::<wgpu_hal::api::Vulkan>()
                .map(|b| b.raw_handle())
        };
        let same_device = handles.raw_device() == Some(ctx.raw_device());
        match raw {
            Some(raw) if same_device => Ok(SharedBuffer {
                raw,
                offset,
                bytes,
                last_use: std::sync::atomic::AtomicU64::new(0),
                name: name.into(),
                ctx: ctx.id(),
                _buffer: buffer.clone(),
            }),
            _ => Err(GpuError::Usage(format!(
                "`{name}`: not a Vulkan buffer of this context's shared device"
            ))),
        }
    }

    /// The range as a kernel binding.
    pub fn binding(&self) -> Binding<'_> {
        Binding {
            raw: self.raw,
            offset: self.offset,
            bytes: self.bytes,
            last_use: &self.last_use,
            name: &self.name,
            ctx: self.ctx,
        }
    }
}
