//! Devices that wgpu adopts (feature `wgpu`): the engine creates the VkInstance and VkDevice
//! with the extensions and features wgpu-hal needs, then wraps them as wgpu objects, so that
//! burn (on wgpu) and the engine's kernels run on one device and can share buffers.
//!
//! wgpu-hal's `physical_device_features` builds the device's feature chain; the engine adds
//! only its push-descriptor extension (the f16, 16-bit storage and float-atomic features it
//! needs map to wgpu features). Chaining the engine's own Vulkan 1.1/1.2 feature structs as
//! well would duplicate structs wgpu chains and fail device creation.

use std::ffi::CStr;

use ash::vk;

use crate::error::{GpuError, Result};

/// The wgpu view of the engine's device: clone these into wgpu users (burn's `WgpuSetup`).
#[derive(Clone, Debug)]
pub struct WgpuHandles {
    /// The instance, wrapping the engine's VkInstance.
    pub instance: wgpu::Instance,
    /// The adapter of the engine's physical device.
    pub adapter: wgpu::Adapter,
    /// The device, wrapping the engine's VkDevice.
    pub device: wgpu::Device,
    /// The queue: the engine's own VkQueue. Submit from one thread at a time, and let one side
    /// finish (burn: sync; the engine: its runs wait) before the other submits.
    pub queue: wgpu::Queue,
}

impl WgpuHandles {
    /// The raw VkDevice behind the wgpu device, as an integer (compare with
    /// `Context::raw_device`).
    pub fn raw_device(&self) -> Option<u64> {
        // SAFETY: read-only access to the raw handle of a live device.
        unsafe {
            self.device
                .as_hal::<wgpu_hal::api::Vulkan>()
                .map(|d| vk::Handle::as_raw(d.raw_device().handle()))
        }
    }
}

/// The wgpu features of the shared device: the engine's needs (subgroups, f16, float atomics)
/// plus every feature cubecl reads off the *adapter* to choose its kernels' types (64-bit
/// integers and floats, f16, f32 atomics) or its timers. cubecl requests all adapter
/// features for devices it creates itself and emits, e.g., u64 in its convolutions where
/// SHADER_INT64 is offered, so a device without them fails burn's shader validation. (All
/// adapter features would also enable extensions the validation layer does not know.)
fn wanted(available: wgpu_types::Features, f16: bool, atomic_float: bool) -> wgpu_types::Features {
    use wgpu_types::Features as F;
    let mut f = F::SUBGROUP
        | F::SHADER_INT64
        | F::SHADER_F64
        | F::SHADER_F16
        | F::SHADER_FLOAT32_ATOMIC
        | F::TIMESTAMP_QUERY;
    if f16 {
        f |= F::SHADER_F16;
    }
    if atomic_float {
        f |= F::SHADER_FLOAT32_ATOMIC;
    }
    f & available
}

/// Instance extensions wgpu-hal wants (those the loader has).
pub(crate) fn instance_extensions(entry: &ash::Entry, api: u32) -> Result<Vec<&'static CStr>> {
    wgpu_hal::vulkan::Instance::desired_extensions(entry, api, wgpu_types::InstanceFlags::empty())
        .map_err(|e| GpuError::NoDevice(format!("wgpu-hal instance extensions: {e}")))
}

/// The adapter wgpu-hal sees for the engine's physical device, with the extensions and feature
/// chain the device must be created with.
pub(crate) struct Share {
    hal_instance: wgpu_hal::vulkan::Instance,
    exposed: wgpu_hal::ExposedAdapter<wgpu_hal::api::Vulkan>,
    features: wgpu_types::Features,
    /// Device extensions: wgpu-hal's and the engine's.
    pub(crate) extensions: Vec<&'static CStr>,
    pub(crate) chain: wgpu_hal::vulkan::PhysicalDeviceFeatures,
}

impl Share {
    /// Wraps the engine's instance for wgpu-hal and exposes `physical`.
    pub(crate) fn new(
        entry: &ash::Entry,
        instance: &ash::Instance,
        api: u32,
        instance_extensions: Vec<&'static CStr>,
        physical: vk::PhysicalDevice,
        f16: bool,
        atomic_float: bool,
    ) -> Result<Share> {
        // SAFETY: `instance` was created from `entry` with `instance_extensions` enabled and API
        // version `api`; the drop callback leaves its destruction to the engine, which outlives
        // every wgpu object (a shared context never destroys its device, see Inner::drop).
        let hal_instance = unsafe {
            wgpu_hal::vulkan::Instance::from_raw(
                entry.clone(),
                instance.clone(),
                api,
                0,
                None,
                instance_extensions,
                wgpu_types::InstanceFlags::empty(),
                wgpu_types::MemoryBudgetThresholds::default(),
                false,
                Some(Box::new(|| {})),
            )
        }
        .map_err(|e| GpuError::NoDevice(format!("wgpu-hal cannot adopt the instance: {e}")))?;
        let exposed = hal_instance.expose_adapter(physical).ok_or_else(|| {
            GpuError::NoDevice("wgpu-hal does not expose this device (not conformant?)".into())
        })?;
        let features = wanted(exposed.features, f16, atomic_float);
        let mut extensions = exposed.adapter.required_device_extensions(features);
        for ext in [ash::khr::push_descriptor::NAME] {
            if !extensions.contains(&ext) {
                extensions.push(ext);
            }
        }
        let chain = exposed
            .adapter
            .physical_device_features(&extensions, features);
        Ok(Share {
            hal_instance,
            exposed,
            features,
            extensions,
            chain,
        })
    }

    /// Wraps the device created with [`Share::extensions`] and [`Share::chain`] as wgpu objects.
    pub(crate) fn adopt(self, device: &ash::Device, family: u32) -> Result<WgpuHandles> {
        let limits = self.exposed.capabilities.limits.clone();
        // SAFETY: `device` was created from this adapter's physical device with `extensions`
        // and the feature chain from `physical_device_features(extensions, features)`, one
        // queue of `family`; the engine keeps it alive (the drop callback does nothing).
        let open = unsafe {
            self.exposed.adapter.device_from_raw(
                device.clone(),
                Some(Box::new(|| {})),
                &self.extensions,
                self.features,
                &limits,
                &wgpu_types::MemoryHints::Performance,
                family,
                0,
            )
        }
        .map_err(|e| GpuError::NoDevice(format!("wgpu-hal cannot adopt the device: {e}")))?;
        // SAFETY: the hal instance, adapter and device belong together (created above).
        let instance =
            unsafe { wgpu::Instance::from_hal::<wgpu_hal::api::Vulkan>(self.hal_instance) };
        // SAFETY: as above.
        let adapter = unsafe { instance.create_adapter_from_hal(self.exposed) };
        let desc = wgpu::DeviceDescriptor {
            label: Some("extranerf shared device"),
            required_features: self.features,
            required_limits: limits,
            ..Default::default()
        };
        // SAFETY: `open` was made from this adapter with these features and limits.
        let (device, queue) = unsafe { adapter.create_device_from_hal(open, &desc) }
            .map_err(|e| GpuError::NoDevice(format!("wgpu cannot adopt the device: {e}")))?;
        Ok(WgpuHandles {
            instance,
            adapter,
            device,
            queue,
        })
    }
}
