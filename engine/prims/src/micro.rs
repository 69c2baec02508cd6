//! Microbenchmarks of the operations the fused training step is made of (issue 61): random
//! reads from a table the hash grid's size, f32 atomic adds without and with collisions, FMA
//! throughput, a 64-wide dense layer per lane, a storage load at a lane-uniform address, and a
//! lane's own vec4s in workgroup memory against a storage buffer. `extranerf bench kernels
//! --only micro` times them (ns per operation and per lane); the kernels are in
//! `kernels/wgsl/micro/` and [`crate::reference::micro_lane`] is what each lane must return.

use extranerf_gpu::kernels::micro as k;
use extranerf_gpu::{Buffer, Context, GpuError, Kernel, Recorder, Result};

/// Bytes of the random-access tables: the hash grid's at 16 levels x 2 features x 2^17
/// entries of f32 (issue 61's configuration), 2^22 floats.
pub const TABLE_LOG2_FLOATS: u32 = 22;
/// Floats (log2) of [`MicroOp::Read4Near`]'s part of the table: 256 KiB.
pub const NEAR_LOG2_FLOATS: u32 = 16;
/// vec4s of each lane's region in [`MicroOp::Workgroup`] and [`MicroOp::Storage`].
pub const REGION_VEC4S: u32 = 32;
/// The dense layers' width (the MLPs' hidden width).
pub const DENSE_WIDTH: u32 = 64;
/// Points per lane of the four-point dense layers (common/mlp_block.wgsl's MLP_GROUP).
pub const DENSE_GROUP: u32 = 4;
/// `fma(a, m, c)` of [`MicroOp::Fma`]: a contraction, so the values stay finite and normal.
pub const FMA_M: f32 = 0.999;
/// See [`FMA_M`].
pub const FMA_C: f32 = 0.001;

/// One microbenchmark.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum MicroOp {
    /// The random index alone (the baseline of the reads and atomics): no memory access.
    Index,
    /// A random 4-byte read.
    Read4,
    /// A random 4-byte read from the table's first 256 KiB (a coarse grid level's size, which
    /// stays in a core's L2 cache).
    Read4Near,
    /// Two adjacent random 4-byte reads (a corner's two features), counted as one operation.
    ReadPair,
    /// The same through the step's branch between a table's two bindings (`table_at`), its
    /// condition from a storage load, as the step's is.
    ReadPairBranch,
    /// A random 8-byte (vec2) read.
    Read8,
    /// A random 16-byte (vec4) read.
    Read16,
    /// A vec4 storage load whose address is the same in every lane (from a loop counter).
    SameAddress,
    /// A vec4 read-modify-write of the lane's own region of workgroup memory.
    Workgroup,
    /// The same in a storage buffer.
    Storage,
    /// An f32 atomic add, `share` lanes adding to the same random address at once (1: each
    /// lane its own addresses).
    Atomic {
        /// Lanes that follow one random sequence.
        share: u32,
    },
    /// An f32 atomic add at distinct random addresses whose line a plain load brought in
    /// first (8 loads, then the 8 adds).
    AtomicPrefetched,
    /// A u32 atomic add at distinct random addresses (one `lock xadd` on x86, where an f32
    /// add is a compare-exchange loop): gradients accumulated in fixed point.
    AtomicU32,
    /// A fused multiply-add with every operand in registers (8 independent vec4 chains).
    Fma,
    /// A 64 x 64 dense layer and ReLU on one point per lane, weights from the uniform block.
    Dense1,
    /// The same on four points per lane sharing each weight load.
    Dense4,
    /// The layer's backward data pass (W^T d) on four points per lane.
    Dense4Back,
}

impl MicroOp {
    /// Every microbenchmark, in the order `bench kernels` prints them.
    pub fn all() -> Vec<MicroOp> {
        vec![
            MicroOp::Index,
            MicroOp::Read4,
            MicroOp::Read4Near,
            MicroOp::ReadPair,
            MicroOp::ReadPairBranch,
            MicroOp::Read8,
            MicroOp::Read16,
            MicroOp::SameAddress,
            MicroOp::Workgroup,
            MicroOp::Storage,
            MicroOp::Atomic { share: 1 },
            MicroOp::Atomic { share: 8 },
            MicroOp::Atomic { share: 64 },
            MicroOp::AtomicPrefetched,
            MicroOp::AtomicU32,
            MicroOp::Fma,
            MicroOp::Dense1,
            MicroOp::Dense4,
            MicroOp::Dense4Back,
        ]
    }

