//! Data-parallel training on burn's collective operations (`burn-collective`).
//!
//! `N` workers, each with its own replica of the network, its own data loading and (on the CPU) its
//! own rayon pool of `threads / N` threads, train on shards of the same global batch: the batch of a
//! step is drawn exactly as a single-device run draws it (`train.batch_size` frames), and worker `r`
//! takes frames `r·b/N .. (r+1)·b/N` of it. Every step:
//!
//! 1. each worker loads its shard, runs the forward pass and its loss; the workers then agree that
//!    every one of them got a finite loss (one all-reduce of a flag): a worker that failed (a bad
//!    file, a non-finite loss) makes all of them stop with its error, none waits forever;
//! 2. the gradients are all-reduced (mean over workers) parameter by parameter, in the order in
//!    which the module visits its parameters (so the replicas need not share burn's parameter ids); a
//!    parameter that has a gradient on some workers only gets the zero gradient from the others, one
//!    with a gradient on none stays without (as on one device);
//! 3. every worker clips by the global norm of the reduced gradients and takes the AdamW step, so
//!    the replicas stay identical; this is checked after every step (a 64-bit fingerprint of every
//!    parameter's bits compared across workers, exactly), not assumed;
//! 4. worker 0 alone logs, reports progress (the global step, the frames of all workers) and writes
//!    checkpoints; the logged loss is the mean of the workers' losses.
//!
//! The objective is the mean over workers of each shard's loss, as with PyTorch's
//! DistributedDataParallel. It equals the single-device loss of the whole batch when the loss of a
//! batch is the mean of its frames' losses and nothing else couples the frames; the three models'
//! losses are not of that kind (their cross-entropies are means over the valid voxels of the whole
//! batch; Lovász and the scene-class affinity terms are not sums over frames at all), and their
//! BatchNorm layers use the statistics of each worker's own shard (not synchronised). Both effects
//! are measured in docs/data_parallel.md.

use crate::error::TrainError;
use burn::module::{AutodiffModule, Module, ModuleVisitor, Param};
use burn::optim::GradientsParams;
use burn::prelude::*;
use burn::tensor::backend::AutodiffBackend;
use burn::tensor::TensorPrimitive;
use burn_collective::{CollectiveConfig, PeerId, ReduceOperation};

/// One worker of a data-parallel run: its rank among `world` workers, registered with the
/// collective of backend `B` (the inner backend of an autodiff backend).
pub struct Peer<B: Backend> {
    id: PeerId,
    rank: usize,
    world: usize,
    device: B::Device,
}

fn collective_err(what: &str) -> impl FnOnce(burn_collective::CollectiveError) -> TrainError + '_ {
    move |e| {
        TrainError::Parallel(format!(
            "{what}: {e:?} (a worker stopped; see its error above)"
        ))
    }
}

impl<B: Backend> Peer<B> {
    /// Registers worker `rank` of `world` with the in-process collective; returns once all `world`
    /// workers have registered.
    pub fn register(rank: usize, world: usize, device: &B::Device) -> Result<Self, TrainError> {
        let id = PeerId::from(rank as u32);
        let config = CollectiveConfig::default().with_num_devices(world);
        burn_collective::register::<B>(id, device.clone(), config)
            .map_err(collective_err("registering the workers"))?;
        Ok(Self {
            id,
            rank,
            world,
            device: device.clone(),
        })
    }

    /// This worker's rank, `0..world`.
    pub fn rank(&self) -> usize {
        self.rank
    }

    /// Number of workers.
    pub fn world(&self) -> usize {
        self.world
    }

    /// The frames of a global batch of `batch` frames that this worker trains on.
    pub fn shard(&self, batch: usize) -> std::ops::Range<usize> {
        let per = batch / self.world;
        self.rank * per..(self.rank + 1) * per
    }

    fn all_reduce<const D: usize>(
        &self,
        t: Tensor<B, D>,
        op: ReduceOperation,
        what: &str,
    ) -> Result<Tensor<B, D>, TrainError> {
        let p = burn_collective::all_reduce::<B>(self.id, t.into_primitive().tensor(), op)
            .map_err(collective_err(what))?;
        Ok(Tensor::from_primitive(TensorPrimitive::Float(p)))
    }

    /// Sums `values` over the workers (exact for integers below 2^24).
    pub fn sum(&self, values: &[f32], what: &str) -> Result<Vec<f32>, TrainError> {
        let t = Tensor::<B, 1>::from_floats(values, &self.device);
        let r = self.all_reduce(t, ReduceOperation::Sum, what)?;
        r.into_data()
            .to_vec::<f32>()
            .map_err(|e| TrainError::Parallel(format!("{what}: {e:?}")))
    }

    /// Whether every worker passed `ok` (each worker learns the same answer).
    pub fn all_ok(&self, ok: bool, what: &str) -> Result<bool, TrainError> {
        let n = self.sum(&[if ok { 1.0 } else { 0.0 }], what)?;
        Ok(n[0] as usize == self.world)
    }

    /// Means of `values` over the workers.
    pub fn mean(&self, values: &[f64], what: &str) -> Result<Vec<f64>, TrainError> {
        let v: Vec<f32> = values.iter().map(|&v| v as f32).collect();
        Ok(self
            .sum(&v, what)?
            .into_iter()
            .map(|s| s as f64 / self.world as f64)
            .collect())
    }

