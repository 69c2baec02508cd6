//! Typed device buffers with staged upload and readback.

use std::marker::PhantomData;
use std::sync::atomic::{AtomicU64, Ordering};

use ash::vk;
use bytemuck::Pod;
use gpu_allocator::vulkan::{Allocation, AllocationCreateDesc, AllocationScheme};
use gpu_allocator::MemoryLocation;

use crate::context::{Context, Garbage};
use crate::error::{GpuError, Result};

/// Storage buffers are padded to this many bytes so kernels can read them as `vec4` arrays.
pub const BUFFER_ALIGN: u64 = 16;

/// A `VkBuffer` with its memory; freed through the release queue after its last GPU use.
pub(crate) struct RawBuffer {
    ctx: Context,
    pub(crate) raw: vk::Buffer,
    allocation: Option<Allocation>,
    /// Allocated (padded) size in bytes.
    pub(crate) bytes: u64,
    pub(crate) name: String,
    /// Timeline value of the last submission that used it.
    pub(crate) last_use: AtomicU64,
}

impl RawBuffer {
    pub(crate) fn new(
        ctx: &Context,
        name: &str,
        bytes: u64,
        location: MemoryLocation,
    ) -> Result<RawBuffer> {
        let info = ctx.info();
        let padded = bytes.max(1).div_ceil(BUFFER_ALIGN) * BUFFER_ALIGN;
        let storage = location == MemoryLocation::GpuOnly;
        if storage && padded > info.max_buffer_bytes {
            return Err(GpuError::BufferTooLarge {
                name: name.into(),
                bytes: padded,
                limit: info.max_buffer_bytes,
            });
        }
        let usage = if storage {
            vk::BufferUsageFlags::STORAGE_BUFFER
                | vk::BufferUsageFlags::UNIFORM_BUFFER
                | vk::BufferUsageFlags::TRANSFER_SRC
                | vk::BufferUsageFlags::TRANSFER_DST
        } else {
            vk::BufferUsageFlags::TRANSFER_SRC | vk::BufferUsageFlags::TRANSFER_DST
        };
        let device = &ctx.inner.device;
        let ci = vk::BufferCreateInfo::default()
            .size(padded)
            .usage(usage)
            .sharing_mode(vk::SharingMode::EXCLUSIVE);
        // SAFETY: valid device and create info; the buffer is destroyed on every error path below
        // or owned by the returned RawBuffer.
        let raw = unsafe { device.create_buffer(&ci, None) }.map_err(|r| match r {
            vk::Result::ERROR_OUT_OF_DEVICE_MEMORY | vk::Result::ERROR_OUT_OF_HOST_MEMORY => {
                GpuError::OutOfDeviceMemory {
                    name: name.into(),
                    bytes: padded,
                }
            }
            r => crate::error::vk_err("vkCreateBuffer", r),
        })?;
        // SAFETY: `raw` was just created on this device.
        let requirements = unsafe { device.get_buffer_memory_requirements(raw) };
        let allocation = {
            let mut guard = ctx.allocator()?;
            let alloc = guard
                .as_mut()
                .ok_or_else(|| GpuError::Usage("allocator already shut down".into()))?;
            let used = ctx
                .inner
                .max_memory
                .map(|_| alloc.generate_report().total_allocated_bytes);
            match (ctx.inner.max_memory, used) {
                (Some(limit), Some(used)) if used.saturating_add(requirements.size) > limit => {
                    Err(gpu_allocator::AllocationError::OutOfMemory)
                }
                _ => alloc.allocate(&AllocationCreateDesc {
                    name,
                    requirements,
                    location,
                    linear: true,
                    allocation_scheme: AllocationScheme::GpuAllocatorManaged,
                }),
            }
        };
        let allocation = match allocation {
            Ok(a) => a,
            Err(e) => {
                // SAFETY: not bound, not used by the GPU.
                unsafe { device.destroy_buffer(raw, None) };
                return Err(match e {
                    gpu_allocator::AllocationError::OutOfMemory => GpuError::OutOfDeviceMemory {
                        name: name.into(),
                        bytes: padded,
                    },
                    e => GpuError::Allocation {
                        name: name.into(),
                        message: e.to_string(),
                    },
                });
            }
        };
        // SAFETY: the allocation satisfies the buffer's requirements and is bound exactly once.
        if let Err(r) =
            unsafe { device.bind_buffer_memory(raw, allocation.memory(), allocation.offset()) }
        {
            ctx.release(0, Garbage::Buffer(raw, allocation));
            return Err(crate::error::vk_err("vkBindBufferMemory", r));
        }
        ctx.name(raw, name);
        Ok(RawBuffer {
            ctx: ctx.clone(),
            raw,
            allocation: Some(allocation),
            bytes: padded,
            name: name.into(),
            last_use: AtomicU64::new(0),
        })
    }

