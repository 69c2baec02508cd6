//! The Vulkan layer: device, errors, buffers, kernels, recorder, timers, layouts, leaks.

#![allow(clippy::unwrap_used)] // tests: a failed unwrap is a failed test, with the error in the message

use extranerf_gpu::kernels::{self, prims as k};
use extranerf_gpu::{
    fold_groups, Buffer, Context, ContextDesc, GpuError, GpuTimer, Kernel, Validation,
};
use extranerf_tests::{assert_no_validation_messages, desc, engine, POISON};

#[test]
fn device_info_is_sane() {
    let e = engine();
    let info = e.ctx.info();
    assert!(!info.name.is_empty());
    assert!(
        info.subgroup_size >= 4,
        "subgroup size {}",
        info.subgroup_size
    );
    assert!(
        info.max_storage_buffer_range >= 1 << 27,
        "maxStorageBufferRange {}",
        info.max_storage_buffer_range
    );
    assert!(info.max_workgroup_count_x >= 65535);
    assert!(!info.heaps.is_empty());
    assert!(
        info.subgroup_arithmetic && info.float32_atomic_add,
        "the primitives need subgroups and f32 atomics: {info:?}"
    );
    // The layer is on unless EXTRANERF_VALIDATION opted out (tests/support.rs).
    if extranerf_gpu::Validation::from_env(extranerf_gpu::Validation::Required)
        == extranerf_gpu::Validation::Required
    {
        assert!(info.validation);
    }
}

/// On a context of its own: on the shared one, a test in another module could take the
/// injected message from the log (and fail) before this test reads it.
#[test]
fn messenger_reaches_the_log() {
    let ctx = Context::new(&desc()).unwrap();
    if !ctx.info().validation {
        eprintln!("SKIPPED: the validation layer is off (EXTRANERF_VALIDATION opts out), so there is no messenger to check");
        return;
    }
    assert!(ctx.inject_debug_message("synthetic message from the test"));
    let msgs = ctx.take_validation_messages();
    assert!(
        msgs.iter()
            .any(|m| m.text.contains("synthetic message") && m.severity == "ERROR"),
        "{msgs:?}"
    );
    // Anything else in the log is a real message: fail rather than swallow it.
    let others: Vec<_> = msgs
        .iter()
        .filter(|m| !m.text.contains("synthetic message"))
        .collect();
    assert!(others.is_empty(), "validation messages: {others:?}");
}

#[test]
fn unknown_device_is_a_clear_error() {
    let err = Context::new(&ContextDesc {
        validation: Validation::Off,
        device: Some("no-such-gpu-xyz".into()),
        max_binding_bytes: None,
        max_memory_bytes: None,
        share_with_wgpu: false,
        no_coop_matrix: false,
    })
    .unwrap_err();
    match &err {
        GpuError::DeviceNotFound {
            requested,
            available,
        } => {
            assert_eq!(requested, "no-such-gpu-xyz");
            assert!(available.contains("0:"), "{available}");
        }
        other => panic!("expected DeviceNotFound, got {other}"),
    }
    let err = Context::new(&ContextDesc {
        validation: Validation::Off,
        device: Some("99".into()),
        max_binding_bytes: None,
        max_memory_bytes: None,
        share_with_wgpu: false,
        no_coop_matrix: false,
    })
    .unwrap_err();
    assert!(matches!(err, GpuError::DeviceNotFound { .. }), "{err}");
}

#[test]
fn device_chosen_by_index_and_name() {
    let list = extranerf_gpu::list_devices().unwrap();
    assert!(!list.is_empty());
    let first = &list[0];
    let by_index = Context::new(&ContextDesc {
        validation: Validation::Off,
        device: Some("0".into()),
        max_binding_bytes: None,
        max_memory_bytes: None,
        share_with_wgpu: false,
        no_coop_matrix: false,
    })
    .unwrap();
    assert_eq!(by_index.info().name, first.name);
    let part = first.name.split_whitespace().next().unwrap().to_uppercase();
    let by_name = Context::new(&ContextDesc {
        validation: Validation::Off,
        device: Some(part),
        max_binding_bytes: None,
        max_memory_bytes: None,
        share_with_wgpu: false,
        no_coop_matrix: false,
    })
    .unwrap();
    assert!(by_name
        .info()
        .name
        .to_uppercase()
        .contains(&first.name.split_whitespace().next().unwrap().to_uppercase()));
}