    /// A short name for tables and JSON.
    pub fn name(self) -> String {
        match self {
            MicroOp::Index => "random index (baseline)".into(),
            MicroOp::Read4 => "random read 4 B".into(),
            MicroOp::Read4Near => "random read 4 B, 256 KiB table".into(),
            MicroOp::ReadPair => "random read 2 x 4 B adjacent (a corner)".into(),
            MicroOp::ReadPairBranch => {
                "random read 2 x 4 B adjacent, through a two-binding branch".into()
            }
            MicroOp::Read8 => "random read 8 B".into(),
            MicroOp::Read16 => "random read 16 B".into(),
            MicroOp::SameAddress => "storage vec4 load, same address in all lanes".into(),
            MicroOp::Workgroup => "workgroup vec4 read-modify-write".into(),
            MicroOp::Storage => "storage vec4 read-modify-write".into(),
            MicroOp::Atomic { share: 1 } => "f32 atomic add, distinct addresses".into(),
            MicroOp::Atomic { share } => format!("f32 atomic add, {share} lanes per address"),
            MicroOp::AtomicPrefetched => {
                "f32 atomic add, distinct addresses, line loaded first".into()
            }
            MicroOp::AtomicU32 => "u32 atomic add, distinct addresses".into(),
            MicroOp::Fma => "FMA, registers".into(),
            MicroOp::Dense1 => "dense 64x64 layer, 1 point/lane".into(),
            MicroOp::Dense4 => "dense 64x64 layer, 4 points/lane".into(),
            MicroOp::Dense4Back => "dense 64x64 backward, 4 points/lane".into(),
        }
    }

    /// What one operation is, for the unit column.
    pub fn unit(self) -> &'static str {
        match self {
            MicroOp::Index => "index",
            MicroOp::Read4
            | MicroOp::Read4Near
            | MicroOp::ReadPair
            | MicroOp::ReadPairBranch
            | MicroOp::Read8
            | MicroOp::Read16 => "read",
            MicroOp::SameAddress => "load",
            MicroOp::Workgroup | MicroOp::Storage => "vec4 r+w",
            MicroOp::Atomic { .. } | MicroOp::AtomicPrefetched | MicroOp::AtomicU32 => "atomic",
            MicroOp::Fma | MicroOp::Dense1 | MicroOp::Dense4 | MicroOp::Dense4Back => "FMA",
        }
    }

    /// The operation whose time is this one's baseline (the same random indices without the
    /// memory access), if any.
    pub fn baseline(self) -> Option<MicroOp> {
        match self {
            MicroOp::Read4
            | MicroOp::Read4Near
            | MicroOp::ReadPair
            | MicroOp::ReadPairBranch
            | MicroOp::Read8
            | MicroOp::Read16
            | MicroOp::Atomic { .. }
            | MicroOp::AtomicPrefetched
            | MicroOp::AtomicU32 => Some(MicroOp::Index),
            _ => None,
        }
    }

    /// log2 of the table's entries at this operation's width (0 when it has no table).
    pub fn log2_entries(self) -> u32 {
        match self {
            MicroOp::Index
            | MicroOp::Read4
            | MicroOp::Atomic { .. }
            | MicroOp::AtomicPrefetched
            | MicroOp::AtomicU32 => TABLE_LOG2_FLOATS,
            MicroOp::Read8 | MicroOp::ReadPair | MicroOp::ReadPairBranch => TABLE_LOG2_FLOATS - 1,
            MicroOp::Read4Near => NEAR_LOG2_FLOATS,
            MicroOp::Read16 => TABLE_LOG2_FLOATS - 2,
            _ => 0,
        }
    }

    /// The kernel's loop count for `ops` requested operations per lane: a multiple of 8 for
    /// memory operations, of 32 FMAs for [`MicroOp::Fma`] (32 x `ops` of them, the FMA being
    /// cheap), and `ops / 256` layers (at least one) for the dense layers.
    pub fn kernel_ops(self, ops: u32) -> u32 {
        match self {
            MicroOp::Fma => ops.max(1).saturating_mul(32),
            MicroOp::Dense1 | MicroOp::Dense4 | MicroOp::Dense4Back => (ops / 256).max(1),
            _ => ops.max(1).div_ceil(8).saturating_mul(8),
        }
    }

    /// Operations (in [`MicroOp::unit`]s) one lane performs for `ops` requested.
    pub fn ops_per_lane(self, ops: u32) -> u64 {
        let n = self.kernel_ops(ops) as u64;
        let layer = (DENSE_WIDTH * DENSE_WIDTH) as u64;
        match self {
            MicroOp::Dense1 => n * layer,
            MicroOp::Dense4 | MicroOp::Dense4Back => n * layer * DENSE_GROUP as u64,
            _ => n,
        }
    }

    /// Lanes that follow one random sequence (1 but for [`MicroOp::Atomic`]).
    pub fn share(self) -> u32 {
        match self {
            MicroOp::Atomic { share } => share,
            _ => 1,
        }
    }
}

