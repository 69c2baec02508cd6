//! Instance, device selection, queue, allocator, timeline, deferred release and validation log.

use std::ffi::{c_void, CStr, CString};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex, MutexGuard};

use ash::vk;
use gpu_allocator::vulkan::{Allocation, Allocator, AllocatorCreateDesc};

use crate::error::{GpuError, Result, VkContext};

const VALIDATION_LAYER: &CStr = c"VK_LAYER_KHRONOS_validation";
/// Longest wait on the GPU before [`GpuError::Timeout`], unless `EXTRANERF_GPU_TIMEOUT_S`
/// says otherwise (see [`wait_timeout_s`]).
pub(crate) const WAIT_TIMEOUT_S: u64 = 600;

/// `EXTRANERF_GPU_TIMEOUT_S`: seconds, a whole number from 1 (unset: [`WAIT_TIMEOUT_S`]).
fn timeout_from_env() -> std::result::Result<u64, String> {
    match std::env::var("EXTRANERF_GPU_TIMEOUT_S") {
        Err(_) => Ok(WAIT_TIMEOUT_S),
        Ok(v) => match v.trim().parse::<u64>() {
            Ok(s) if s >= 1 => Ok(s),
            _ => Err(format!(
                "EXTRANERF_GPU_TIMEOUT_S is `{v}`: give a whole number of seconds, at least 1"
            )),
        },
    }
}

/// The longest wait on the GPU: `EXTRANERF_GPU_TIMEOUT_S` (for a device far slower than
/// usual, such as lavapipe under valgrind, whose first dispatch of a large kernel compiles for
/// many minutes), else 600 s. [`Context::new`] refuses an invalid value, so it never gets here.
pub(crate) fn wait_timeout_s() -> u64 {
    static SECONDS: std::sync::OnceLock<u64> = std::sync::OnceLock::new();
    *SECONDS.get_or_init(|| timeout_from_env().unwrap_or(WAIT_TIMEOUT_S))
}

/// Whether to load the Khronos validation layer.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Default)]
pub enum Validation {
    /// Never.
    Off,
    /// When installed (tests use this; CI installs it).
    #[default]
    IfAvailable,
    /// Fail with [`GpuError::ValidationUnavailable`] when it is not installed.
    Required,
}

impl Validation {
    /// Reads `EXTRANERF_VALIDATION` (`0`/`off`, `1`/`on`, `required`), else `default`.
    pub fn from_env(default: Validation) -> Validation {
        match std::env::var("EXTRANERF_VALIDATION")
            .ok()
            .as_deref()
            .map(str::to_ascii_lowercase)
            .as_deref()
        {
            Some("0" | "off" | "false" | "no") => Validation::Off,
            Some("1" | "on" | "true" | "yes") => Validation::IfAvailable,
            Some("required" | "require") => Validation::Required,
            _ => default,
        }
    }
}

/// How to create a [`Context`].
#[derive(Clone, Debug, Default)]
pub struct ContextDesc {
    /// Validation layer policy.
    pub validation: Validation,
    /// Device to use: an index into [`list_devices`] or a case-insensitive part of its name.
    /// `None` reads `EXTRANERF_DEVICE`, else picks discrete > integrated > virtual > CPU.
    pub device: Option<String>,
    /// Treat storage bindings as limited to this many bytes when the device allows more
    /// (`maxStorageBufferRange`), so large tables are split as on a smaller device.
    pub max_binding_bytes: Option<u64>,
    /// Refuse buffer allocations once the engine's live allocations would exceed this many
    /// bytes (as if the device had no more memory): reproduces a smaller device's
    /// out-of-memory error anywhere (tests, `--max-memory`).
    pub max_memory_bytes: Option<u64>,
    /// Create the device so that wgpu adopts it ([`Context::wgpu`]; needs the `wgpu` feature).
    /// It enables what wgpu-hal asks for, robust buffer access included, and is never
    /// destroyed before the process exits, since wgpu users such as burn keep it in global
    /// registries.
    pub share_with_wgpu: bool,
    /// Leave `VK_KHR_cooperative_matrix` off even where the device offers it, as on a device
    /// without it (tests of the scalar fallbacks and of `--mlp coop`'s error).
    pub no_coop_matrix: bool,
}

/// One heap of the device.
#[derive(Clone, Debug)]
pub struct HeapInfo {
    /// Bytes.
    pub size: u64,
    /// `VK_MEMORY_HEAP_DEVICE_LOCAL_BIT`.
    pub device_local: bool,
}

/// What the engine knows about its device; printed by `extranerf info`.
#[derive(Clone, Debug)]
pub struct DeviceInfo {
    /// Index in the loader's enumeration.
    pub index: usize,
    /// `deviceName`.
    pub name: String,
    /// Discrete GPU, integrated GPU, virtual GPU, CPU or other.
    pub device_type: String,
    /// Driver name (VkPhysicalDeviceDriverProperties), e.g. `llvmpipe`.
    pub driver_name: String,
    /// Driver info, e.g. `Mesa 25.0.7 (LLVM 15.0.6)`.
    pub driver_info: String,
    /// The device's Vulkan version `major.minor.patch`.
    pub api_version: String,
    /// The version the engine uses (instance and device).
    pub used_api_version: String,
    /// PCI vendor id.
    pub vendor_id: u32,
    /// Memory heaps.
    pub heaps: Vec<HeapInfo>,
    /// Subgroup size.
    pub subgroup_size: u32,
    /// Compute shaders have subgroup basic + arithmetic + ballot operations.
    pub subgroup_arithmetic: bool,
    /// `maxStorageBufferRange`: the most bytes one storage binding covers.
    pub max_storage_buffer_range: u64,
    /// The largest buffer the engine creates (`maxMemoryAllocationSize`); buffers larger than
    /// one binding are bound in ranges.
    pub max_buffer_bytes: u64,
    /// `minStorageBufferOffsetAlignment`.
    pub min_storage_buffer_offset_alignment: u64,
    /// `maxUniformBufferRange`.
    pub max_uniform_buffer_range: u64,
    /// `minUniformBufferOffsetAlignment`.
    pub min_uniform_buffer_offset_alignment: u64,
    /// `maxComputeWorkGroupCount[0]`.
    pub max_workgroup_count_x: u32,
    /// `maxComputeWorkGroupCount[1]`.
    pub max_workgroup_count_y: u32,
    /// `maxComputeSharedMemorySize`.
    pub max_shared_memory: u32,
    /// Nanoseconds per timestamp tick.
    pub timestamp_period_ns: f32,
    /// The compute queue writes timestamps.
    pub timestamps: bool,
    /// `shaderBufferFloat32AtomicAdd` (VK_EXT_shader_atomic_float), enabled when present.
    pub float32_atomic_add: bool,
    /// `shaderFloat16`, enabled when present (for the f16 path).
    pub shader_float16: bool,
    /// `storageBuffer16BitAccess` and `uniformAndStorageBuffer16BitAccess` (naga declares both
    /// for f16 storage), enabled when present.
    pub storage_buffer_16bit: bool,
    /// The validation layer is loaded.
    pub validation: bool,
    /// The cooperative-matrix shapes the device offers (`VK_KHR_cooperative_matrix`, enabled
    /// when present); empty without the extension.
    pub coop_matrix: Vec<CoopMatrixShape>,
}

