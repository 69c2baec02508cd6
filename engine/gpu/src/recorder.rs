//! Command recording with automatic hazard barriers, submission on the timeline, and timers.

use std::sync::atomic::{AtomicU64, Ordering};

use ash::vk;
use bytemuck::Pod;

use crate::buffer::{Binding, RawBuffer};
use crate::context::{wait_timeout_s, Context, Garbage, Ticket};
use crate::error::{GpuError, Result, VkContext};
use crate::kernel::Kernel;

/// Records dispatches, copies and timestamps into one command buffer.
///
/// Everything a recording uses (buffers, kernels, timers) stays borrowed until the recorder is
/// submitted or dropped, so nothing can be destroyed while it is still referenced; after the
/// submission, drops are deferred by the release queue. This does not compile:
///
/// ```compile_fail,E0597
/// # use extranerf_gpu::{Buffer, Context, Kernel};
/// # fn f(ctx: &Context, desc: &'static extranerf_gpu::kernels::KernelDesc, b: &Buffer<u32>) {
/// let mut rec = ctx.recorder("early drop").unwrap();
/// {
///     let kernel = Kernel::new(ctx, desc).unwrap();
///     rec.dispatch(&kernel, [b.binding()], &0u32, 1).unwrap();
/// } // `kernel` dropped while `rec` still refers to it
/// ctx.run(rec).unwrap();
/// # }
/// ```
///
/// Barriers are inserted automatically: a command that reads or writes a buffer written since
/// the last barrier, or writes one read since then, is preceded by a compute/transfer memory
/// barrier. [`Recorder::barrier`] forces one.
pub struct Recorder<'a> {
    ctx: Context,
    /// Each recorder has its own pool, so recorders on several threads need no locking.
    pool: vk::CommandPool,
    cmd: vk::CommandBuffer,
    label: String,
    uses: Vec<&'a AtomicU64>,
    written: Vec<vk::Buffer>,
    read: Vec<vk::Buffer>,
    submitted: bool,
    /// Number of dispatches recorded.
    pub dispatches: u32,
    /// Number of barriers recorded.
    pub barriers: u32,
}

impl std::fmt::Debug for Recorder<'_> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Recorder")
            .field("label", &self.label)
            .field("dispatches", &self.dispatches)
            .finish_non_exhaustive()
    }
}

const ALL_ACCESS: vk::AccessFlags = vk::AccessFlags::from_raw(
    vk::AccessFlags::SHADER_READ.as_raw()
        | vk::AccessFlags::SHADER_WRITE.as_raw()
        | vk::AccessFlags::TRANSFER_READ.as_raw()
        | vk::AccessFlags::TRANSFER_WRITE.as_raw(),
);
const STAGES: vk::PipelineStageFlags = vk::PipelineStageFlags::from_raw(
    vk::PipelineStageFlags::COMPUTE_SHADER.as_raw() | vk::PipelineStageFlags::TRANSFER.as_raw(),
);

/// Folds a workgroup count above the per-dimension limit into a 2-D grid (x * y >= groups).
pub fn fold_groups(groups: u64, max_x: u32, max_y: u32) -> Result<[u32; 2]> {
    if groups <= max_x as u64 {
        return Ok([groups as u32, 1]);
    }
    let y = groups.div_ceil(max_x as u64);
    if y > max_y as u64 {
        return Err(GpuError::Usage(format!(
            "{groups} workgroups exceed the device's {max_x} x {max_y} grid"
        )));
    }
    let x = groups.div_ceil(y);
    Ok([x as u32, y as u32])
}