#[test]
fn buffer_limits_and_ranges_are_errors_not_panics() {
    let e = engine();
    // Beyond what the device allocates: an error naming the buffer.
    let limit = e.ctx.info().max_buffer_bytes;
    assert!(limit >= e.ctx.info().max_storage_buffer_range);
    let err = Buffer::<u32>::new(&e.ctx, "huge table", (limit / 4 + 1) as usize).unwrap_err();
    match &err {
        GpuError::BufferTooLarge { name, limit: l, .. } => {
            assert_eq!(name, "huge table");
            assert_eq!(*l, limit);
            assert!(err.to_string().contains("maxMemoryAllocationSize"));
        }
        other => panic!("expected BufferTooLarge, got {other}"),
    }
    // A buffer larger than one binding is created, bound in ranges, and refused whole, by
    // name, on a context that limits bindings to 4 KiB.
    let small = Context::new(&ContextDesc {
        max_binding_bytes: Some(4096),
        max_memory_bytes: None,
        ..desc()
    })
    .unwrap();
    let prims = extranerf_prims::Prims::new(&small).unwrap();
    let big = Buffer::<f32>::from_slice(&small, "big", &vec![1.0; 2048]).unwrap();
    let y = Buffer::<f32>::from_slice(&small, "y", &vec![0.0; 1024]).unwrap();
    let mut rec = small.recorder("ranges").unwrap();
    prims
        .saxpy(
            &mut rec,
            2.0,
            big.binding().sub(4096, 4096).unwrap(),
            y.binding(),
            1024,
        )
        .unwrap();
    let whole = prims.saxpy(&mut rec, 2.0, big.binding(), y.binding(), 1024);
    match whole {
        Err(err @ GpuError::BufferTooLarge { .. }) => {
            assert!(
                err.to_string().contains("big")
                    && err.to_string().contains("maxStorageBufferRange"),
                "{err}"
            );
        }
        other => panic!("expected BufferTooLarge, got {other:?}"),
    }
    small.run(rec).unwrap();
    assert!(y.read().unwrap().iter().all(|&v| v == 2.0));
    // Sub-ranges must start on 256 bytes and stay inside.
    assert!(big.binding().sub(100, 16).is_err());
    assert!(big.binding().sub(4096, 8192).is_err());
    assert_no_validation_messages(&small);
    let b = Buffer::<u32>::new(&e.ctx, "small", 10).unwrap();
    assert!(matches!(b.write(&[1; 11]), Err(GpuError::Usage(_))));
    assert!(matches!(b.write_at(8, &[1; 3]), Err(GpuError::Usage(_))));
    assert!(matches!(b.read_range(5, 6), Err(GpuError::Usage(_))));
    assert!(matches!(
        b.read_range(usize::MAX, 2),
        Err(GpuError::Usage(_))
    ));
    let empty = Buffer::<u32>::new(&e.ctx, "empty", 0).unwrap();
    assert!(empty.read().unwrap().is_empty());
    empty.write(&[]).unwrap();
    assert_no_validation_messages(&e.ctx);
}

#[test]
fn upload_readback_round_trip_and_ranges() {
    let e = engine();
    let data: Vec<u32> = (0..1003).map(|i| i * 7 + 1).collect();
    let b = Buffer::from_slice(&e.ctx, "round trip", &data).unwrap();
    assert_eq!(b.read().unwrap(), data);
    b.write_at(500, &[POISON; 3]).unwrap();
    assert_eq!(
        b.read_range(499, 5).unwrap(),
        vec![data[499], POISON, POISON, POISON, data[503]]
    );
    let f = Buffer::from_slice(&e.ctx, "f32", &[1.5f32, -0.0, f32::INFINITY]).unwrap();
    let back = f.read().unwrap();
    assert_eq!(back[0], 1.5);
    assert!(back[1].is_sign_negative() && back[2].is_infinite());
    assert_no_validation_messages(&e.ctx);
}

