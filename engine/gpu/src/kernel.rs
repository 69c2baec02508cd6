//! Compute pipelines built from the generated SPIR-V, bound through push descriptors.

use ash::vk;
use extranerf_kernels::KernelDesc;

use crate::context::{Context, Garbage};
use crate::error::{GpuError, Result, VkContext};

/// A compute pipeline for one kernel entry point.
pub struct Kernel {
    pub(crate) ctx: Context,
    pub(crate) desc: &'static KernelDesc,
    pub(crate) pipeline: vk::Pipeline,
    pub(crate) layout: vk::PipelineLayout,
    set_layout: vk::DescriptorSetLayout,
    module: vk::ShaderModule,
}

impl std::fmt::Debug for Kernel {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Kernel")
            .field("name", &self.desc.name)
            .finish_non_exhaustive()
    }
}

impl Kernel {
    /// Builds the pipeline; fails with [`GpuError::MissingFeature`] when the kernel needs what
    /// the device lacks.
    pub fn new(ctx: &Context, desc: &'static KernelDesc) -> Result<Kernel> {
        let info = ctx.info();
        let missing = |what: &str| GpuError::MissingFeature {
            device: info.name.clone(),
            what: what.into(),
            needed_by: format!("kernel `{}`", desc.name),
        };
        if desc.needs_float32_atomic_add && !info.float32_atomic_add {
            return Err(missing(
                "shaderBufferFloat32AtomicAdd (VK_EXT_shader_atomic_float)",
            ));
        }
        if desc.needs_f16 && !(info.shader_float16 && info.storage_buffer_16bit) {
            return Err(missing(
                "shaderFloat16 and storageBuffer16BitAccess (the f16 path)",
            ));
        }
        if desc.coop_tile != 0 && !info.offers_coop_tile(desc.coop_tile) {
            return Err(missing(match desc.coop_tile {
                8 => "VK_KHR_cooperative_matrix with 8x8x8 f16*f16+f32 subgroup tiles",
                _ => "VK_KHR_cooperative_matrix with 16x16x16 f16*f16+f32 subgroup tiles",
            }));
        }
        if desc.needs_subgroups && !info.subgroup_arithmetic {
            return Err(missing(
                "subgroup basic/arithmetic/ballot operations in compute shaders",
            ));
        }
        if desc.params_size > 128 {
            return Err(GpuError::KernelMismatch {
                kernel: desc.name,
                problem: format!(
                    "{} bytes of parameters exceed the 128 guaranteed push-constant bytes",
                    desc.params_size
                ),
            });
        }
        for b in desc.bindings {
            if b.uniform_bytes as u64 > info.max_uniform_buffer_range {
                return Err(GpuError::KernelMismatch {
                    kernel: desc.name,
                    problem: format!(
                        "uniform block `{}` has {} bytes; the device allows {}",
                        b.name, b.uniform_bytes, info.max_uniform_buffer_range
                    ),
                });
            }
        }
        let device = &ctx.inner.device;
        let bindings: Vec<_> = desc
            .bindings
            .iter()
            .map(|b| {
                vk::DescriptorSetLayoutBinding::default()
                    .binding(b.binding)
                    .descriptor_type(descriptor_type(b))
                    .descriptor_count(1)
                    .stage_flags(vk::ShaderStageFlags::COMPUTE)
            })
            .collect();
        let set_ci = vk::DescriptorSetLayoutCreateInfo::default()
            .flags(vk::DescriptorSetLayoutCreateFlags::PUSH_DESCRIPTOR_KHR)
            .bindings(&bindings);
        let ranges = [vk::PushConstantRange::default()
            .stage_flags(vk::ShaderStageFlags::COMPUTE)
            .offset(0)
            .size(desc.params_size)];
        let module_ci = vk::ShaderModuleCreateInfo::default().code(desc.spirv);
        let entry = std::ffi::CString::new(desc.entry).map_err(|_| GpuError::KernelMismatch {
            kernel: desc.name,
            problem: "entry name has a NUL".into(),
        })?;
        // SAFETY: valid device; create infos point at locals alive across the calls; on failure
        // every object created so far is destroyed before returning.
        unsafe {
            let module = device
                .create_shader_module(&module_ci, None)
                .during("vkCreateShaderModule")?;
            let set_layout = match device.create_descriptor_set_layout(&set_ci, None) {
                Ok(l) => l,
                Err(r) => {
                    device.destroy_shader_module(module, None);
                    return Err(crate::error::vk_err("vkCreateDescriptorSetLayout", r));
                }
            };
            let set_layouts = [set_layout];
            let mut layout_ci = vk::PipelineLayoutCreateInfo::default().set_layouts(&set_layouts);
            if desc.params_size > 0 {
                layout_ci = layout_ci.push_constant_ranges(&ranges);
            }
            let layout = match device.create_pipeline_layout(&layout_ci, None) {
                Ok(l) => l,
                Err(r) => {
                    device.destroy_descriptor_set_layout(set_layout, None);
                    device.destroy_shader_module(module, None);
                    return Err(crate::error::vk_err("vkCreatePipelineLayout", r));
                }
            };
            let stage = vk::PipelineShaderStageCreateInfo::default()
                .stage(vk::ShaderStageFlags::COMPUTE)
                .module(module)
                .name(&entry);
            let pci = [vk::ComputePipelineCreateInfo::default()
                .stage(stage)
                .layout(layout)];
            let pipeline =
                match device.create_compute_pipelines(vk::PipelineCache::null(), &pci, None) {
                    Ok(p) => p[0],
                    Err((_, r)) => {
                        device.destroy_pipeline_layout(layout, None);
                        device.destroy_descriptor_set_layout(set_layout, None);
                        device.destroy_shader_module(module, None);
                        return Err(crate::error::vk_err("vkCreateComputePipelines", r));
                    }
                };
            ctx.name(module, desc.name);
            ctx.name(set_layout, desc.name);
            ctx.name(layout, desc.name);
            ctx.name(pipeline, desc.name);
            Ok(Kernel {
                ctx: ctx.clone(),
                desc,
                pipeline,
                layout,
                set_layout,
                module,
            })
        }
    }

    /// The reflected description.
    pub fn desc(&self) -> &'static KernelDesc {
        self.desc
    }
}

impl Drop for Kernel {
    fn drop(&mut self) {
        // Pipelines are only referenced by command buffers; the last submission is at most the
        // context's latest, so waiting for that one is always safe.
        let last = self.ctx.inner_last_submitted();
        self.ctx.release(
            last,
            Garbage::Pipeline {
                pipeline: self.pipeline,
                layout: self.layout,
                set_layout: self.set_layout,
                module: self.module,
            },
        );
    }
}

/// The descriptor type of a reflected binding.
pub(crate) fn descriptor_type(b: &extranerf_kernels::BindingDesc) -> vk::DescriptorType {
    if b.uniform_bytes > 0 {
        vk::DescriptorType::UNIFORM_BUFFER
    } else {
        vk::DescriptorType::STORAGE_BUFFER
    }
}