    pub(crate) fn mapped(&self) -> Result<&[u8]> {
        self.allocation
            .as_ref()
            .and_then(|a| a.mapped_slice())
            .ok_or_else(|| GpuError::Usage(format!("buffer `{}` is not host-visible", self.name)))
    }

    pub(crate) fn mapped_mut(&mut self) -> Result<&mut [u8]> {
        let name = self.name.clone();
        self.allocation
            .as_mut()
            .and_then(|a| a.mapped_slice_mut())
            .ok_or_else(|| GpuError::Usage(format!("buffer `{name}` is not host-visible")))
    }
}

impl Drop for RawBuffer {
    fn drop(&mut self) {
        if let Some(a) = self.allocation.take() {
            self.ctx.release(
                self.last_use.load(Ordering::Acquire),
                Garbage::Buffer(self.raw, a),
            );
        }
    }
}

/// A device-local storage buffer of `len` elements of `T`.
pub struct Buffer<T: Pod> {
    pub(crate) raw: RawBuffer,
    len: usize,
    _t: PhantomData<T>,
}

impl<T: Pod> std::fmt::Debug for Buffer<T> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Buffer")
            .field("name", &self.raw.name)
            .field("len", &self.len)
            .finish()
    }
}

/// One buffer bound to a kernel or used by a copy: what the recorder needs, borrowed.
#[derive(Clone, Copy, Debug)]
pub struct Binding<'a> {
    pub(crate) raw: vk::Buffer,
    /// Byte offset of the bound range in the buffer.
    pub(crate) offset: u64,
    /// Bytes in the bound range.
    pub(crate) bytes: u64,
    pub(crate) last_use: &'a AtomicU64,
    pub(crate) name: &'a str,
    /// The context the buffer belongs to.
    pub(crate) ctx: usize,
}

impl<'a> Binding<'a> {
    /// Bytes bound (the buffer's padded size, or a slice's range).
    pub fn bytes(&self) -> u64 {
        self.bytes
    }

    /// The buffer's name.
    pub fn name(&self) -> &str {
        self.name
    }

    /// Bytes `offset .. offset + bytes` of this binding as a binding of their own (rounded up
    /// to 16 bytes). The offset must be a multiple of 256 bytes, the largest
    /// `minStorageBufferOffsetAlignment` Vulkan allows, and the range must stay inside.
    pub fn sub(&self, offset: u64, bytes: u64) -> Result<Binding<'a>> {
        let bytes = bytes.max(1).div_ceil(16) * 16;
        if !offset.is_multiple_of(256) || offset.saturating_add(bytes) > self.bytes {
            return Err(GpuError::Usage(format!(
                "range {offset}..+{bytes} of `{}` ({} bytes bound): the offset must be a multiple of 256 and the range inside",
                self.name, self.bytes
            )));
        }
        Ok(Binding {
            offset: self.offset + offset,
            bytes,
            ..*self
        })
    }

    /// Fails unless `count` elements of `elem_bytes` fit in the binding.
    pub fn check_fits(&self, count: u64, elem_bytes: u64, what: &str) -> Result<()> {
        if count.saturating_mul(elem_bytes) > self.bytes {
            return Err(GpuError::Usage(format!(
                "{what}: `{}` holds {} bytes, {count} elements of {elem_bytes} bytes do not fit",
                self.name, self.bytes
            )));
        }
        Ok(())
    }
}

impl<T: Pod> Buffer<T> {
    /// A new buffer of `len` elements with unspecified contents.
    pub fn new(ctx: &Context, name: &str, len: usize) -> Result<Buffer<T>> {
        let bytes = (len as u64)
            .checked_mul(std::mem::size_of::<T>() as u64)
            .ok_or_else(|| GpuError::Usage(format!("buffer `{name}`: {len} elements overflow")))?;
        Ok(Buffer {
            raw: RawBuffer::new(ctx, name, bytes, MemoryLocation::GpuOnly)?,
            len,
            _t: PhantomData,
        })
    }

    /// A new buffer holding `data`.
    pub fn from_slice(ctx: &Context, name: &str, data: &[T]) -> Result<Buffer<T>> {
        let b = Buffer::new(ctx, name, data.len())?;
        b.write(data)?;
        Ok(b)
    }

    /// Number of elements.
    pub fn len(&self) -> usize {
        self.len
    }

    /// True when it holds no elements.
    pub fn is_empty(&self) -> bool {
        self.len == 0
    }

    /// Bytes of the elements (without padding).
    pub fn size_bytes(&self) -> u64 {
        (self.len * std::mem::size_of::<T>()) as u64
    }

