//! burn on the engine's Vulkan device (issue 5): the engine creates the device, burn's wgpu
//! runtime adopts it, and engine kernels read and write burn's tensors in place.
//! One test binary, fixed shapes: each lavapipe process pays burn's shader warm-up once.

#![allow(clippy::unwrap_used)] // tests: a failed unwrap is a failed test, with the error in the message

use burn::tensor::Tensor;
use extranerf_diffusion::device::{burn_device, TensorBuffer};
use extranerf_gpu::{Buffer, Context, ContextDesc};
use extranerf_prims::Prims;
use extranerf_tests::{assert_no_validation_messages, desc};

#[test]
fn burn_runs_on_the_engine_device_and_shares_tensors_in_place() {
    let ctx = Context::new(&ContextDesc {
        share_with_wgpu: true,
        ..desc()
    })
    .unwrap();
    let h = ctx.wgpu().expect("shared context has wgpu handles");
    // One VkDevice: wgpu's raw device is the engine's.
    assert_eq!(h.raw_device(), Some(ctx.raw_device()));
    let dev = burn_device(&ctx).unwrap();
    let n = 1024usize;
    let a: Vec<f32> = (0..n).map(|i| i as f32 * 0.25 - 7.0).collect();
    let ta = Tensor::<1>::from_floats(a.as_slice(), &dev);
    let tb = ta * 3.0 + 1.0;
    dev.sync().unwrap();
    // The engine reads burn's result in place: y = 2 b + y.
    let prims = Prims::new(&ctx).unwrap();
    let y = Buffer::from_slice(&ctx, "y", &vec![1.0f32; n]).unwrap();
    let view = TensorBuffer::new(&ctx, &tb).unwrap();
    let mut rec = ctx.recorder("read burn tensor").unwrap();
    prims
        .saxpy(&mut rec, 2.0, view.binding(), y.binding(), n as u64)
        .unwrap();
    ctx.run(rec).unwrap();
    let got = y.read().unwrap();
    for (i, (&g, &x)) in got.iter().zip(&a).enumerate() {
        let want = 2.0 * (3.0 * x + 1.0) + 1.0;
        assert!(
            (g - want).abs() <= 1e-5 * want.abs().max(1.0),
            "{i}: {g} vs {want}"
        );
    }
    // The engine writes burn's tensor in place; burn reads what the engine wrote.
    let mut rec = ctx.recorder("write burn tensor").unwrap();
    prims
        .fill(&mut rec, view.binding(), n as u64, 5.5f32.to_bits())
        .unwrap();
    ctx.run(rec).unwrap();
    drop(view);
    let back: Vec<f32> = (tb * 2.0).into_data().try_to_vec::<f32>().unwrap();
    assert!(back.iter().all(|&v| v == 11.0), "{:?}", &back[..4]);
    assert_no_validation_messages(&ctx);
}