/// The kernels and buffers of the microbenchmarks, for `lanes` lanes.
#[derive(Debug)]
pub struct Micro {
    lanes: u32,
    index: Kernel,
    read4: Kernel,
    read_pair: Kernel,
    read_pair_branch: Kernel,
    read8: Kernel,
    read16: Kernel,
    same_address: Kernel,
    workgroup: Kernel,
    storage: Kernel,
    atomic: Kernel,
    atomic_u32: Kernel,
    atomic_prefetched: Kernel,
    fma: Kernel,
    dense1: Kernel,
    dense4: Kernel,
    dense4_back: Kernel,
    /// 2^22 floats, entry e = e mod 8 (sums of them stay exact in f32).
    table: Buffer<f32>,
    /// 16 vec4s for [`MicroOp::SameAddress`].
    small: Buffer<f32>,
    /// lanes x REGION_VEC4S vec4s for [`MicroOp::Storage`].
    region: Buffer<f32>,
    /// The atomics' target, 2^22 floats.
    acc: Buffer<f32>,
    /// The dense layers' weights: the uniform block (64 KiB), W (64 x 64) then b at float 0.
    weights: Buffer<f32>,
    /// Per lane 4 points x 64 activations.
    inputs: Buffer<f32>,
    out: Buffer<f32>,
}