/// One cooperative-matrix shape a device offers
/// (`vkGetPhysicalDeviceCooperativeMatrixPropertiesKHR`): `A (m x k) * B (k x n) + C (m x n)`.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct CoopMatrixShape {
    /// Rows of A and C.
    pub m: u32,
    /// Columns of B and C.
    pub n: u32,
    /// Columns of A, rows of B.
    pub k: u32,
    /// Element types of A, B, C and the result (`f16`, `f32`, `bf16`, `i8`, `u8`, `i32`, ...).
    pub types: [String; 4],
    /// Scope (`subgroup`, `workgroup`, ...).
    pub scope: String,
}

impl CoopMatrixShape {
    /// True for a square `tile` shape with f16 A and B and an f32 accumulator at subgroup scope:
    /// the one the engine's cooperative-matrix kernels use.
    pub fn is_f16_f32(&self, tile: u32) -> bool {
        self.m == tile
            && self.n == tile
            && self.k == tile
            && self.types == ["f16", "f16", "f32", "f32"]
            && self.scope == "subgroup"
    }
}

impl std::fmt::Display for CoopMatrixShape {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let [a, b, c, r] = &self.types;
        write!(
            f,
            "{}x{}x{} {a}*{b}+{c}->{r} ({})",
            self.m, self.n, self.k, self.scope
        )
    }
}

impl DeviceInfo {
    /// True for a CPU device (lavapipe).
    pub fn is_cpu(&self) -> bool {
        self.device_type == device_type_name(vk::PhysicalDeviceType::CPU)
    }

    /// The largest square f16 x f16 + f32 subgroup tile (8 or 16) that the engine's
    /// cooperative-matrix kernels can use on this device, if any.
    pub fn coop_tile(&self) -> Option<u32> {
        [16, 8].into_iter().find(|&t| self.offers_coop_tile(t))
    }

    /// True when the device offers the square f16 x f16 + f32 subgroup tile of edge `tile`.
    pub fn offers_coop_tile(&self, tile: u32) -> bool {
        self.coop_matrix.iter().any(|s| s.is_f16_f32(tile))
    }
}

/// One validation-layer message.
#[derive(Clone, Debug)]
pub struct ValidationMessage {
    /// `WARNING` or `ERROR`.
    pub severity: String,
    /// The message, with its id.
    pub text: String,
}

#[derive(Debug, Default)]
pub(crate) struct ValidationLog {
    messages: Mutex<Vec<ValidationMessage>>,
}

/// The validation messages of one context; outlives it, so messages emitted while the device
/// and instance are destroyed (leaked objects) can still be read.
#[derive(Clone, Debug)]
pub struct ValidationLogHandle(Arc<ValidationLog>);

impl ValidationLogHandle {
    /// Messages so far (warnings and errors), clearing the log.
    pub fn take(&self) -> Vec<ValidationMessage> {
        self.0
            .messages
            .lock()
            .map(|mut m| std::mem::take(&mut *m))
            .unwrap_or_default()
    }
}

/// Something whose destruction waits until the GPU is done with it.
pub(crate) enum Garbage {
    Buffer(vk::Buffer, Allocation),
    Pipeline {
        pipeline: vk::Pipeline,
        layout: vk::PipelineLayout,
        set_layout: vk::DescriptorSetLayout,
        module: vk::ShaderModule,
    },
    QueryPool(vk::QueryPool),
    /// A recorder's own pool (and with it its command buffer).
    CommandPool(vk::CommandPool),
}

pub(crate) struct Inner {
    _entry: ash::Entry,
    pub(crate) instance: ash::Instance,
    debug_instance: Option<ash::ext::debug_utils::Instance>,
    messenger: vk::DebugUtilsMessengerEXT,
    log: Arc<ValidationLog>,
    pub(crate) device: ash::Device,
    debug_device: Option<ash::ext::debug_utils::Device>,
    pub(crate) push_descriptor: ash::khr::push_descriptor::Device,
    queue: Mutex<vk::Queue>,
    pub(crate) queue_family: u32,
    pub(crate) timeline: vk::Semaphore,
    last_submitted: AtomicU64,
    allocator: Mutex<Option<Allocator>>,
    garbage: Mutex<Vec<(u64, Garbage)>>,
    pub(crate) info: DeviceInfo,
    /// [`ContextDesc::max_memory_bytes`].
    pub(crate) max_memory: Option<u64>,
    /// Created for wgpu to adopt: the device and instance outlive the context.
    shared: bool,
    #[cfg(feature = "wgpu")]
    wgpu: Option<crate::wgpu_share::WgpuHandles>,
}

/// A submission's place on the context's timeline; wait on it with [`Context::wait`].
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord)]
pub struct Ticket(pub u64);

/// The engine's Vulkan device: cheap to clone, shared by every resource made from it.
#[derive(Clone)]
pub struct Context {
    pub(crate) inner: Arc<Inner>,
}

impl std::fmt::Debug for Context {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Context")
            .field("device", &self.inner.info.name)
            .finish_non_exhaustive()
    }
}