impl Context {
    /// Starts recording; `label` names the command buffer.
    pub fn recorder<'a>(&self, label: &str) -> Result<Recorder<'a>> {
        self.collect_garbage()?;
        let device = &self.inner.device;
        let pool_ci = vk::CommandPoolCreateInfo::default()
            .queue_family_index(self.inner.queue_family)
            .flags(vk::CommandPoolCreateFlags::TRANSIENT);
        // SAFETY: valid device; the pool is owned by the Recorder and released through the
        // release queue after its submission completes (or at once if never submitted).
        let pool =
            unsafe { device.create_command_pool(&pool_ci, None) }.during("vkCreateCommandPool")?;
        self.name(pool, label);
        let ai = vk::CommandBufferAllocateInfo::default()
            .command_pool(pool)
            .level(vk::CommandBufferLevel::PRIMARY)
            .command_buffer_count(1);
        let bi = vk::CommandBufferBeginInfo::default()
            .flags(vk::CommandBufferUsageFlags::ONE_TIME_SUBMIT);
        // SAFETY: the pool was just created and is used by this thread only.
        let begun = unsafe {
            device
                .allocate_command_buffers(&ai)
                .and_then(|c| device.begin_command_buffer(c[0], &bi).map(|()| c[0]))
        };
        let cmd = match begun {
            Ok(c) => c,
            Err(r) => {
                self.release(0, Garbage::CommandPool(pool));
                return Err(crate::error::vk_err(
                    "vkAllocateCommandBuffers/vkBeginCommandBuffer",
                    r,
                ));
            }
        };
        self.name(cmd, label);
        // Order this recording after everything submitted before it: a barrier's first scope
        // covers all earlier commands on the queue, so work of earlier submissions (which the
        // host may not have waited for) is visible here.
        let mb = [vk::MemoryBarrier::default()
            .src_access_mask(ALL_ACCESS)
            .dst_access_mask(ALL_ACCESS)];
        // SAFETY: the command buffer was just begun.
        unsafe {
            device.cmd_pipeline_barrier(
                cmd,
                STAGES,
                STAGES,
                vk::DependencyFlags::empty(),
                &mb,
                &[],
                &[],
            )
        };
        Ok(Recorder {
            ctx: self.clone(),
            pool,
            cmd,
            label: label.into(),
            uses: Vec::new(),
            written: Vec::new(),
            read: Vec::new(),
            submitted: false,
            dispatches: 0,
            barriers: 0,
        })
    }

    /// Ends and submits the recording; returns its timeline ticket.
    pub fn submit(&self, mut rec: Recorder<'_>) -> Result<Ticket> {
        let device = &self.inner.device;
        // SAFETY: the command buffer is in the recording state (begun in `recorder`).
        unsafe { device.end_command_buffer(rec.cmd) }.during("vkEndCommandBuffer")?;
        let queue = self.lock_queue()?;
        let value = self.next_submission_value();
        let values = [value];
        let sems = [self.inner.timeline];
        let cmds = [rec.cmd];
        let mut tl = vk::TimelineSemaphoreSubmitInfo::default().signal_semaphore_values(&values);
        let si = [vk::SubmitInfo::default()
            .command_buffers(&cmds)
            .signal_semaphores(&sems)
            .push_next(&mut tl)];
        // SAFETY: the queue is used under its mutex; the command buffer stays alive until the
        // release queue sees the timeline pass `value`. Timeline values increase per submit
        // because `next_submission_value` is taken under the queue lock.
        let r = unsafe { device.queue_submit(*queue, &si, vk::Fence::null()) };
        drop(queue);
        rec.submitted = true;
        for u in &rec.uses {
            u.fetch_max(value, Ordering::AcqRel);
        }
        if let Err(r) = r {
            // Nothing was queued: signal the value from the host so later waits do not hang.
            let signal = vk::SemaphoreSignalInfo::default()
                .semaphore(self.inner.timeline)
                .value(value);
            // SAFETY: value is greater than any signalled so far (taken under the queue lock).
            let _ = unsafe { device.signal_semaphore(&signal) };
            self.release(value, Garbage::CommandPool(rec.pool));
            return Err(crate::error::vk_err("vkQueueSubmit", r));
        }
        self.release(value, Garbage::CommandPool(rec.pool));
        Ok(Ticket(value))
    }

    /// Blocks until the GPU has finished `ticket` (and everything before it).
    pub fn wait(&self, ticket: Ticket) -> Result<()> {
        let sems = [self.inner.timeline];
        let values = [ticket.0];
        let wi = vk::SemaphoreWaitInfo::default()
            .semaphores(&sems)
            .values(&values);
        // SAFETY: timeline semaphore of this device.
        match unsafe {
            self.inner
                .device
                .wait_semaphores(&wi, wait_timeout_s().saturating_mul(1_000_000_000))
        } {
            Ok(()) => {}
            Err(vk::Result::TIMEOUT) => {
                return Err(GpuError::Timeout {
                    seconds: wait_timeout_s(),
                })
            }
            Err(r) => return Err(crate::error::vk_err("vkWaitSemaphores", r)),
        }
        self.collect_garbage()
    }

    /// Submits and waits.
    pub fn run(&self, rec: Recorder<'_>) -> Result<()> {
        let t = self.submit(rec)?;
        self.wait(t)
    }
}

