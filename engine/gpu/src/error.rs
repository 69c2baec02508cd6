//! The one error type of the Vulkan layer.

use ash::vk;

/// Everything that can go wrong in the Vulkan layer, each with a message a user can act on.
#[derive(Debug, thiserror::Error)]
pub enum GpuError {
    /// `libvulkan.so.1` (or the platform's loader) could not be opened.
    #[error(
        "no Vulkan loader could be loaded ({0}); install the loader and a driver, for example \
         `apt-get install libvulkan1 mesa-vulkan-drivers` (Mesa's lavapipe runs on any CPU)"
    )]
    NoLoader(String),
    /// The loader works but no usable driver or device is installed.
    #[error(
        "no usable Vulkan device: {0}; install a driver, for example \
         `apt-get install mesa-vulkan-drivers` for the lavapipe CPU device"
    )]
    NoDevice(String),
    /// `--device` / `EXTRANERF_DEVICE` named a device that is not there.
    #[error("no Vulkan device matches `{requested}`; available devices: {available}")]
    DeviceNotFound {
        /// What the user asked for.
        requested: String,
        /// Index and name of every device found.
        available: String,
    },
    /// A feature or extension the engine (or a kernel) needs is missing.
    #[error("device `{device}` lacks {what}, which {needed_by} needs")]
    MissingFeature {
        /// Device name.
        device: String,
        /// The feature or extension.
        what: String,
        /// Who needs it.
        needed_by: String,
    },
    /// Validation was required but the Khronos layer is not installed.
    #[error(
        "the Khronos validation layer (VK_LAYER_KHRONOS_validation) was required but is not \
         installed; install it with `apt-get install vulkan-validationlayers`"
    )]
    ValidationUnavailable,
    /// Device (or host-visible) memory ran out.
    #[error("out of device memory while allocating `{name}` ({bytes} bytes)")]
    OutOfDeviceMemory {
        /// Name of the resource being created.
        name: String,
        /// Its size.
        bytes: u64,
    },
    /// A buffer larger than the device allocates (`maxMemoryAllocationSize`), or a storage
    /// binding larger than `maxStorageBufferRange` (lavapipe: 128 MiB).
    #[error(
        "buffer `{name}` needs {bytes} bytes but this device allows at most {limit} bytes there \
         (maxMemoryAllocationSize for a buffer, maxStorageBufferRange for one binding); split it"
    )]
    BufferTooLarge {
        /// Name of the buffer.
        name: String,
        /// Bytes it needs.
        bytes: u64,
        /// The device limit.
        limit: u64,
    },
    /// The device was lost (driver crash, GPU reset, hang).
    #[error("the Vulkan device was lost during {during}; the context cannot be used any more")]
    DeviceLost {
        /// The call that reported it.
        during: &'static str,
    },
    /// Waiting for the GPU took longer than the timeout.
    #[error("timed out after {seconds} s waiting for the GPU")]
    Timeout {
        /// The timeout.
        seconds: u64,
    },
    /// Any other failing Vulkan call.
    #[error("{call} failed: {result}")]
    Vulkan {
        /// The Vulkan function.
        call: &'static str,
        /// Its result code.
        result: vk::Result,
    },
    /// gpu-allocator refused an allocation for a reason other than running out of memory.
    #[error("allocating memory for `{name}`: {message}")]
    Allocation {
        /// Name of the resource.
        name: String,
        /// What the allocator said.
        message: String,
    },
    /// Bindings or parameters handed to a kernel do not match its reflected interface.
    #[error("kernel `{kernel}`: {problem}")]
    KernelMismatch {
        /// Kernel name.
        kernel: &'static str,
        /// What does not match.
        problem: String,
    },
    /// A call with arguments that cannot work (lengths, ranges).
    #[error("{0}")]
    Usage(String),
}

/// Result alias of the Vulkan layer.
pub type Result<T, E = GpuError> = std::result::Result<T, E>;

/// An element count as the `u32` the kernels index with, or a [`GpuError::Usage`] naming `what`.
pub fn count_u32(n: u64, what: &str) -> Result<u32> {
    u32::try_from(n).map_err(|_| {
        GpuError::Usage(format!(
            "{what}: {n} elements exceed the kernels' 32-bit indices"
        ))
    })
}

/// Maps a failing `VkResult` to the error a user can act on.
pub(crate) fn vk_err(call: &'static str, result: vk::Result) -> GpuError {
    match result {
        vk::Result::ERROR_DEVICE_LOST => GpuError::DeviceLost { during: call },
        vk::Result::ERROR_OUT_OF_DEVICE_MEMORY | vk::Result::ERROR_OUT_OF_HOST_MEMORY => {
            GpuError::OutOfDeviceMemory {
                name: call.to_string(),
                bytes: 0,
            }
        }
        result => GpuError::Vulkan { call, result },
    }
}

/// Adds the call name to an `ash` result.
pub(crate) trait VkContext<T> {
    fn during(self, call: &'static str) -> Result<T>;
}

impl<T> VkContext<T> for std::result::Result<T, vk::Result> {
    fn during(self, call: &'static str) -> Result<T> {
        self.map_err(|r| vk_err(call, r))
    }
}