unsafe extern "system" fn debug_callback(
    severity: vk::DebugUtilsMessageSeverityFlagsEXT,
    _types: vk::DebugUtilsMessageTypeFlagsEXT,
    data: *const vk::DebugUtilsMessengerCallbackDataEXT<'_>,
    user: *mut c_void,
) -> vk::Bool32 {
    // SAFETY: `user` is the `Arc<ValidationLog>` held by `Inner`, which destroys the messenger
    // before dropping its Arc; `data` and its strings are valid for the duration of the call
    // per the Vulkan spec.
    let (log, text) = unsafe {
        let log = &*(user as *const ValidationLog);
        let d = &*data;
        let id = if d.p_message_id_name.is_null() {
            "".into()
        } else {
            CStr::from_ptr(d.p_message_id_name).to_string_lossy()
        };
        let msg = if d.p_message.is_null() {
            "".into()
        } else {
            CStr::from_ptr(d.p_message).to_string_lossy()
        };
        (log, format!("[{id}] {msg}"))
    };
    let sev = if severity.contains(vk::DebugUtilsMessageSeverityFlagsEXT::ERROR) {
        "ERROR"
    } else {
        "WARNING"
    };
    tracing::warn!(target: "vulkan", "{sev}: {text}");
    if let Ok(mut m) = log.messages.lock() {
        m.push(ValidationMessage {
            severity: sev.to_string(),
            text,
        });
    }
    vk::FALSE
}

fn version_string(v: u32) -> String {
    format!(
        "{}.{}.{}",
        vk::api_version_major(v),
        vk::api_version_minor(v),
        vk::api_version_patch(v)
    )
}

fn device_type_name(t: vk::PhysicalDeviceType) -> &'static str {
    match t {
        vk::PhysicalDeviceType::DISCRETE_GPU => "discrete GPU",
        vk::PhysicalDeviceType::INTEGRATED_GPU => "integrated GPU",
        vk::PhysicalDeviceType::VIRTUAL_GPU => "virtual GPU",
        vk::PhysicalDeviceType::CPU => "CPU",
        _ => "other",
    }
}

fn type_rank(t: vk::PhysicalDeviceType) -> u32 {
    match t {
        vk::PhysicalDeviceType::DISCRETE_GPU => 0,
        vk::PhysicalDeviceType::INTEGRATED_GPU => 1,
        vk::PhysicalDeviceType::VIRTUAL_GPU => 2,
        vk::PhysicalDeviceType::CPU => 3,
        _ => 4,
    }
}

fn c_name(bytes: &[std::ffi::c_char]) -> String {
    // Vulkan fixed-size name arrays are NUL-terminated; without a NUL the whole array is used.
    let b: Vec<u8> = bytes
        .iter()
        .take_while(|&&c| c != 0)
        .map(|&c| c as u8)
        .collect();
    String::from_utf8_lossy(&b).into_owned()
}

fn load_entry() -> Result<ash::Entry> {
    // SAFETY: loading the system Vulkan loader runs its initialisers; this is the documented way
    // to use ash with a dynamically loaded loader, and the Entry is kept alive in `Inner`.
    unsafe { ash::Entry::load() }.map_err(|e| GpuError::NoLoader(e.to_string()))
}

/// A device as the loader lists it.
#[derive(Clone, Debug)]
pub struct DeviceListing {
    /// Index for `--device`.
    pub index: usize,
    /// Name.
    pub name: String,
    /// Kind.
    pub device_type: String,
    /// Vulkan version.
    pub api_version: String,
}

/// Lists the Vulkan devices without creating a logical device.
pub fn list_devices() -> Result<Vec<DeviceListing>> {
    let entry = load_entry()?;
    let app = vk::ApplicationInfo::default().api_version(vk::API_VERSION_1_2);
    let ci = vk::InstanceCreateInfo::default().application_info(&app);
    // SAFETY: the create info and everything it points to live across the call.
    let instance = unsafe { entry.create_instance(&ci, None) }.during("vkCreateInstance")?;
    // SAFETY: the instance is valid; it is destroyed below and its handles are not kept.
    let result = unsafe {
        let r = instance
            .enumerate_physical_devices()
            .during("vkEnumeratePhysicalDevices")
            .map(|pds| {
                pds.iter()
                    .enumerate()
                    .map(|(index, &pd)| {
                        let p = instance.get_physical_device_properties(pd);
                        DeviceListing {
                            index,
                            name: c_name(&p.device_name),
                            device_type: device_type_name(p.device_type).into(),
                            api_version: version_string(p.api_version),
                        }
                    })
                    .collect()
            });
        instance.destroy_instance(None);
        r
    };
    result
}