#[test]
fn kernel_interface_mismatch_is_an_error() {
    let e = engine();
    let kernel = Kernel::new(&e.ctx, &k::fill::fill::DESC).unwrap();
    let b = Buffer::<u32>::new(&e.ctx, "b", 16).unwrap();
    let mut rec = e.ctx.recorder("mismatch").unwrap();
    let wrong_params = k::saxpy::Params { n: 1, a: 1.0 };
    let bad_count = rec.dispatch(
        &kernel,
        [b.binding(), b.binding()],
        &k::fill::Params { n: 16, value: 0 },
        16,
    );
    assert!(
        matches!(bad_count, Err(GpuError::KernelMismatch { .. })),
        "{bad_count:?}"
    );
    // Same size, different struct: allowed by size; a different size is refused.
    let bad_size = rec.dispatch(&kernel, [b.binding()], &[0u32; 3], 16);
    assert!(
        matches!(bad_size, Err(GpuError::KernelMismatch { .. })),
        "{bad_size:?}"
    );
    rec.dispatch(&kernel, [b.binding()], &wrong_params, 0)
        .unwrap();
    drop(rec);
    assert_no_validation_messages(&e.ctx);
}

/// A uniform block must be covered by the bound range and fit the device's uniform range; each
/// violation is a clear error, not a validation failure. (Slices already enforce the storage
/// offset alignment, which on lavapipe equals the uniform one.)
#[test]
fn uniform_block_bindings_are_checked() {
    use kernels::field::mlp::{mlp_fwd_block as kb, Params};
    let e = engine();
    assert_eq!(
        kb::DESC
            .bindings
            .iter()
            .filter(|b| b.uniform_bytes == 65536)
            .count(),
        1
    );
    let kernel = Kernel::new(&e.ctx, &kb::DESC).unwrap();
    let small = Buffer::<f32>::new(&e.ctx, "small block", 1024).unwrap();
    let big = Buffer::<f32>::new(&e.ctx, "big block", 16384 + 64).unwrap();
    let any = Buffer::<f32>::new(&e.ctx, "any", 64).unwrap();
    let p = Params {
        n: 1,
        chunk: 1,
        saved_stride: 0,
        groups: 16,
        lut: [0, 1, 2, 3],
    };
    let mut rec = e.ctx.recorder("uniform checks").unwrap();
    for (block, what) in [
        (small.binding(), "too small"),
        (big.binding(), "beyond the uniform range"),
    ] {
        let b = kb::Bindings {
            shape_buf: any.binding(),
            inputs: any.binding(),
            outputs: any.binding(),
            mlp: block,
        };
        let r = rec.dispatch(&kernel, b.into_array(), &p, 1);
        match r {
            Err(GpuError::Usage(m)) => assert!(m.contains("uniform block"), "{what}: {m}"),
            other => panic!("{what}: {other:?}"),
        }
    }
    drop(rec);
    assert_no_validation_messages(&e.ctx);
}

#[test]
fn workgroup_folding() {
    assert_eq!(fold_groups(0, 65535, 65535).unwrap(), [0, 1]);
    assert_eq!(fold_groups(65535, 65535, 65535).unwrap(), [65535, 1]);
    let [x, y] = fold_groups(65536, 65535, 65535).unwrap();
    assert!(x as u64 * y as u64 >= 65536 && x <= 65535 && y == 2);
    let [x, y] = fold_groups(4_000_000_007, 65535, 65535).unwrap();
    assert!(x as u64 * y as u64 >= 4_000_000_007 && x <= 65535 && y <= 65535);
    assert!(fold_groups(65535u64 * 65535 + 1, 65535, 65535).is_err());
}

#[test]
fn timestamps_bracket_a_dispatch() {
    let e = engine();
    let timer = GpuTimer::new(&e.ctx, "test timer", 2).unwrap();
    let b = Buffer::<u32>::new(&e.ctx, "timed", 1 << 20).unwrap();
    let mut rec = e.ctx.recorder("timed").unwrap();
    rec.reset_timer(&timer).unwrap();
    rec.timestamp(&timer, 0).unwrap();
    e.prims.fill(&mut rec, b.binding(), 1 << 20, 3).unwrap();
    rec.timestamp(&timer, 1).unwrap();
    assert!(rec.timestamp(&timer, 2).is_err());
    e.ctx.run(rec).unwrap();
    let t = timer.read_ns(2).unwrap();
    assert!(t[1] >= t[0] && t[1] - t[0] < 60e9, "{t:?}");
    assert_no_validation_messages(&e.ctx);
}