impl Micro {
    /// Builds the kernels (the atomic one needs `shaderBufferFloat32AtomicAdd`) and their
    /// buffers for `lanes` lanes (at least one); `weights` (64 x 64 then 64 biases) and
    /// `inputs` (lanes x 4 x 64) feed the dense layers.
    pub fn new(ctx: &Context, lanes: u32, weights: &[f32], inputs: &[f32]) -> Result<Micro> {
        let layer = (DENSE_WIDTH * (DENSE_WIDTH + 1)) as usize;
        let per_lane = (DENSE_GROUP * DENSE_WIDTH) as usize;
        if lanes == 0 || weights.len() != layer || inputs.len() != lanes as usize * per_lane {
            return Err(GpuError::Usage(format!(
                "micro benchmarks: {lanes} lanes (at least 1) need {layer} weights and {} inputs, got {} and {}",
                lanes as usize * per_lane,
                weights.len(),
                inputs.len()
            )));
        }
        let floats = 1usize << TABLE_LOG2_FLOATS;
        let table: Vec<f32> = (0..floats).map(|e| (e % 8) as f32).collect();
        let small: Vec<f32> = (0..64).map(|e| (e % 5) as f32).collect();
        let mut block = weights.to_vec();
        block.resize(BLOCK_FLOATS, 0.0);
        Ok(Micro {
            lanes,
            index: Kernel::new(ctx, &k::micro_mem::micro_index::DESC)?,
            read4: Kernel::new(ctx, &k::micro_mem::micro_read4::DESC)?,
            read_pair: Kernel::new(ctx, &k::micro_mem::micro_read_pair::DESC)?,
            read_pair_branch: Kernel::new(ctx, &k::micro_mem::micro_read_pair_branch::DESC)?,
            read8: Kernel::new(ctx, &k::micro_mem::micro_read8::DESC)?,
            read16: Kernel::new(ctx, &k::micro_mem::micro_read16::DESC)?,
            same_address: Kernel::new(ctx, &k::micro_mem::micro_same_address::DESC)?,
            workgroup: Kernel::new(ctx, &k::micro_mem::micro_workgroup::DESC)?,
            storage: Kernel::new(ctx, &k::micro_mem::micro_storage::DESC)?,
            atomic: Kernel::new(ctx, &k::micro_atomic::micro_atomic::DESC)?,
            atomic_u32: Kernel::new(ctx, &k::micro_atomic::micro_atomic_u32::DESC)?,
            atomic_prefetched: Kernel::new(ctx, &k::micro_atomic::micro_atomic_prefetched::DESC)?,
            fma: Kernel::new(ctx, &k::micro_alu::micro_fma::DESC)?,
            dense1: Kernel::new(ctx, &k::micro_alu::micro_dense1::DESC)?,
            dense4: Kernel::new(ctx, &k::micro_alu::micro_dense4::DESC)?,
            dense4_back: Kernel::new(ctx, &k::micro_alu::micro_dense4_back::DESC)?,
            table: Buffer::from_slice(ctx, "micro table", &table)?,
            small: Buffer::from_slice(ctx, "micro small", &small)?,
            region: Buffer::new(ctx, "micro region", 4 * (lanes * REGION_VEC4S) as usize)?,
            acc: Buffer::new(ctx, "micro atomics", floats)?,
            weights: Buffer::from_slice(ctx, "micro weights", &block)?,
            inputs: Buffer::from_slice(ctx, "micro inputs", inputs)?,
            out: Buffer::new(ctx, "micro out", lanes as usize)?,
        })
    }