impl Context {
    /// Creates the engine's device per `desc` (see [`ContextDesc`]).
    pub fn new(desc: &ContextDesc) -> Result<Context> {
        timeout_from_env().map_err(GpuError::Usage)?;
        let entry = load_entry()?;
        // SAFETY: plain queries on a loaded entry.
        let (loader_version, layers, inst_exts) = unsafe {
            (
                entry
                    .try_enumerate_instance_version()
                    .during("vkEnumerateInstanceVersion")?
                    .unwrap_or(vk::API_VERSION_1_0),
                entry
                    .enumerate_instance_layer_properties()
                    .during("vkEnumerateInstanceLayerProperties")?,
                entry
                    .enumerate_instance_extension_properties(None)
                    .during("vkEnumerateInstanceExtensionProperties")?,
            )
        };
        if loader_version < vk::API_VERSION_1_2 {
            return Err(GpuError::NoDevice(format!(
                "the Vulkan loader is version {}, the engine needs 1.2",
                version_string(loader_version)
            )));
        }
        let has_layer = layers
            .iter()
            .any(|l| c_name(&l.layer_name) == VALIDATION_LAYER.to_string_lossy());
        let validation = match desc.validation {
            Validation::Off => false,
            Validation::IfAvailable => has_layer,
            Validation::Required if has_layer => true,
            Validation::Required => return Err(GpuError::ValidationUnavailable),
        };
        let has_debug_utils = inst_exts
            .iter()
            .any(|e| c_name(&e.extension_name) == ash::ext::debug_utils::NAME.to_string_lossy());
        let api = vk::API_VERSION_1_3.min(loader_version);
        let app_name = c"extranerf";
        let app = vk::ApplicationInfo::default()
            .application_name(app_name)
            .engine_name(app_name)
            .api_version(api);
        let layer_ptrs: Vec<*const std::ffi::c_char> = if validation {
            vec![VALIDATION_LAYER.as_ptr()]
        } else {
            vec![]
        };
        #[cfg_attr(not(feature = "wgpu"), allow(unused_mut))] // extended only for wgpu sharing
        let mut instance_exts: Vec<&'static CStr> = if has_debug_utils {
            vec![ash::ext::debug_utils::NAME]
        } else {
            vec![]
        };
        if desc.share_with_wgpu {
            #[cfg(feature = "wgpu")]
            for e in crate::wgpu_share::instance_extensions(&entry, api)? {
                if !instance_exts.contains(&e) {
                    instance_exts.push(e);
                }
            }
            #[cfg(not(feature = "wgpu"))]
            return Err(GpuError::Usage(
                "sharing the device with wgpu needs extranerf-gpu's `wgpu` feature".into(),
            ));
        }
        let ext_ptrs: Vec<*const std::ffi::c_char> =
            instance_exts.iter().map(|e| e.as_ptr()).collect();
        let log = Arc::<ValidationLog>::default();
        let mut messenger_ci = vk::DebugUtilsMessengerCreateInfoEXT::default()
            .message_severity(
                vk::DebugUtilsMessageSeverityFlagsEXT::WARNING
                    | vk::DebugUtilsMessageSeverityFlagsEXT::ERROR,
            )
            .message_type(
                vk::DebugUtilsMessageTypeFlagsEXT::GENERAL
                    | vk::DebugUtilsMessageTypeFlagsEXT::VALIDATION
                    | vk::DebugUtilsMessageTypeFlagsEXT::PERFORMANCE,
            )
            .pfn_user_callback(Some(debug_callback))
            .user_data(Arc::as_ptr(&log) as *mut c_void);
        let mut ci = vk::InstanceCreateInfo::default()
            .application_info(&app)
            .enabled_layer_names(&layer_ptrs)
            .enabled_extension_names(&ext_ptrs);
        if has_debug_utils && validation {
            // Also catch messages from instance creation itself.
            ci = ci.push_next(&mut messenger_ci);
        }
        // SAFETY: every pointer in `ci` refers to locals that outlive the call; the log box
        // outlives the messenger (see `Inner::drop`).
        let instance = unsafe { entry.create_instance(&ci, None) }.during("vkCreateInstance")?;
        let mut guard = InstanceGuard {
            instance: Some(instance),
            debug: None,
            messenger: vk::DebugUtilsMessengerEXT::null(),
        };
        let instance_ref = guard.instance.as_ref().expect("set above");
        if has_debug_utils {
            let dbg = ash::ext::debug_utils::Instance::new(&entry, instance_ref);
            if validation {
                // SAFETY: valid instance, create info as above.
                guard.messenger = unsafe { dbg.create_debug_utils_messenger(&messenger_ci, None) }
                    .during("vkCreateDebugUtilsMessengerEXT")?;
            }
            guard.debug = Some(dbg);
        }

        let requested = desc
            .device
            .clone()
            .or_else(|| std::env::var("EXTRANERF_DEVICE").ok())
            .filter(|s| !s.trim().is_empty());
        let (index, physical) = select_device(instance_ref, requested.as_deref())?;
        let (mut info, mut features) =
            probe_device(&entry, instance_ref, index, physical, api, validation)?;
        // The device wgpu adopts gets wgpu-hal's feature chain, which enables cooperative
        // matrices and the memory model they need only for wgpu's experimental feature: left off.
        if desc.no_coop_matrix || desc.share_with_wgpu {
            features.coop_matrix = false;
            info.coop_matrix.clear();
        }
        if let Some(limit) = desc.max_binding_bytes {
            // A smaller binding limit than the device's: the split and ranged paths run on any
            // device (tests, or reproducing a smaller device's behaviour).
            info.max_storage_buffer_range = info.max_storage_buffer_range.min(limit.max(256));
        }