impl<'a> Recorder<'a> {
    /// Records `kernel` over `threads` invocations (x), folding more than the device's
    /// workgroup limit into 2-D; `bindings` come from the kernel's generated `Bindings`.
    pub fn dispatch<P: Pod, const N: usize>(
        &mut self,
        kernel: &'a Kernel,
        bindings: [Binding<'a>; N],
        params: &P,
        threads: u64,
    ) -> Result<()> {
        let desc = kernel.desc;
        self.same_device(kernel.ctx.id(), &format!("kernel `{}`", desc.name))?;
        for b in &bindings {
            self.same_device(b.ctx, &format!("buffer `{}`", b.name))?;
        }
        if N != desc.bindings.len() {
            return Err(GpuError::KernelMismatch {
                kernel: desc.name,
                problem: format!(
                    "{N} bindings given, the kernel uses {}",
                    desc.bindings.len()
                ),
            });
        }
        let pbytes = bytemuck::bytes_of(params);
        if pbytes.len() != desc.params_size as usize {
            return Err(GpuError::KernelMismatch {
                kernel: desc.name,
                problem: format!(
                    "{} parameter bytes given, the kernel declares {}",
                    pbytes.len(),
                    desc.params_size
                ),
            });
        }
        let info = &self.ctx.inner.info;
        for (b, d) in bindings.iter().zip(desc.bindings) {
            if d.uniform_bytes == 0 {
                if b.bytes > info.max_storage_buffer_range {
                    return Err(GpuError::BufferTooLarge {
                        name: format!("{}` bound as `{}` of kernel `{}", b.name, d.name, desc.name),
                        bytes: b.bytes,
                        limit: info.max_storage_buffer_range,
                    });
                }
                continue;
            }
            let align = info.min_uniform_buffer_offset_alignment.max(1);
            if b.bytes < d.uniform_bytes as u64
                || b.bytes > info.max_uniform_buffer_range
                || !b.offset.is_multiple_of(align)
            {
                return Err(GpuError::Usage(format!(
                    "kernel {}: `{}` bound as uniform block `{}` must cover its {} bytes, stay within {} bytes and start on a multiple of {align} (it has {} bytes at offset {})",
                    desc.name,
                    b.name,
                    d.name,
                    d.uniform_bytes,
                    info.max_uniform_buffer_range,
                    b.bytes,
                    b.offset
                )));
            }
        }
        if threads == 0 {
            return Ok(());
        }
        let wg = desc.workgroup_size[0].max(1) as u64;
        let [gx, gy] = fold_groups(
            threads.div_ceil(wg),
            info.max_workgroup_count_x,
            info.max_workgroup_count_y,
        )?;
        let mut hazard = false;
        for (b, d) in bindings.iter().zip(desc.bindings) {
            hazard |= self.written.contains(&b.raw) || (!d.read_only && self.read.contains(&b.raw));
        }
        if hazard {
            self.barrier();
        }
        let infos: Vec<[vk::DescriptorBufferInfo; 1]> = bindings
            .iter()
            .map(|b| {
                [vk::DescriptorBufferInfo::default()
                    .buffer(b.raw)
                    .offset(b.offset)
                    .range(b.bytes)]
            })
            .collect();
        let writes: Vec<vk::WriteDescriptorSet> = desc
            .bindings
            .iter()
            .zip(&infos)
            .map(|(d, info)| {
                vk::WriteDescriptorSet::default()
                    .dst_binding(d.binding)
                    .descriptor_type(crate::kernel::descriptor_type(d))
                    .buffer_info(info)
            })
            .collect();
        let device = &self.ctx.inner.device;
        // SAFETY: the command buffer is recording; the pipeline, layout and buffers are alive
        // for 'a (buffers) or until the release queue passes this submission (pipeline); the
        // descriptor writes match the set layout built from the same reflection.
        unsafe {
            device.cmd_bind_pipeline(self.cmd, vk::PipelineBindPoint::COMPUTE, kernel.pipeline);
            self.ctx.inner.push_descriptor.cmd_push_descriptor_set(
                self.cmd,
                vk::PipelineBindPoint::COMPUTE,
                kernel.layout,
                0,
                &writes,
            );
            if !pbytes.is_empty() {
                device.cmd_push_constants(
                    self.cmd,
                    kernel.layout,
                    vk::ShaderStageFlags::COMPUTE,
                    0,
                    pbytes,
                );
            }
            device.cmd_dispatch(self.cmd, gx, gy, 1);
        }
        for (b, d) in bindings.iter().zip(desc.bindings) {
            self.uses.push(b.last_use);
            if d.read_only {
                self.read.push(b.raw);
            } else {
                self.written.push(b.raw);
            }
        }
        self.dispatches += 1;
        Ok(())
    }

    /// Refuses a resource made on another context (its handles mean nothing on this device).
    fn same_device(&self, ctx: usize, what: &str) -> Result<()> {
        if ctx != self.ctx.id() {
            return Err(GpuError::Usage(format!(
                "{what} belongs to another Vulkan context than recorder `{}`",
                self.label
            )));
        }
        Ok(())
    }

    /// A full compute/transfer memory barrier.
    pub fn barrier(&mut self) {
        let mb = [vk::MemoryBarrier::default()
            .src_access_mask(ALL_ACCESS)
            .dst_access_mask(ALL_ACCESS)];
        // SAFETY: recording command buffer.
        unsafe {
            self.ctx.inner.device.cmd_pipeline_barrier(
                self.cmd,
                STAGES,
                STAGES,
                vk::DependencyFlags::empty(),
                &mb,
                &[],
                &[],
            )
        };
        self.written.clear();
        self.read.clear();
        self.barriers += 1;
    }

    fn track_copy(&mut self, src: vk::Buffer, dst: vk::Buffer) {
        if self.written.contains(&src) || self.written.contains(&dst) || self.read.contains(&dst) {
            self.barrier();
        }
        self.read.push(src);
        self.written.push(dst);
    }

    /// `vkCmdCopyBuffer` of `bytes` bytes between two buffers.
    pub fn copy(
        &mut self,
        src: Binding<'a>,
        src_offset: u64,
        dst: Binding<'a>,
        dst_offset: u64,
        bytes: u64,
    ) -> Result<()> {
        self.same_device(src.ctx, &format!("buffer `{}`", src.name))?;
        self.same_device(dst.ctx, &format!("buffer `{}`", dst.name))?;
        if src_offset.saturating_add(bytes) > src.bytes
            || dst_offset.saturating_add(bytes) > dst.bytes
        {
            return Err(GpuError::Usage(format!(
                "copy of {bytes} bytes from `{}`+{src_offset} to `{}`+{dst_offset} is out of range",
                src.name, dst.name
            )));
        }
        if bytes == 0 {
            return Ok(());
        }
        self.uses.push(src.last_use);
        self.uses.push(dst.last_use);
        self.record_copy(
            src.raw,
            src.offset + src_offset,
            dst.raw,
            dst.offset + dst_offset,
            bytes,
        );
        Ok(())
    }

    /// `vkCmdFillBuffer`: fills the first `words` 32-bit words with `value`.
    pub fn fill_words(&mut self, dst: Binding<'a>, words: u64, value: u32) -> Result<()> {
        self.same_device(dst.ctx, &format!("buffer `{}`", dst.name))?;
        if words.saturating_mul(4) > dst.bytes {
            return Err(GpuError::Usage(format!(
                "fill of {words} words overruns `{}`",
                dst.name
            )));
        }
        if words == 0 {
            return Ok(());
        }
        self.track_copy(dst.raw, dst.raw);
        self.uses.push(dst.last_use);
        // SAFETY: recording command buffer; range checked above (multiple of 4 bytes).
        unsafe {
            self.ctx
                .inner
                .device
                .cmd_fill_buffer(self.cmd, dst.raw, dst.offset, words * 4, value)
        };
        Ok(())
    }

    /// Staging upload copy; the staging buffer's lifetime is handled by the caller.
    pub(crate) fn copy_raw(
        &mut self,
        staging: &RawBuffer,
        src_offset: u64,
        dst: Binding<'a>,
        dst_offset: u64,
        bytes: u64,
    ) {
        self.uses.push(dst.last_use);
        self.record_copy(
            staging.raw,
            src_offset,
            dst.raw,
            dst.offset + dst_offset,
            bytes,
        );
    }

    /// Readback copy into a host-visible staging buffer, made visible to the host.
    pub(crate) fn copy_to_host(
        &mut self,
        src: Binding<'a>,
        src_offset: u64,
        staging: &RawBuffer,
        bytes: u64,
    ) {
        self.uses.push(src.last_use);
        self.record_copy(src.raw, src.offset + src_offset, staging.raw, 0, bytes);
        let mb = [vk::MemoryBarrier::default()
            .src_access_mask(vk::AccessFlags::TRANSFER_WRITE)
            .dst_access_mask(vk::AccessFlags::HOST_READ)];
        // SAFETY: recording command buffer; makes the copy visible to the host read after the
        // wait.
        unsafe {
            self.ctx.inner.device.cmd_pipeline_barrier(
                self.cmd,
                vk::PipelineStageFlags::TRANSFER,
                vk::PipelineStageFlags::HOST,
                vk::DependencyFlags::empty(),
                &mb,
                &[],
                &[],
            );
        }
    }

    /// Records one buffer copy after any barrier its hazards need. Callers check ranges and
    /// keep both buffers alive until the submission completes.
    fn record_copy(
        &mut self,
        src: vk::Buffer,
        src_offset: u64,
        dst: vk::Buffer,
        dst_offset: u64,
        bytes: u64,
    ) {
        self.track_copy(src, dst);
        let region = [vk::BufferCopy {
            src_offset,
            dst_offset,
            size: bytes,
        }];
        // SAFETY: recording command buffer; callers checked the ranges and keep the buffers
        // alive until the release queue passes this submission.
        unsafe {
            self.ctx
                .inner
                .device
                .cmd_copy_buffer(self.cmd, src, dst, &region)
        };
    }

    /// Resets all queries of `timer` (record before the first timestamp).
    pub fn reset_timer(&mut self, timer: &'a GpuTimer) -> Result<()> {
        self.same_device(timer.ctx.id(), "timer")?;
        // SAFETY: recording command buffer; pool of this device, alive until the release queue
        // passes this submission.
        unsafe {
            self.ctx
                .inner
                .device
                .cmd_reset_query_pool(self.cmd, timer.pool, 0, timer.capacity)
        };
        Ok(())
    }

    /// Writes timestamp `index` once all previous commands have finished.
    pub fn timestamp(&mut self, timer: &'a GpuTimer, index: u32) -> Result<()> {
        self.same_device(timer.ctx.id(), "timer")?;
        if index >= timer.capacity {
            return Err(GpuError::Usage(format!(
                "timestamp {index} past the timer's {} slots",
                timer.capacity
            )));
        }
        // SAFETY: recording command buffer; index checked.
        unsafe {
            self.ctx.inner.device.cmd_write_timestamp(
                self.cmd,
                vk::PipelineStageFlags::BOTTOM_OF_PIPE,
                timer.pool,
                index,
            )
        };
        Ok(())
    }
}

impl Drop for Recorder<'_> {
    fn drop(&mut self) {
        if !self.submitted {
            // Never submitted: nothing on the GPU refers to it.
            self.ctx.release(0, Garbage::CommandPool(self.pool));
        }
    }
}