    /// Checks that every worker holds `fingerprint` (exactly): its 8 bytes and their squares are
    /// summed over the workers; sums equal to `world · b` and `world · b²` for every byte `b` mean
    /// that all workers have the same bytes (no spread around a common mean).
    pub fn same_everywhere(&self, fingerprint: u64, what: &str) -> Result<bool, TrainError> {
        let bytes = fingerprint.to_le_bytes();
        let mut v: Vec<f32> = bytes.iter().map(|&b| b as f32).collect();
        v.extend(bytes.iter().map(|&b| (b as f32) * (b as f32)));
        let s = self.sum(&v, what)?;
        let n = self.world as f32;
        Ok(bytes
            .iter()
            .enumerate()
            .all(|(i, &b)| s[i] == n * b as f32 && s[8 + i] == n * (b as f32) * (b as f32)))
    }

    /// Leaves the collective.
    pub fn finish(self) {
        let _ = burn_collective::finish_collective::<B>(self.id);
    }
}

/// The device of worker `rank` of `workers`: where the backend has several devices of `base`'s
/// kind (GPUs), device `base + rank`, one per worker; where it has one (the CPU), `base` itself,
/// shared by the workers.
pub fn worker_device<B: Backend>(
    base: &B::Device,
    rank: usize,
    workers: usize,
) -> Result<B::Device, TrainError> {
    let id = base.to_id();
    let count = B::device_count(id.type_id);
    if count <= 1 {
        return Ok(base.clone());
    }
    let first = id.index_id as usize;
    if first + workers > count {
        return Err(TrainError::Config(format!(
            "train.devices = {workers} from device {first}: the machine has {count} devices of this kind"
        )));
    }
    Ok(B::Device::from_id(burn::tensor::backend::DeviceId {
        type_id: id.type_id,
        index_id: (first + rank) as u16,
    }))
}

/// Releases every worker waiting in a collective operation of backend `B` (they get an error) and
/// forgets the registered workers: how a failed worker stops the others.
pub fn abort_collective<B: Backend>() {
    burn_collective::reset_collective::<B>();
}

/// Which parameters have a gradient here (1) or not (0), in the module's visiting order.
struct Presence<'a, B: AutodiffBackend> {
    grads: &'a GradientsParams,
    flags: Vec<f32>,
    _b: std::marker::PhantomData<B>,
}

impl<B: AutodiffBackend> ModuleVisitor<B> for Presence<'_, B> {
    fn visit_float<const D: usize>(&mut self, param: &Param<Tensor<B, D>>) {
        let has = self.grads.get::<B::InnerBackend, D>(param.id).is_some();
        self.flags.push(if has { 1.0 } else { 0.0 });
    }
}

/// All-reduces (mean) the gradient of every parameter that has one on some worker.
struct Reduce<'a, B: AutodiffBackend> {
    peer: &'a Peer<B::InnerBackend>,
    grads: &'a mut GradientsParams,
    counts: &'a [f32],
    index: usize,
    error: Option<TrainError>,
}

impl<B: AutodiffBackend> ModuleVisitor<B> for Reduce<'_, B> {
    fn visit_float<const D: usize>(&mut self, param: &Param<Tensor<B, D>>) {
        let i = self.index;
        self.index += 1;
        if self.error.is_some() || self.counts.get(i).copied().unwrap_or(0.0) == 0.0 {
            return;
        }
        let g = match self.grads.remove::<B::InnerBackend, D>(param.id) {
            Some(g) => g,
            None => {
                let p = param.val().inner();
                Tensor::zeros(p.shape(), &p.device())
            }
        };
        match self
            .peer
            .all_reduce(g, ReduceOperation::Sum, "all-reducing the gradients")
            .map(|g| g.div_scalar(self.peer.world as f64))
        {
            Ok(g) => self.grads.register::<B::InnerBackend, D>(param.id, g),
            Err(e) => self.error = Some(e),
        }
    }
}

/// Replaces each worker's gradients by their mean over the workers (see the module docs).
pub fn all_reduce_grads<B: AutodiffBackend, M: AutodiffModule<B>>(
    peer: &Peer<B::InnerBackend>,
    module: &M,
    mut grads: GradientsParams,
) -> Result<GradientsParams, TrainError> {
    let mut presence = Presence::<B> {
        grads: &grads,
        flags: Vec::new(),
        _b: Default::default(),
    };
    module.visit(&mut presence);
    let counts = peer.sum(&presence.flags, "counting the gradients")?;
    if counts.len() != presence.flags.len() {
        return Err(TrainError::Parallel(format!(
            "the workers' networks differ: {} parameters here, {} summed",
            presence.flags.len(),
            counts.len()
        )));
    }
    let mut reduce = Reduce::<B> {
        peer,
        grads: &mut grads,
        counts: &counts,
        index: 0,
        error: None,
    };
    module.visit(&mut reduce);
    match reduce.error {
        Some(e) => Err(e),
        None => Ok(grads),
    }
}

/// A 64-bit fingerprint of the bits of every float parameter of `module` (FNV-1a over the f32 bit
/// patterns, parameters in visiting order): equal fingerprints mean identical replicas.
pub fn fingerprint<B: Backend, M: Module<B>>(module: &M) -> u64 {
    struct Fp(u64);
    impl<B: Backend> ModuleVisitor<B> for Fp {
        fn visit_float<const D: usize>(&mut self, param: &Param<Tensor<B, D>>) {
            let data = param.val().into_data().convert::<f32>();
            let words = data.as_slice::<f32>().unwrap_or(&[]);
            for w in words {
                self.0 ^= w.to_bits() as u64;
                self.0 = self.0.wrapping_mul(0x0100_0000_01b3);
            }
            // The shape too, so that a reshaped copy is not "the same".
            self.0 ^= D as u64 ^ ((words.len() as u64) << 8);
            self.0 = self.0.wrapping_mul(0x0100_0000_01b3);
        }
    }
    let mut v = Fp(0xcbf2_9ce4_8422_2325);
    module.visit(&mut v);
    v.0
}