        // Queue: the first family with compute.
        // SAFETY: valid physical device.
        let families =
            unsafe { instance_ref.get_physical_device_queue_family_properties(physical) };
        let family = families
            .iter()
            .position(|f| f.queue_flags.contains(vk::QueueFlags::COMPUTE))
            .ok_or_else(|| GpuError::NoDevice(format!("{} has no compute queue", info.name)))?
            as u32;
        // SAFETY: valid physical device.
        let dev_exts = unsafe { instance_ref.enumerate_device_extension_properties(physical) }
            .during("vkEnumerateDeviceExtensionProperties")?;
        let has_ext = |n: &CStr| {
            dev_exts
                .iter()
                .any(|e| c_name(&e.extension_name) == n.to_string_lossy())
        };
        if !has_ext(ash::khr::push_descriptor::NAME) {
            return Err(GpuError::MissingFeature {
                device: info.name.clone(),
                what: "VK_KHR_push_descriptor".into(),
                needed_by: "kernel binding".into(),
            });
        }
        let mut ext_names = vec![ash::khr::push_descriptor::NAME.as_ptr()];
        if features.atomic_float {
            ext_names.push(ash::ext::shader_atomic_float::NAME.as_ptr());
        }
        if features.coop_matrix {
            ext_names.push(ash::khr::cooperative_matrix::NAME.as_ptr());
        }
        #[cfg(feature = "wgpu")]
        let mut share = if desc.share_with_wgpu {
            let sh = crate::wgpu_share::Share::new(
                &entry,
                instance_ref,
                api,
                instance_exts.clone(),
                physical,
                info.shader_float16 && info.storage_buffer_16bit,
                features.atomic_float,
            )?;
            ext_names = sh.extensions.iter().map(|e| e.as_ptr()).collect();
            Some(sh)
        } else {
            None
        };
        let priorities = [1.0f32];
        let queue_ci = [vk::DeviceQueueCreateInfo::default()
            .queue_family_index(family)
            .queue_priorities(&priorities)];
        let mut f11 = vk::PhysicalDeviceVulkan11Features::default()
            .storage_buffer16_bit_access(info.storage_buffer_16bit)
            .uniform_and_storage_buffer16_bit_access(info.storage_buffer_16bit);
        let mut f12 = vk::PhysicalDeviceVulkan12Features::default()
            .timeline_semaphore(true)
            .shader_float16(info.shader_float16)
            .vulkan_memory_model(features.coop_matrix)
            .vulkan_memory_model_device_scope(features.coop_matrix);
        let mut fatomic = vk::PhysicalDeviceShaderAtomicFloatFeaturesEXT::default()
            .shader_buffer_float32_atomic_add(true)
            .shader_buffer_float32_atomics(true);
        let mut fcoop =
            vk::PhysicalDeviceCooperativeMatrixFeaturesKHR::default().cooperative_matrix(true);
        let mut dci = vk::DeviceCreateInfo::default()
            .queue_create_infos(&queue_ci)
            .enabled_extension_names(&ext_names);
        #[cfg(feature = "wgpu")]
        let shared = share.is_some();
        #[cfg(not(feature = "wgpu"))]
        let shared = false;
        if shared {
            // wgpu-hal's feature chain covers the engine's needs (see wgpu_share).
            #[cfg(feature = "wgpu")]
            if let Some(sh) = share.as_mut() {
                dci = sh.chain.add_to_device_create(dci);
            }
        } else {
            dci = dci.push_next(&mut f11).push_next(&mut f12);
            if features.atomic_float {
                dci = dci.push_next(&mut fatomic);
            }
        }
        if features.coop_matrix {
            dci = dci.push_next(&mut fcoop);
        }
        // SAFETY: all pointers in `dci` refer to locals alive across the call; features enabled
        // were reported as supported by `probe_device`.
        let device =
            unsafe { instance_ref.create_device(physical, &dci, None) }.during("vkCreateDevice")?;
        // From here on the device must be destroyed on error: build Inner right away.
        let push_descriptor = ash::khr::push_descriptor::Device::new(instance_ref, &device);
        let debug_device =
            has_debug_utils.then(|| ash::ext::debug_utils::Device::new(instance_ref, &device));
        // SAFETY: family index was used to create the device with one queue.
        let queue = unsafe { device.get_device_queue(family, 0) };
        let allocator = Allocator::new(&AllocatorCreateDesc {
            instance: instance_ref.clone(),
            device: device.clone(),
            physical_device: physical,
            debug_settings: {
                let mut d = gpu_allocator::AllocatorDebugSettings::default();
                d.log_leaks_on_shutdown = true;
                d
            },
            buffer_device_address: false,
            allocation_sizes: Default::default(),
        });
        let mut type_ci = vk::SemaphoreTypeCreateInfo::default()
            .semaphore_type(vk::SemaphoreType::TIMELINE)
            .initial_value(0);
        let sem_ci = vk::SemaphoreCreateInfo::default().push_next(&mut type_ci);
        // SAFETY: valid device; on failure the device is destroyed here, on success the
        // semaphore is owned by Inner, which destroys it in Drop.
        let created = unsafe {
            match (allocator, device.create_semaphore(&sem_ci, None)) {
                (Ok(a), Ok(t)) => Ok((t, a)),
                (a, t) => {
                    let err = match (&a, &t) {
                        (Err(e), _) => GpuError::Allocation {
                            name: "allocator".into(),
                            message: e.to_string(),
                        },
                        (_, Err(r)) => crate::error::vk_err("vkCreateSemaphore", *r),
                        _ => GpuError::Usage("device set-up failed".into()),
                    };
                    drop(a);
                    if let Ok(t) = t {
                        device.destroy_semaphore(t, None);
                    }
                    device.destroy_device(None);
                    Err(err)
                }
            }
        };
        let (timeline, allocator) = created?;
        #[cfg(feature = "wgpu")]
        let wgpu = match share {
            Some(sh) => match sh.adopt(&device, family) {
                Ok(h) => Some(h),
                Err(e) => {
                    // SAFETY: nothing else uses the device yet.
                    unsafe {
                        drop(allocator);
                        device.destroy_semaphore(timeline, None);
                        device.destroy_device(None);
                    }
                    return Err(e);
                }
            },
            None => None,
        };
        let (instance, debug_instance, messenger) = guard.take();
        let inner = Inner {
            _entry: entry,
            instance,
            debug_instance,
            messenger,
            log,
            device,
            debug_device,
            push_descriptor,
            queue: Mutex::new(queue),
            queue_family: family,
            timeline,
            last_submitted: AtomicU64::new(0),
            allocator: Mutex::new(Some(allocator)),
            garbage: Mutex::new(Vec::new()),
            info,
            max_memory: desc.max_memory_bytes,
            shared,
            #[cfg(feature = "wgpu")]
            wgpu,
        };
        let ctx = Context {
            inner: Arc::new(inner),
        };
        ctx.name(timeline, "extranerf timeline");
        ctx.name(queue, "extranerf compute queue");
        Ok(ctx)
    }

    /// The raw VkDevice handle as an integer (to check that another API drives the same
    /// device).
    pub fn raw_device(&self) -> u64 {
        vk::Handle::as_raw(self.inner.device.handle())
    }

    /// The device as wgpu objects, when created with [`ContextDesc::share_with_wgpu`].
    #[cfg(feature = "wgpu")]
    pub fn wgpu(&self) -> Option<&crate::wgpu_share::WgpuHandles> {
        self.inner.wgpu.as_ref()
    }

    /// What the engine knows about its device.
    pub fn info(&self) -> &DeviceInfo {
        &self.inner.info
    }

    /// Validation messages (warnings and errors) so far, and clears the log.
    pub fn take_validation_messages(&self) -> Vec<ValidationMessage> {
        self.validation_log().take()
    }

    /// A handle on the validation log that stays valid after the context is dropped.
    pub fn validation_log(&self) -> ValidationLogHandle {
        ValidationLogHandle(self.inner.log.clone())
    }

    /// Sends a message through the debug messenger as the validation layer would (tests use it
    /// to show that messages reach the log). Returns false when no messenger exists. Always
    /// built, not behind a feature: a test-only feature would make the tests build every engine
    /// crate a second time instead of sharing the release binary's build (docs/testing.md).
    pub fn inject_debug_message(&self, text: &str) -> bool {
        let Some(dbg) = &self.inner.debug_instance else {
            return false;
        };
        if self.inner.messenger == vk::DebugUtilsMessengerEXT::null() {
            return false;
        }
        let Ok(c) = CString::new(text.replace('\0', " ")) else {
            return false;
        };
        let data = vk::DebugUtilsMessengerCallbackDataEXT::default()
            .message(&c)
            .message_id_name(c"extranerf-test");
        // SAFETY: valid instance-level debug utils; `data` outlives the synchronous call.
        unsafe {
            dbg.submit_debug_utils_message(
                vk::DebugUtilsMessageSeverityFlagsEXT::ERROR,
                vk::DebugUtilsMessageTypeFlagsEXT::VALIDATION,
                &data,
            )
        };
        true
    }

    /// Number of live allocations (frees anything the GPU is done with first).
    pub fn live_allocations(&self) -> Result<usize> {
        self.collect_garbage()?;
        Ok(self
            .allocator()?
            .as_ref()
            .map(|a| a.generate_report().allocations.len())
            .unwrap_or(0))
    }

    /// Bytes in live allocations and bytes of device memory blocks the allocator holds (frees
    /// anything the GPU is done with first).
    pub fn allocated_bytes(&self) -> Result<(u64, u64)> {
        self.collect_garbage()?;
        Ok(self
            .allocator()?
            .as_ref()
            .map(|a| {
                let r = a.generate_report();
                (r.total_allocated_bytes, r.total_capacity_bytes)
            })
            .unwrap_or((0, 0)))
    }

    /// Blocks until all submitted work has finished and frees what waited on it.
    pub fn wait_idle(&self) -> Result<()> {
        self.wait(Ticket(self.inner.last_submitted.load(Ordering::Acquire)))
    }

    pub(crate) fn allocator(&self) -> Result<MutexGuard<'_, Option<Allocator>>> {
        self.inner
            .allocator
            .lock()
            .map_err(|_| GpuError::Usage("allocator mutex poisoned by an earlier panic".into()))
    }

    pub(crate) fn lock_queue(&self) -> Result<MutexGuard<'_, vk::Queue>> {
        self.inner
            .queue
            .lock()
            .map_err(|_| GpuError::Usage("queue mutex poisoned by an earlier panic".into()))
    }

    /// Identity of the device, to refuse resources of another context.
    pub(crate) fn id(&self) -> usize {
        Arc::as_ptr(&self.inner) as usize
    }

    pub(crate) fn inner_last_submitted(&self) -> u64 {
        self.inner.last_submitted.load(Ordering::Acquire)
    }

    pub(crate) fn next_submission_value(&self) -> u64 {
        self.inner.last_submitted.fetch_add(1, Ordering::AcqRel) + 1
    }

    /// The highest timeline value the GPU has finished.
    pub(crate) fn completed_value(&self) -> Result<u64> {
        // SAFETY: the semaphore is a timeline semaphore owned by this device.
        unsafe {
            self.inner
                .device
                .get_semaphore_counter_value(self.inner.timeline)
        }
        .during("vkGetSemaphoreCounterValue")
    }

    /// Labels a Vulkan object for validation messages and debuggers (no-op without debug utils).
    pub(crate) fn name<H: vk::Handle>(&self, handle: H, name: &str) {
        let Some(dbg) = &self.inner.debug_device else {
            return;
        };
        let Ok(cname) = CString::new(name.replace('\0', " ")) else {
            return;
        };
        let info = vk::DebugUtilsObjectNameInfoEXT::default()
            .object_handle(handle)
            .object_name(&cname);
        // SAFETY: `handle` is a live object of this device; naming has no other effect. A
        // failure only loses the label, so it is ignored.
        let _ = unsafe { dbg.set_debug_utils_object_name(&info) };
    }

    /// Queues `g` for destruction once the GPU has passed timeline value `last_use`.
    pub(crate) fn release(&self, last_use: u64, g: Garbage) {
        let done = self
            .completed_value()
            .map(|c| c >= last_use)
            .unwrap_or(false);
        if done {
            self.destroy(g);
        } else if let Ok(mut q) = self.inner.garbage.lock() {
            q.push((last_use, g));
        }
    }

    /// Frees everything whose last use the GPU has passed.
    pub(crate) fn collect_garbage(&self) -> Result<()> {
        let completed = self.completed_value()?;
        let ready: Vec<Garbage> = {
            let mut q = self
                .inner
                .garbage
                .lock()
                .map_err(|_| GpuError::Usage("release queue poisoned".into()))?;
            let (ready, keep): (Vec<_>, Vec<_>) = std::mem::take(&mut *q)
                .into_iter()
                .partition(|(v, _)| *v <= completed);
            *q = keep;
            ready.into_iter().map(|(_, g)| g).collect()
        };
        for g in ready {
            self.destroy(g);
        }
        Ok(())
    }

    fn destroy(&self, g: Garbage) {
        destroy_garbage(&self.inner.device, &self.inner.allocator, g);
    }
}