    /// Records what must precede each timed run of `op`: zeroing the storage region or the
    /// atomics' target.
    pub fn record_setup<'a>(&'a self, rec: &mut Recorder<'a>, op: MicroOp) -> Result<()> {
        match op {
            MicroOp::Storage => rec.fill_words(self.region.binding(), self.region.len() as u64, 0),
            MicroOp::Atomic { .. } | MicroOp::AtomicPrefetched | MicroOp::AtomicU32 => {
                rec.fill_words(self.acc.binding(), self.acc.len() as u64, 0)
            }
            _ => Ok(()),
        }
    }

    /// Records one run of `op` with `ops` requested operations per lane (see
    /// [`MicroOp::kernel_ops`]); each lane's result lands in [`Micro::read_out`].
    pub fn record<'a>(&'a self, rec: &mut Recorder<'a>, op: MicroOp, ops: u32) -> Result<()> {
        if let MicroOp::Atomic { share } = op {
            if share == 0 {
                return Err(GpuError::Usage(
                    "micro atomics: at least 1 lane per address".into(),
                ));
            }
        }
        let lut = [0, 1, 2, 3];
        let (lanes, log2_entries, share) = (self.lanes, op.log2_entries(), op.share());
        let ops = op.kernel_ops(ops);
        let threads = lanes as u64;
        let out = self.out.binding();
        macro_rules! params {
            ($m:ident) => {
                k::$m::Params {
                    lanes,
                    ops,
                    log2_entries,
                    share,
                    m: FMA_M,
                    c: FMA_C,
                    lut,
                    ..Default::default()
                }
            };
        }
        let mem = params!(micro_mem);
        let alu = params!(micro_alu);
        use k::micro_mem as mm;
        match op {
            MicroOp::Index => rec.dispatch(
                &self.index,
                mm::micro_index::Bindings { out }.into_array(),
                &mem,
                threads,
            ),
            MicroOp::Read4 | MicroOp::Read4Near => rec.dispatch(
                &self.read4,
                mm::micro_read4::Bindings {
                    table4: self.table.binding(),
                    out,
                }
                .into_array(),
                &mem,
                threads,
            ),
            MicroOp::ReadPair => rec.dispatch(
                &self.read_pair,
                mm::micro_read_pair::Bindings {
                    table4: self.table.binding(),
                    out,
                }
                .into_array(),
                &mem,
                threads,
            ),
            MicroOp::ReadPairBranch => rec.dispatch(
                &self.read_pair_branch,
                mm::micro_read_pair_branch::Bindings {
                    table4: self.table.binding(),
                    small: self.small.binding(),
                    out,
                    table_hi: self.table.binding(),
                }
                .into_array(),
                &mem,
                threads,
            ),
            MicroOp::Read8 => rec.dispatch(
                &self.read8,
                mm::micro_read8::Bindings {
                    table8: self.table.binding(),
                    out,
                }
                .into_array(),
                &mem,
                threads,
            ),
            MicroOp::Read16 => rec.dispatch(
                &self.read16,
                mm::micro_read16::Bindings {
                    table16: self.table.binding(),
                    out,
                }
                .into_array(),
                &mem,
                threads,
            ),
            MicroOp::SameAddress => rec.dispatch(
                &self.same_address,
                mm::micro_same_address::Bindings {
                    small: self.small.binding(),
                    out,
                }
                .into_array(),
                &mem,
                threads,
            ),
            MicroOp::Workgroup => rec.dispatch(
                &self.workgroup,
                mm::micro_workgroup::Bindings { out }.into_array(),
                &mem,
                threads,
            ),
            MicroOp::Storage => rec.dispatch(
                &self.storage,
                mm::micro_storage::Bindings {
                    region: self.region.binding(),
                    out,
                }
                .into_array(),
                &mem,
                threads,
            ),
            MicroOp::Atomic { .. } => rec.dispatch(
                &self.atomic,
                k::micro_atomic::micro_atomic::Bindings {
                    acc: self.acc.binding(),
                }
                .into_array(),
                &params!(micro_atomic),
                threads,
            ),
            MicroOp::AtomicPrefetched => rec.dispatch(
                &self.atomic_prefetched,
                k::micro_atomic::micro_atomic_prefetched::Bindings {
                    acc: self.acc.binding(),
                    out,
                }
                .into_array(),
                &params!(micro_atomic),
                threads,
            ),
            MicroOp::AtomicU32 => rec.dispatch(
                &self.atomic_u32,
                k::micro_atomic::micro_atomic_u32::Bindings {
                    acc_u32: self.acc.binding(),
                }
                .into_array(),
                &params!(micro_atomic),
                threads,
            ),
            MicroOp::Fma => rec.dispatch(
                &self.fma,
                k::micro_alu::micro_fma::Bindings { out }.into_array(),
                &alu,
                threads,
            ),
            MicroOp::Dense1 | MicroOp::Dense4 | MicroOp::Dense4Back => {
                let kernel = match op {
                    MicroOp::Dense1 => &self.dense1,
                    MicroOp::Dense4 => &self.dense4,
                    _ => &self.dense4_back,
                };
                // The three entry points bind the same three buffers.
                let b = k::micro_alu::micro_dense4::Bindings {
                    mlp: self.weights.binding(),
                    inputs: self.inputs.binding(),
                    out,
                };
                rec.dispatch(kernel, b.into_array(), &alu, threads)
            }
        }
    }

    /// Each lane's result of the last run (not of the atomics, whose result is
    /// [`Micro::read_atomics`]).
    pub fn read_out(&self) -> Result<Vec<f32>> {
        self.out.read()
    }

    /// The atomics' target after the last atomic run: each entry's count of adds (as f32
    /// after [`MicroOp::Atomic`], as u32 after [`MicroOp::AtomicU32`]).
    pub fn read_atomics(&self) -> Result<Vec<f32>> {
        self.acc.read()
    }
}

/// Floats of the uniform weight block (64 KiB), as the MLPs' (`extranerf_nerf`'s
/// `BLOCK_FLOATS`).
pub const BLOCK_FLOATS: usize = 16384;
