//! Gradient utilities: clipping by GLOBAL norm (burn clips each tensor separately) and the split of
//! parameters into a weight-decay group and a no-decay group (biases, norm scales/offsets, embeddings,
//! queries), as the SparseOcc configs do (docs/reference_models.md §1 "optimiser": no decay for norms and embeddings).

use burn::module::{ModuleVisitor, Param, ParamId};
use burn::optim::GradientsParams;
use burn::prelude::*;
use burn::tensor::backend::AutodiffBackend;

struct SqNorm<'a, B: AutodiffBackend> {
    grads: &'a GradientsParams,
    total: f64,
    _b: std::marker::PhantomData<B>,
}

impl<B: AutodiffBackend> ModuleVisitor<B> for SqNorm<'_, B> {
    fn visit_float<const D: usize>(&mut self, param: &Param<Tensor<B, D>>) {
        if let Some(g) = self.grads.get::<B::InnerBackend, D>(param.id) {
            let s: f64 = g.powi_scalar(2).sum().into_scalar().elem();
            self.total += s;
        }
    }
}

struct Scale<'a, B: AutodiffBackend> {
    grads: &'a mut GradientsParams,
    factor: f64,
    _b: std::marker::PhantomData<B>,
}

impl<B: AutodiffBackend> ModuleVisitor<B> for Scale<'_, B> {
    fn visit_float<const D: usize>(&mut self, param: &Param<Tensor<B, D>>) {
        if let Some(g) = self.grads.remove::<B::InnerBackend, D>(param.id) {
            self.grads
                .register::<B::InnerBackend, D>(param.id, g.mul_scalar(self.factor));
        }
    }
}

/// Global L2 norm of all gradients of `module`'s parameters.
pub fn global_grad_norm<B: AutodiffBackend, M: burn::module::AutodiffModule<B>>(
    module: &M,
    grads: &GradientsParams,
) -> f64 {
    let mut v = SqNorm::<B> {
        grads,
        total: 0.0,
        _b: Default::default(),
    };
    module.visit(&mut v);
    v.total.sqrt()
}

/// Scales all gradients so that their global norm is at most `max_norm` (PyTorch
/// `clip_grad_norm_` semantics: factor `max_norm / (norm + 1e-6)` when above). Returns the norm before
/// clipping.
pub fn clip_global_norm<B: AutodiffBackend, M: burn::module::AutodiffModule<B>>(
    module: &M,
    grads: &mut GradientsParams,
    max_norm: f64,
) -> f64 {
    let norm = global_grad_norm::<B, M>(module, grads);
    if norm.is_finite() && norm > max_norm {
        let mut v = Scale::<B> {
            grads,
            factor: max_norm / (norm + 1e-6),
            _b: Default::default(),
        };
        module.visit(&mut v);
    }
    norm
}

struct Split<'a, B: AutodiffBackend> {
    grads: &'a mut GradientsParams,
    no_decay: GradientsParams,
    path: Vec<String>,
    _b: std::marker::PhantomData<B>,
}

impl<B: AutodiffBackend> ModuleVisitor<B> for Split<'_, B> {
    fn enter_module(&mut self, name: &str, _container_type: &str) {
        self.path.push(name.to_lowercase());
    }
    fn exit_module(&mut self, _name: &str, _container_type: &str) {
        self.path.pop();
    }
    fn visit_float<const D: usize>(&mut self, param: &Param<Tensor<B, D>>) {
        let named_no_decay = self.path.iter().any(|p| {
            p.contains("norm") || p.contains("embed") || p.contains("query") || p.contains("token")
        });
        if D == 1 || named_no_decay {
            if let Some(g) = self.grads.remove::<B::InnerBackend, D>(param.id) {
                self.no_decay.register::<B::InnerBackend, D>(param.id, g);
            }
        }
    }
}

/// Moves the gradients of no-decay parameters (1-D tensors, and anything under a module whose name
/// contains `norm`, `embed`, `query` or `token`) out of `grads` into a second set.
pub fn split_no_decay<B: AutodiffBackend, M: burn::module::AutodiffModule<B>>(
    module: &M,
    grads: &mut GradientsParams,
) -> GradientsParams {
    let mut v = Split::<B> {
        grads,
        no_decay: GradientsParams::new(),
        path: Vec::new(),
        _b: Default::default(),
    };
    module.visit(&mut v);
    v.no_decay
}

/// Parameter ids of a module (for tests and bookkeeping).
pub fn param_ids<B: Backend, M: Module<B>>(module: &M) -> Vec<ParamId> {
    struct Ids(Vec<ParamId>);
    impl<B: Backend> ModuleVisitor<B> for Ids {
        fn visit_float<const D: usize>(&mut self, param: &Param<Tensor<B, D>>) {
            self.0.push(param.id);
        }
    }
    let mut v = Ids(Vec::new());
    module.visit(&mut v);
    v.0
}