fn destroy_garbage(device: &ash::Device, allocator: &Mutex<Option<Allocator>>, g: Garbage) {
    // SAFETY: garbage is only destroyed once the timeline shows the GPU finished its last use
    // (or the device is idle during teardown), and each handle is owned by exactly one entry.
    unsafe {
        match g {
            Garbage::Buffer(buffer, allocation) => {
                if let Ok(mut a) = allocator.lock() {
                    if let Some(a) = a.as_mut() {
                        if let Err(e) = a.free(allocation) {
                            tracing::error!("freeing buffer memory: {e}");
                        }
                    }
                }
                device.destroy_buffer(buffer, None);
            }
            Garbage::Pipeline {
                pipeline,
                layout,
                set_layout,
                module,
            } => {
                device.destroy_pipeline(pipeline, None);
                device.destroy_pipeline_layout(layout, None);
                device.destroy_descriptor_set_layout(set_layout, None);
                device.destroy_shader_module(module, None);
            }
            Garbage::QueryPool(p) => device.destroy_query_pool(p, None),
            Garbage::CommandPool(pool) => device.destroy_command_pool(pool, None),
        }
    }
}

impl Drop for Inner {
    fn drop(&mut self) {
        // Teardown order: wait idle -> drain the release queue -> allocator -> device -> instance.
        // SAFETY: every resource holds an Arc to Inner, so none is alive any more; after
        // device_wait_idle nothing is in flight, so everything can be destroyed in order.
        unsafe {
            let _ = self.device.device_wait_idle();
            let garbage = self
                .garbage
                .lock()
                .map(|mut g| std::mem::take(&mut *g))
                .unwrap_or_default();
            for (_, g) in garbage {
                destroy_garbage(&self.device, &self.allocator, g);
            }
            if let Ok(mut a) = self.allocator.lock() {
                drop(a.take());
            }
            self.device.destroy_semaphore(self.timeline, None);
            if self.shared {
                // wgpu users (burn's global runtime) may still hold objects on this device:
                // leave the device, instance, messenger and its log to the process exit.
                std::mem::forget(self.log.clone());
                return;
            }
            self.device.destroy_device(None);
            if let Some(dbg) = &self.debug_instance {
                if self.messenger != vk::DebugUtilsMessengerEXT::null() {
                    dbg.destroy_debug_utils_messenger(self.messenger, None);
                }
            }
            self.instance.destroy_instance(None);
        }
        // `log` (an Arc) is dropped after this, when the messenger no longer exists.
    }
}