    /// The name it was created with.
    pub fn name(&self) -> &str {
        &self.raw.name
    }

    /// This buffer as a kernel binding or copy operand.
    pub fn binding(&self) -> Binding<'_> {
        Binding {
            raw: self.raw.raw,
            offset: 0,
            bytes: self.raw.bytes,
            last_use: &self.raw.last_use,
            name: &self.raw.name,
            ctx: self.raw.ctx.id(),
        }
    }

    /// Elements `start .. start + len` as a binding of their own (one flat parameter buffer
    /// bound section by section). The start must sit on the device's
    /// `minStorageBufferOffsetAlignment`; the range is rounded up to 16 bytes so kernels may read
    /// it as vec4s, and must stay inside the buffer.
    pub fn slice(&self, start: usize, len: usize) -> Result<Binding<'_>> {
        let size = std::mem::size_of::<T>() as u64;
        let offset = start as u64 * size;
        let bytes = (len as u64 * size).max(1).div_ceil(16) * 16;
        let align = self
            .raw
            .ctx
            .info()
            .min_storage_buffer_offset_alignment
            .max(1);
        if !offset.is_multiple_of(align) {
            return Err(GpuError::Usage(format!(
                "slice of `{}` at element {start}: byte offset {offset} is not a multiple of the device's storage offset alignment {align}",
                self.raw.name
            )));
        }
        if offset.saturating_add(bytes) > self.raw.bytes {
            return Err(GpuError::Usage(format!(
                "slice of `{}` at element {start} with {len} elements overruns its {} bytes",
                self.raw.name, self.raw.bytes
            )));
        }
        Ok(Binding {
            raw: self.raw.raw,
            offset,
            bytes,
            last_use: &self.raw.last_use,
            name: &self.raw.name,
            ctx: self.raw.ctx.id(),
        })
    }

    /// Uploads `data` (exactly `len` elements) through a staging buffer and waits.
    pub fn write(&self, data: &[T]) -> Result<()> {
        self.write_at(0, data)
    }

    /// Uploads `data` to elements `offset..offset + data.len()` and waits.
    pub fn write_at(&self, offset: usize, data: &[T]) -> Result<()> {
        if offset
            .checked_add(data.len())
            .is_none_or(|end| end > self.len)
        {
            return Err(GpuError::Usage(format!(
                "write of {} elements at {offset} into `{}` of {} elements",
                data.len(),
                self.raw.name,
                self.len
            )));
        }
        if data.is_empty() {
            return Ok(());
        }
        let ctx = self.raw.ctx.clone();
        let bytes: &[u8] = bytemuck::cast_slice(data);
        let mut staging = RawBuffer::new(
            &ctx,
            &format!("{} (upload staging)", self.raw.name),
            bytes.len() as u64,
            MemoryLocation::CpuToGpu,
        )?;
        staging.mapped_mut()?[..bytes.len()].copy_from_slice(bytes);
        let mut rec = ctx.recorder("upload")?;
        let dst_off = (offset * std::mem::size_of::<T>()) as u64;
        rec.copy_raw(&staging, 0, self.binding(), dst_off, bytes.len() as u64);
        let t = ctx.submit(rec)?;
        staging.last_use.fetch_max(t.0, Ordering::AcqRel);
        ctx.wait(t)
    }

    /// Downloads all elements through a staging buffer (waits for the GPU).
    pub fn read(&self) -> Result<Vec<T>> {
        self.read_range(0, self.len)
    }

    /// Downloads elements `offset..offset + count`.
    pub fn read_range(&self, offset: usize, count: usize) -> Result<Vec<T>> {
        if offset.checked_add(count).is_none_or(|end| end > self.len) {
            return Err(GpuError::Usage(format!(
                "read of {count} elements at {offset} from `{}` of {} elements",
                self.raw.name, self.len
            )));
        }
        if count == 0 {
            return Ok(Vec::new());
        }
        let ctx = self.raw.ctx.clone();
        let size = (count * std::mem::size_of::<T>()) as u64;
        let staging = RawBuffer::new(
            &ctx,
            &format!("{} (readback staging)", self.raw.name),
            size,
            MemoryLocation::GpuToCpu,
        )?;
        let mut rec = ctx.recorder("readback")?;
        let src = self.binding();
        rec.copy_to_host(
            src,
            (offset * std::mem::size_of::<T>()) as u64,
            &staging,
            size,
        );
        let t = ctx.submit(rec)?;
        staging.last_use.fetch_max(t.0, Ordering::AcqRel);
        ctx.wait(t)?;
        let bytes = &staging.mapped()?[..size as usize];
        let mut out = vec![T::zeroed(); count];
        bytemuck::cast_slice_mut::<T, u8>(&mut out).copy_from_slice(bytes);
        Ok(out)
    }
}
