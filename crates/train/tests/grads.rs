//! Global-norm clipping and the no-decay split against values computed by hand.

use burn::backend::{Autodiff, NdArray};
use burn::nn::{LayerNorm, LayerNormConfig, Linear, LinearConfig};
use burn::optim::GradientsParams;
use burn::prelude::*;
use occ_train::grads::{clip_global_norm, global_grad_norm, param_ids, split_no_decay};

type B = Autodiff<NdArray<f64>>;

#[derive(Module, Debug)]
struct Tiny<B: Backend> {
    fc: Linear<B>,
    norm: LayerNorm<B>,
}

/// A 3 -> 4 linear layer and a layer norm over 4, on the default device.
fn tiny() -> Tiny<B> {
    let dev = Default::default();
    Tiny {
        fc: LinearConfig::new(3, 4).init(&dev),
        norm: LayerNormConfig::new(4).init(&dev),
    }
}

fn grads_of(m: &Tiny<B>) -> GradientsParams {
    let dev = Default::default();
    let x = Tensor::<B, 2>::from_floats([[1.0, -2.0, 0.5], [0.3, 0.1, -1.0]], &dev);
    let y = m.norm.forward(m.fc.forward(x));
    let loss = (y.clone() * y).sum().mul_scalar(3.0) + m.fc.weight.val().sum();
    GradientsParams::from_grads(loss.backward(), m)
}

fn sq_sum(g: &GradientsParams, m: &Tiny<B>) -> f64 {
    let mut s = 0.0;
    if let Some(t) = g.get::<NdArray<f64>, 2>(m.fc.weight.id) {
        s += t.powi_scalar(2).sum().into_scalar();
    }
    for id in [
        m.fc.bias.as_ref().unwrap().id,
        m.norm.gamma.id,
        m.norm.beta.as_ref().unwrap().id,
    ] {
        if let Some(t) = g.get::<NdArray<f64>, 1>(id) {
            s += t.powi_scalar(2).sum().into_scalar();
        }
    }
    s
}

#[test]
fn clipping_uses_the_global_norm() {
    let m = tiny();
    let mut g = grads_of(&m);
    let norm = global_grad_norm::<B, _>(&m, &g);
    assert!((norm - sq_sum(&g, &m).sqrt()).abs() < 1e-12);
    assert!(norm > 0.5);
    let before = clip_global_norm::<B, _>(&m, &mut g, 0.5);
    assert_eq!(before, norm);
    let after = sq_sum(&g, &m).sqrt();
    assert!((after - 0.5 * norm / (norm + 1e-6)).abs() < 1e-9, "{after}");
    // Below the threshold nothing changes.
    let mut g2 = grads_of(&m);
    clip_global_norm::<B, _>(&m, &mut g2, 1e9);
    assert!((sq_sum(&g2, &m).sqrt() - norm).abs() < 1e-12);
}

#[test]
fn no_decay_group_holds_biases_and_norms() {
    let m = tiny();
    let mut g = grads_of(&m);
    let total = g.len();
    assert_eq!(total, param_ids::<B, _>(&m).len());
    let nd = split_no_decay::<B, _>(&m, &mut g);
    assert_eq!(nd.len() + g.len(), total);
    assert!(g.get::<NdArray<f64>, 2>(m.fc.weight.id).is_some());
    assert!(nd
        .get::<NdArray<f64>, 1>(m.fc.bias.as_ref().unwrap().id)
        .is_some());
    assert!(nd.get::<NdArray<f64>, 1>(m.norm.gamma.id).is_some());
}