/// Timestamp queries: record with [`Recorder::timestamp`], read after the submission finished.
pub struct GpuTimer {
    ctx: Context,
    pool: vk::QueryPool,
    capacity: u32,
}

impl std::fmt::Debug for GpuTimer {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("GpuTimer")
            .field("capacity", &self.capacity)
            .finish_non_exhaustive()
    }
}

impl GpuTimer {
    /// A pool of `capacity` timestamps; fails when the compute queue has no timestamps.
    pub fn new(ctx: &Context, name: &str, capacity: u32) -> Result<GpuTimer> {
        if !ctx.info().timestamps {
            return Err(GpuError::MissingFeature {
                device: ctx.info().name.clone(),
                what: "timestamps on the compute queue".into(),
                needed_by: "GpuTimer".into(),
            });
        }
        let ci = vk::QueryPoolCreateInfo::default()
            .query_type(vk::QueryType::TIMESTAMP)
            .query_count(capacity.max(1));
        // SAFETY: valid device and create info.
        let pool =
            unsafe { ctx.inner.device.create_query_pool(&ci, None) }.during("vkCreateQueryPool")?;
        ctx.name(pool, name);
        Ok(GpuTimer {
            ctx: ctx.clone(),
            pool,
            capacity: capacity.max(1),
        })
    }

    /// Reads timestamps `0..count` in nanoseconds (waits for them to be available).
    pub fn read_ns(&self, count: u32) -> Result<Vec<f64>> {
        if count > self.capacity {
            return Err(GpuError::Usage(format!(
                "{count} timestamps requested from a timer of {}",
                self.capacity
            )));
        }
        let mut raw = vec![0u64; count as usize];
        if count > 0 {
            // SAFETY: the queries were reset and written by a submitted command buffer; WAIT
            // blocks until they are available.
            unsafe {
                self.ctx.inner.device.get_query_pool_results(
                    self.pool,
                    0,
                    &mut raw,
                    vk::QueryResultFlags::TYPE_64 | vk::QueryResultFlags::WAIT,
                )
            }
            .during("vkGetQueryPoolResults")?;
        }
        let period = self.ctx.info().timestamp_period_ns as f64;
        Ok(raw.into_iter().map(|t| t as f64 * period).collect())
    }
}

impl Drop for GpuTimer {
    fn drop(&mut self) {
        let last = self.ctx.inner_last_submitted();
        self.ctx.release(last, Garbage::QueryPool(self.pool));
    }
}