/// Destroys the instance (and messenger) if device creation fails part-way.
struct InstanceGuard {
    instance: Option<ash::Instance>,
    debug: Option<ash::ext::debug_utils::Instance>,
    messenger: vk::DebugUtilsMessengerEXT,
}

impl InstanceGuard {
    fn take(
        &mut self,
    ) -> (
        ash::Instance,
        Option<ash::ext::debug_utils::Instance>,
        vk::DebugUtilsMessengerEXT,
    ) {
        let messenger = std::mem::replace(&mut self.messenger, vk::DebugUtilsMessengerEXT::null());
        (
            self.instance.take().expect("taken once"),
            self.debug.take(),
            messenger,
        )
    }
}

impl Drop for InstanceGuard {
    fn drop(&mut self) {
        if let Some(instance) = self.instance.take() {
            // SAFETY: nothing made from this instance survives a failed Context::new.
            unsafe {
                if let Some(dbg) = &self.debug {
                    if self.messenger != vk::DebugUtilsMessengerEXT::null() {
                        dbg.destroy_debug_utils_messenger(self.messenger, None);
                    }
                }
                instance.destroy_instance(None);
            }
        }
    }
}

fn select_device(
    instance: &ash::Instance,
    requested: Option<&str>,
) -> Result<(usize, vk::PhysicalDevice)> {
    // SAFETY: valid instance.
    let pds =
        unsafe { instance.enumerate_physical_devices() }.during("vkEnumeratePhysicalDevices")?;
    if pds.is_empty() {
        return Err(GpuError::NoDevice(
            "the Vulkan loader found no physical device (no driver installed?)".into(),
        ));
    }
    // SAFETY: handles from enumerate_physical_devices.
    let props: Vec<_> = pds
        .iter()
        .map(|&pd| unsafe { instance.get_physical_device_properties(pd) })
        .collect();
    let listing = || {
        props
            .iter()
            .enumerate()
            .map(|(i, p)| {
                format!(
                    "{i}: {} ({})",
                    c_name(&p.device_name),
                    device_type_name(p.device_type)
                )
            })
            .collect::<Vec<_>>()
            .join(", ")
    };
    if let Some(req) = requested {
        let req_t = req.trim();
        let found = match req_t.parse::<usize>() {
            Ok(i) => (i < pds.len()).then_some(i),
            Err(_) => props.iter().position(|p| {
                c_name(&p.device_name)
                    .to_lowercase()
                    .contains(&req_t.to_lowercase())
            }),
        };
        return match found {
            Some(i) if props[i].api_version >= vk::API_VERSION_1_2 => Ok((i, pds[i])),
            Some(i) => Err(GpuError::MissingFeature {
                device: c_name(&props[i].device_name),
                what: format!(
                    "Vulkan 1.2 (it has {})",
                    version_string(props[i].api_version)
                ),
                needed_by: "the engine".into(),
            }),
            None => Err(GpuError::DeviceNotFound {
                requested: req_t.to_string(),
                available: listing(),
            }),
        };
    }
    let best = props
        .iter()
        .enumerate()
        .filter(|(_, p)| p.api_version >= vk::API_VERSION_1_2)
        .min_by_key(|(i, p)| (type_rank(p.device_type), *i))
        .map(|(i, _)| i)
        .ok_or_else(|| {
            GpuError::NoDevice(format!(
                "no device supports Vulkan 1.2; found {}",
                listing()
            ))
        })?;
    Ok((best, pds[best]))
}

struct Features {
    atomic_float: bool,
    coop_matrix: bool,
}

fn component_name(t: vk::ComponentTypeKHR) -> String {
    match t {
        vk::ComponentTypeKHR::FLOAT16 => "f16".into(),
        vk::ComponentTypeKHR::FLOAT32 => "f32".into(),
        vk::ComponentTypeKHR::FLOAT64 => "f64".into(),
        vk::ComponentTypeKHR::SINT8 => "i8".into(),
        vk::ComponentTypeKHR::SINT16 => "i16".into(),
        vk::ComponentTypeKHR::SINT32 => "i32".into(),
        vk::ComponentTypeKHR::SINT64 => "i64".into(),
        vk::ComponentTypeKHR::UINT8 => "u8".into(),
        vk::ComponentTypeKHR::UINT16 => "u16".into(),
        vk::ComponentTypeKHR::UINT32 => "u32".into(),
        vk::ComponentTypeKHR::UINT64 => "u64".into(),
        // BFLOAT16_KHR (VK_KHR_shader_bfloat16) and the float8 types postdate ash 0.38.
        other if other.as_raw() == 1_000_141_000 => "bf16".into(),
        other => format!("type{}", other.as_raw()),
    }
}

fn scope_name(s: vk::ScopeKHR) -> String {
    match s {
        vk::ScopeKHR::DEVICE => "device".into(),
        vk::ScopeKHR::WORKGROUP => "workgroup".into(),
        vk::ScopeKHR::SUBGROUP => "subgroup".into(),
        vk::ScopeKHR::QUEUE_FAMILY => "queue family".into(),
        other => format!("scope{}", other.as_raw()),
    }
}

