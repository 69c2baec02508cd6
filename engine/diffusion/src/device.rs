//! burn on the engine's device: the engine creates the VkDevice ([`ContextDesc::share_with_wgpu`]),
//! wgpu adopts it, and burn's wgpu runtime is registered on those handles. Engine kernels bind a
//! burn tensor's memory through [`TensorBuffer`]: nothing crosses the host.
//!
//! [`ContextDesc::share_with_wgpu`]: extranerf_gpu::ContextDesc::share_with_wgpu

use burn::tensor::{Device, Tensor};
use burn_cubecl::CubeBackend;
use cubecl_wgpu::{AutoCompiler, WgpuResource, WgpuServer};
use extranerf_gpu::{Binding, Context, SharedBuffer};

/// What can go wrong handing the device over.
#[derive(Debug, thiserror::Error)]
pub enum DeviceError {
    /// The context was not created to share its device.
    #[error(
        "the engine's context was not created with share_with_wgpu; create it so to run burn on it"
    )]
    NotShared,
    /// burn refused the handles.
    #[error("burn cannot use the engine's device: {0}")]
    Burn(String),
    /// The tensor is not a plain wgpu tensor on this device.
    #[error("tensor memory: {0}")]
    Tensor(String),
    /// The engine refused the buffer.
    #[error(transparent)]
    Gpu(#[from] extranerf_gpu::GpuError),
}

/// Registers burn's wgpu runtime on the engine's device (once per context; clone the result).
pub fn burn_device(ctx: &Context) -> Result<Device, DeviceError> {
    let h = ctx.wgpu().ok_or(DeviceError::NotShared)?;
    let setup = burn::tensor::wgpu::WgpuSetup {
        instance: h.instance.clone(),
        adapter: h.adapter.clone(),
        device: h.device.clone(),
        queue: h.queue.clone(),
        backend: burn::tensor::wgpu::wgpu::Backend::Vulkan,
    };
    Device::wgpu_options()
        .setup(setup)
        .init()
        .map_err(|e| DeviceError::Burn(e.to_string()))
}

/// A float tensor's memory, bound by engine kernels in place. burn must be idle on the tensor
/// while the engine uses it (call [`TensorBuffer::new`] after burn's work is submitted; it
/// synchronises), and the tensor must stay alive.
#[derive(Debug)]
pub struct TensorBuffer {
    shared: SharedBuffer,
    // burn's ManagedResource: keeps the allocation in place while the engine holds the range.
    _resource: Box<dyn std::any::Any>,
}

impl TensorBuffer {
    /// The memory of `tensor` (a float tensor on [`burn_device`]'s device of `ctx`).
    pub fn new<const D: usize>(
        ctx: &Context,
        tensor: &Tensor<D>,
    ) -> Result<TensorBuffer, DeviceError> {
        let prim = tensor
            .clone()
            .try_into_primitive::<CubeBackend>()
            .map_err(|e| DeviceError::Tensor(format!("{e:?}")))?;
        let bytes = prim.handle.size_in_used();
        let managed = prim
            .client
            .get_resource::<WgpuServer<AutoCompiler>>(prim.handle.clone())
            .map_err(|e| DeviceError::Tensor(format!("{e:?}")))?;
        let r: &WgpuResource = managed.resource();
        let shared = SharedBuffer::new(ctx, &r.buffer, r.offset, bytes, "burn tensor")?;
        Ok(TensorBuffer {
            shared,
            _resource: Box::new(managed),
        })
    }

    /// The tensor's memory as a kernel binding.
    pub fn binding(&self) -> Binding<'_> {
        self.shared.binding()
    }
}

/// Where the diffusion model runs (`--diffusion-backend`).
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "lowercase")]
#[cfg_attr(feature = "clap", derive(clap::ValueEnum))]
pub enum Backend {
    /// The engine's Vulkan device, unless that device is itself a CPU implementation (Mesa
    /// lavapipe), where burn's CPU backend measured several times faster (`bench diffusion`).
    Auto,
    /// burn's wgpu backend on the engine's own VkDevice (the product path).
    Device,
    /// burn's CPU backend (flex).
    Cpu,
}

impl Backend {
    /// What `Auto` resolves to on a device of this Vulkan type ("CPU" for lavapipe).
    pub fn resolve(self, device_type: &str) -> Backend {
        match self {
            Backend::Auto if device_type == "CPU" => Backend::Cpu,
            Backend::Auto => Backend::Device,
            b => b,
        }
    }

    /// The backend's name in reports.
    pub fn name(self) -> &'static str {
        match self {
            Backend::Auto => "auto",
            Backend::Device => "device (burn wgpu on the engine's VkDevice)",
            Backend::Cpu => "cpu (burn flex)",
        }
    }
}

/// The burn device for a resolved backend: the engine's shared device for `Device` (the
/// context must be created with `share_with_wgpu`), burn's CPU backend for `Cpu`.
pub fn diffusion_device(ctx: &Context, backend: Backend) -> Result<(Backend, Device), DeviceError> {
    let b = backend.resolve(&ctx.info().device_type);
    let d = match b {
        Backend::Cpu => Device::flex(),
        _ => burn_device(ctx)?,
    };
    Ok((b, d))
}