#[test]
fn every_params_twin_matches_naga_layout() {
    assert!(!kernels::LAYOUTS.is_empty());
    for l in kernels::LAYOUTS {
        assert_eq!(l.naga_size as usize, l.rust_size, "{}: size", l.file);
        for (name, naga, rust) in l.members {
            assert_eq!(*naga as usize, *rust, "{}::{name}: offset", l.file);
        }
    }
    for kd in kernels::ALL {
        assert!(
            kd.spirv.len() > 5 && kd.spirv[0] == 0x0723_0203,
            "{}: not SPIR-V",
            kd.name
        );
        assert!(
            kd.spirv[1] >= 0x0001_0300,
            "{}: SPIR-V version {:#x} < 1.3",
            kd.name,
            kd.spirv[1]
        );
        let mut seen = std::collections::BTreeSet::new();
        assert!(
            kd.bindings.iter().all(|b| seen.insert(b.binding)),
            "{}: duplicate binding",
            kd.name
        );
    }
}

/// Every kernel builds, except cooperative-matrix ones whose tile the device does not offer:
/// those are refused as a missing feature.
#[test]
fn every_kernel_builds_on_the_device() {
    let e = engine();
    let info = e.ctx.info();
    for kd in kernels::ALL {
        let offered = kd.coop_tile == 0 || info.offers_coop_tile(kd.coop_tile);
        match Kernel::new(&e.ctx, kd) {
            Ok(_) => assert!(
                offered,
                "{}: built without its cooperative-matrix tile",
                kd.name
            ),
            Err(err) if !offered => assert!(
                matches!(err, GpuError::MissingFeature { .. }),
                "{}: {err}",
                kd.name
            ),
            Err(err) => panic!("{}: {err}", kd.name),
        }
    }
    assert_no_validation_messages(&e.ctx);
}

/// Creates and drops every resource kind on a context of its own, then drops the context: the
/// allocator must be back to zero allocations and the validation layer (which reports objects
/// not destroyed at vkDestroyDevice / vkDestroyInstance) must stay silent.
#[test]
fn create_drop_every_resource_kind_leaks_nothing() {
    let ctx = Context::new(&desc()).unwrap();
    let log = ctx.validation_log();
    assert_eq!(ctx.live_allocations().unwrap(), 0);
    {
        let prims = extranerf_prims::Prims::new(&ctx).unwrap();
        let b = Buffer::<u32>::from_slice(&ctx, "leak check", &[1, 2, 3]).unwrap();
        let c = Buffer::<f32>::new(&ctx, "leak check 2", 5).unwrap();
        let timer = GpuTimer::new(&ctx, "leak timer", 4).unwrap();
        let _scan = extranerf_prims::ScanPlan::new(&ctx, 5000).unwrap();
        let _sort = extranerf_prims::SortPlan::new(&ctx, 5000).unwrap();
        let unsubmitted = ctx.recorder("never submitted").unwrap();
        drop(unsubmitted);
        let mut rec = ctx.recorder("submitted").unwrap();
        rec.reset_timer(&timer).unwrap();
        rec.timestamp(&timer, 0).unwrap();
        prims.fill(&mut rec, b.binding(), 3, 9).unwrap();
        rec.copy(b.binding(), 0, c.binding(), 0, 12).unwrap();
        // Submit and drop everything while the GPU may still be running: deferred release.
        let ticket = ctx.submit(rec).unwrap();
        assert!(ctx.live_allocations().unwrap() > 0);
        drop((b, c, timer, prims));
        ctx.wait(ticket).unwrap();
    }
    ctx.wait_idle().unwrap();
    assert_eq!(
        ctx.live_allocations().unwrap(),
        0,
        "allocations left after every resource was dropped"
    );
    drop(ctx);
    let msgs = log.take();
    assert!(msgs.is_empty(), "validation messages at teardown: {msgs:?}");
}