fn probe_device(
    entry: &ash::Entry,
    instance: &ash::Instance,
    index: usize,
    pd: vk::PhysicalDevice,
    api: u32,
    validation: bool,
) -> Result<(DeviceInfo, Features)> {
    let mut driver = vk::PhysicalDeviceDriverProperties::default();
    let mut subgroup = vk::PhysicalDeviceSubgroupProperties::default();
    let mut maint3 = vk::PhysicalDeviceMaintenance3Properties::default();
    let mut props2 = vk::PhysicalDeviceProperties2::default()
        .push_next(&mut driver)
        .push_next(&mut subgroup)
        .push_next(&mut maint3);
    let mut f11 = vk::PhysicalDeviceVulkan11Features::default();
    let mut f12 = vk::PhysicalDeviceVulkan12Features::default();
    let mut fatomic = vk::PhysicalDeviceShaderAtomicFloatFeaturesEXT::default();
    let mut fcoop = vk::PhysicalDeviceCooperativeMatrixFeaturesKHR::default();
    // SAFETY: valid physical device; the chained structs live across the calls.
    // An extension's feature struct is chained only when the device has the extension, so it
    // stays all-false (its Default) otherwise: its flags alone say what is usable.
    let (mem, families) = unsafe {
        instance.get_physical_device_properties2(pd, &mut props2);
        let exts = instance
            .enumerate_device_extension_properties(pd)
            .during("vkEnumerateDeviceExtensionProperties")?;
        let has = |n: &CStr| {
            exts.iter()
                .any(|e| c_name(&e.extension_name) == n.to_string_lossy())
        };
        let mut f2 = vk::PhysicalDeviceFeatures2::default()
            .push_next(&mut f11)
            .push_next(&mut f12);
        if has(ash::ext::shader_atomic_float::NAME) {
            f2 = f2.push_next(&mut fatomic);
        }
        if has(ash::khr::cooperative_matrix::NAME) {
            f2 = f2.push_next(&mut fcoop);
        }
        instance.get_physical_device_features2(pd, &mut f2);
        (
            instance.get_physical_device_memory_properties(pd),
            instance.get_physical_device_queue_family_properties(pd),
        )
    };
    let p = props2.properties;
    let name = c_name(&p.device_name);
    if f12.timeline_semaphore == vk::FALSE {
        return Err(GpuError::MissingFeature {
            device: name,
            what: "timelineSemaphore".into(),
            needed_by: "GPU/host synchronisation".into(),
        });
    }
    let ops = vk::SubgroupFeatureFlags::BASIC
        | vk::SubgroupFeatureFlags::ARITHMETIC
        | vk::SubgroupFeatureFlags::BALLOT;
    let timestamps = families
        .iter()
        .find(|f| f.queue_flags.contains(vk::QueueFlags::COMPUTE))
        .map(|f| f.timestamp_valid_bits > 0)
        .unwrap_or(false);
    let heaps = mem.memory_heaps[..mem.memory_heap_count as usize]
        .iter()
        .map(|h| HeapInfo {
            size: h.size,
            device_local: h.flags.contains(vk::MemoryHeapFlags::DEVICE_LOCAL),
        })
        .collect();
    let atomic_float = fatomic.shader_buffer_float32_atomic_add == vk::TRUE;
    // naga writes cooperative-matrix kernels in the Vulkan memory model, with device-scope
    // atomics.
    let coop_matrix = fcoop.cooperative_matrix == vk::TRUE
        && f12.vulkan_memory_model == vk::TRUE
        && f12.vulkan_memory_model_device_scope == vk::TRUE;
    let coop_shapes = if coop_matrix {
        let coop = ash::khr::cooperative_matrix::Instance::new(entry, instance);
        // SAFETY: valid physical device that offers VK_KHR_cooperative_matrix; the function
        // pointer was loaded from this instance.
        unsafe { coop.get_physical_device_cooperative_matrix_properties(pd) }
            .during("vkGetPhysicalDeviceCooperativeMatrixPropertiesKHR")?
            .iter()
            .map(|p| CoopMatrixShape {
                m: p.m_size,
                n: p.n_size,
                k: p.k_size,
                types: [p.a_type, p.b_type, p.c_type, p.result_type].map(component_name),
                scope: scope_name(p.scope),
            })
            .collect()
    } else {
        Vec::new()
    };
    let info = DeviceInfo {
        index,
        name,
        device_type: device_type_name(p.device_type).into(),
        driver_name: c_name(&driver.driver_name),
        driver_info: c_name(&driver.driver_info),
        api_version: version_string(p.api_version),
        used_api_version: version_string(api.min(p.api_version)),
        vendor_id: p.vendor_id,
        heaps,
        subgroup_size: subgroup.subgroup_size,
        subgroup_arithmetic: subgroup
            .supported_stages
            .contains(vk::ShaderStageFlags::COMPUTE)
            && subgroup.supported_operations.contains(ops),
        max_storage_buffer_range: p.limits.max_storage_buffer_range as u64,
        max_buffer_bytes: maint3
            .max_memory_allocation_size
            .max(p.limits.max_storage_buffer_range as u64),
        min_storage_buffer_offset_alignment: p.limits.min_storage_buffer_offset_alignment,
        max_uniform_buffer_range: p.limits.max_uniform_buffer_range as u64,
        min_uniform_buffer_offset_alignment: p.limits.min_uniform_buffer_offset_alignment,
        max_workgroup_count_x: p.limits.max_compute_work_group_count[0],
        max_workgroup_count_y: p.limits.max_compute_work_group_count[1],
        max_shared_memory: p.limits.max_compute_shared_memory_size,
        timestamp_period_ns: p.limits.timestamp_period,
        timestamps,
        float32_atomic_add: atomic_float,
        shader_float16: f12.shader_float16 == vk::TRUE,
        // naga's f16 storage declares UniformAndStorageBuffer16BitAccess: both are needed.
        storage_buffer_16bit: f11.storage_buffer16_bit_access == vk::TRUE
            && f11.uniform_and_storage_buffer16_bit_access == vk::TRUE,
        validation,
        coop_matrix: coop_shapes,
    };
    Ok((
        info,
        Features {
            atomic_float,
            coop_matrix,
        },
    ))
}