/// Buffers, kernels and timers of one context are refused by another context's recorder
/// (their handles mean nothing on that device).
#[test]
fn resources_of_another_context_are_refused() {
    let e = engine();
    let other = Context::new(&ContextDesc {
        validation: Validation::Off,
        device: None,
        max_binding_bytes: None,
        max_memory_bytes: None,
        share_with_wgpu: false,
        no_coop_matrix: false,
    })
    .unwrap();
    let foreign = Buffer::<u32>::new(&other, "foreign", 16).unwrap();
    let foreign_kernel = Kernel::new(&other, &k::fill::fill::DESC).unwrap();
    let foreign_timer = GpuTimer::new(&other, "foreign timer", 2).unwrap();
    let local = Buffer::<u32>::new(&e.ctx, "local", 16).unwrap();
    let own_kernel = Kernel::new(&e.ctx, &k::fill::fill::DESC).unwrap();
    let mut rec = e.ctx.recorder("mixing contexts").unwrap();
    let p = k::fill::Params { n: 16, value: 1 };
    for err in [
        rec.dispatch(&own_kernel, [foreign.binding()], &p, 16)
            .unwrap_err(),
        rec.dispatch(&foreign_kernel, [local.binding()], &p, 16)
            .unwrap_err(),
        rec.copy(foreign.binding(), 0, local.binding(), 0, 4)
            .unwrap_err(),
        rec.fill_words(foreign.binding(), 1, 0).unwrap_err(),
        rec.reset_timer(&foreign_timer).unwrap_err(),
        rec.timestamp(&foreign_timer, 0).unwrap_err(),
    ] {
        assert!(err.to_string().contains("another Vulkan context"), "{err}");
    }
    assert!(
        rec.copy(local.binding(), 0, local.binding(), u64::MAX, 4)
            .is_err(),
        "offset overflow must be an error"
    );
    assert_eq!(rec.dispatches, 0);
    drop(rec);
    assert_no_validation_messages(&e.ctx);
}

#[test]
fn slices_bind_a_range_of_one_buffer() {
    let e = engine();
    let ctx = &e.ctx;
    let align = ctx.info().min_storage_buffer_offset_alignment as usize;
    // Start of the second section: a multiple of the alignment in u32 elements.
    let at = align.div_ceil(4).max(1) * 3;
    let n = at + 100;
    let buf = Buffer::<u32>::from_slice(ctx, "sliced", &vec![7u32; n]).unwrap();
    let mut rec = ctx.recorder("slices").unwrap();
    // A kernel, a fill and a copy each confined to their slice.
    e.prims
        .fill(&mut rec, buf.slice(at, 37).unwrap(), 37, 1)
        .unwrap();
    rec.fill_words(buf.slice(0, 5).unwrap(), 5, 2).unwrap();
    rec.copy(
        buf.slice(0, 5).unwrap(),
        0,
        buf.slice(at, 50).unwrap(),
        40 * 4,
        2 * 4,
    )
    .unwrap();
    ctx.run(rec).unwrap();
    let got = buf.read().unwrap();
    for (i, v) in got.iter().enumerate() {
        let want = match i {
            0..5 => 2,
            _ if (at..at + 37).contains(&i) => 1,
            _ if (at + 40..at + 42).contains(&i) => 2,
            _ => 7,
        };
        assert_eq!(*v, want, "element {i}");
    }
    // Misaligned starts and overruns are errors naming the buffer.
    if align > 4 {
        let e1 = buf.slice(1, 4).unwrap_err().to_string();
        assert!(e1.contains("sliced") && e1.contains("alignment"), "{e1}");
    }
    let e2 = buf.slice(at, n).unwrap_err().to_string();
    assert!(e2.contains("sliced") && e2.contains("overruns"), "{e2}");
    // A slice's range is enforced by the checks of the operations that use it.
    let mut rec = ctx.recorder("slice overrun").unwrap();
    assert!(rec.fill_words(buf.slice(0, 5).unwrap(), 9, 0).is_err());
    assert_no_validation_messages(ctx);
}

/// A memory limit makes allocations past it fail as a full device does: a clear error naming
/// the buffer, nothing leaked, and room again once buffers are dropped.
#[test]
fn memory_limit_gives_out_of_memory_errors() {
    let ctx = Context::new(&ContextDesc {
        max_memory_bytes: Some(1 << 20),
        ..desc()
    })
    .unwrap();
    let a = Buffer::<f32>::new(&ctx, "first half", 1 << 17).unwrap();
    let e = Buffer::<f32>::new(&ctx, "one too many", 1 << 18).unwrap_err();
    match &e {
        GpuError::OutOfDeviceMemory { name, bytes } => {
            assert_eq!((name.as_str(), *bytes), ("one too many", 1 << 20));
        }
        other => panic!("expected out of memory, got {other:?}"),
    }
    assert!(e.to_string().contains("one too many"), "{e}");
    drop(a);
    ctx.wait_idle().unwrap();
    let b = Buffer::<f32>::new(&ctx, "after the drop", 1 << 18).unwrap();
    assert_eq!(b.len(), 1 << 18);
    drop(b);
    assert_no_validation_messages(&ctx);
}
