//! Occupancy losses against the PyTorch reference fixtures (`$SPARSEOCC_FIXTURES/reference`, files
//! discovered through `manifest.json`; values and gradients w.r.t. the logits; an external folder:
//! without it those tests print a skip line), plus property checks
//! on seeded random inputs: uniform-weight CE, Lovasz on hard predictions (= 1 − IoU), scal losses
//! decreasing towards the target, mask BCE / dice by hand, finite-difference gradients.

#[path = "common/compare.rs"]
mod compare;
use burn::backend::{Autodiff, NdArray};
use burn::prelude::*;
use burn::tensor::activation::softmax;
use burn::tensor::Element;
use compare::rel_err;
use occ_labels::IGNORE;
use occ_model::loss::{
    cross_entropy, cross_entropy_weighted, depth_bce, dice_loss, dice_per_mask, geo_scal_loss,
    lovasz_softmax, mask_bce, mask_bce_per_mask, monoscene_class_weights, occ_loss, sem_scal_loss,
};
use occ_testdata::read_npy;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use std::path::{Path, PathBuf};

type B64 = Autodiff<NdArray<f64>>;
type B32 = Autodiff<NdArray<f32>>;

// ------------------------------------------------------------------------------------------------
// Fixture access.

struct Manifest {
    dir: PathBuf,
    json: serde_json::Value,
}

impl Manifest {
    /// `None` (skip reported by `occ_testdata`) without the external fixtures folder.
    fn load() -> Option<Self> {
        let dir = occ_testdata::fixtures()?.join("reference");
        let path = dir.join("manifest.json");
        let text =
            std::fs::read_to_string(&path).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
        let json =
            serde_json::from_str(&text).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
        Some(Self { dir, json })
    }

    /// The file listed in the manifest whose name without extension is `stem`.
    fn file(&self, stem: &str) -> PathBuf {
        let files = self.json["files"]
            .as_object()
            .expect("manifest.json: no `files` object");
        let name = files
            .keys()
            .find(|k| Path::new(k).file_stem().and_then(|s| s.to_str()) == Some(stem))
            .unwrap_or_else(|| panic!("manifest.json lists no file `{stem}.*`"));
        self.dir.join(name)
    }

    /// `loss_values` of the manifest.
    fn loss_values(&self) -> Vec<(String, f64)> {
        self.json["loss_values"]
            .as_object()
            .expect("manifest.json: no `loss_values` object")
            .iter()
            .map(|(k, v)| (k.clone(), v.as_f64().expect("loss value is not a number")))
            .collect()
    }
}

struct LossCase {
    logits: Vec<f64>,
    n: usize,
    c: usize,
    labels: Vec<u8>,
    weights: Vec<f64>,
    /// (name, value, gradient w.r.t. logits)
    refs: Vec<(String, f64, Vec<f64>)>,
}

fn load_case() -> Option<LossCase> {
    let m = Manifest::load()?;
    let (logits, shape) = read_npy::<f64>(&m.file("loss_logits"));
    assert_eq!(shape.len(), 2, "loss_logits must be [N, C]");
    let (n, c) = (shape[0], shape[1]);
    let (labels, lshape) = read_npy::<i64>(&m.file("loss_labels"));
    assert_eq!(lshape, vec![n], "loss_labels must be [N]");
    let labels: Vec<u8> = labels
        .iter()
        .map(|&l| u8::try_from(l).unwrap_or_else(|_| panic!("label {l} does not fit u8")))
        .collect();
    let (weights, wshape) = read_npy::<f64>(&m.file("loss_class_weights"));
    assert_eq!(wshape, vec![c], "loss_class_weights must be [C]");
    let mut refs = Vec::new();
    for (name, value) in m.loss_values() {
        let (g, gshape) = read_npy::<f64>(&m.file(&format!("loss_grad_{name}")));
        assert_eq!(gshape, vec![n, c], "loss_grad_{name} must be [N, C]");
        refs.push((name, value, g));
    }
    for want in ["ce_weighted", "lovasz_softmax", "geo_scal", "sem_scal"] {
        assert!(
            refs.iter().any(|(n, _, _)| n == want),
            "manifest loss_values lacks `{want}`"
        );
    }
    Some(LossCase {
        logits,
        n,
        c,
        labels,
        weights,
        refs,
    })
}

/// A tensor of the backend's float element type. The dtype is explicit: burn 0.21 keeps one
/// default float dtype per device, shared by `NdArray<f32>` and `NdArray<f64>` in one process
/// (whichever registers first), so `from_data(.., &device)` alone could give f32 on the f64 backend.
fn tensor2<B: Backend>(v: &[f64], shape: [usize; 2]) -> Tensor<B, 2> {
    let dtype = <B::FloatElem as Element>::dtype();
    Tensor::from_data(
        TensorData::new(v.to_vec(), shape),
        (&Default::default(), dtype),
    )
}

fn host<B: Backend, const D: usize>(t: Tensor<B, D>) -> Vec<f64> {
    t.into_data().convert::<f64>().to_vec::<f64>().unwrap()
}

/// Evaluates loss `name` of the fixture on logits.
fn eval_loss<B: occ_sparse::SparseConvBackend>(
    name: &str,
    logits: Tensor<B, 2>,
    labels: &[u8],
    weights: &[f64],
) -> Tensor<B, 1> {
    match name {
        "ce_weighted" => cross_entropy_weighted(logits, labels, weights, IGNORE).unwrap(),
        "lovasz_softmax" => lovasz_softmax(softmax(logits, 1), labels, IGNORE).unwrap(),
        "geo_scal" => geo_scal_loss(logits, labels, 0, IGNORE).unwrap(),
        "sem_scal" => sem_scal_loss(logits, labels, IGNORE).unwrap(),
        other => panic!("manifest loss `{other}` is not known to this test"),
    }
}

fn check_fixture<B: burn::tensor::backend::AutodiffBackend + occ_sparse::SparseConvBackend>(
    tol: f64,
    grad_tol: f64,
) {
    let Some(case) = load_case() else { return };
    for (name, value, grad_ref) in &case.refs {
        let x = tensor2::<B>(&case.logits, [case.n, case.c]).require_grad();
        let loss = eval_loss(name, x.clone(), &case.labels, &case.weights);
        let got = host(loss.clone())[0];
        let rel = (got - value).abs() / value.abs().max(1e-300);
        assert!(
            rel <= tol,
            "{name}: value {got} vs reference {value} (relative error {rel:e} > {tol:e})"
        );
        let grads = loss.backward();
        let g = host(x.grad(&grads).expect("no gradient"));
        let gr = rel_err(&g, grad_ref);
        assert!(
            gr <= grad_tol,
            "{name}: gradient relative error {gr:e} > {grad_tol:e}"
        );
        eprintln!("{name}: value rel err {rel:.2e}, grad rel err {gr:.2e}");
    }
}

#[test]
fn fixture_values_and_gradients_f64() {
    check_fixture::<B64>(1e-6, 1e-6);
}

/// f32: values to 1e-4. Gradients to 1e-3 only: burn-ndarray's SIMD f32 `recip` (used by the
/// backward of `log` and of tensor division) is the hardware approximation (`rcpps`, relative
/// error up to ~3.7e-4), which alone puts the softmax / log-sum-exp gradients ~2e-4 (relative to
/// the largest entry) off on this fixture; everything else is exact to f32 rounding.
#[test]
fn fixture_values_and_gradients_f32() {
    check_fixture::<B32>(1e-4, 1e-3);
}

/// `occ_loss` returns the four terms of L_occ with the fixture's values.
#[test]
fn occ_loss_terms_match_fixture() {
    let Some(case) = load_case() else { return };
    let x = tensor2::<B64>(&case.logits, [case.n, case.c]);
    let terms = occ_loss(x, &case.labels, &case.weights).unwrap();
    let names: Vec<&str> = terms.iter().map(|(n, _)| n.as_str()).collect();
    assert_eq!(names, ["ce", "lovasz", "geo_scal", "sem_scal"]);
    for (term, fixture_name) in
        terms
            .iter()
            .zip(["ce_weighted", "lovasz_softmax", "geo_scal", "sem_scal"])
    {
        let want = case
            .refs
            .iter()
            .find(|(n, _, _)| n == fixture_name)
            .unwrap()
            .1;
        let got = host(term.1.clone())[0];
        assert!(
            (got - want).abs() <= 1e-9 * want.abs(),
            "{}: {got} vs {want}",
            term.0.as_str()
        );
    }
}

/// The fixture's class weights are MonoScene's `1/ln(f+0.001)` (docs/losses.md §2), when it has 20 classes.
#[test]
fn fixture_class_weights_are_monoscene() {
    let Some(case) = load_case() else { return };
    if case.c == 20 {
        let ours = monoscene_class_weights();
        assert!(rel_err(&case.weights, &ours) < 1e-6, "{:?}", case.weights);
    }
}

// ------------------------------------------------------------------------------------------------
// Property checks on random inputs.

fn random_case(r: &mut ChaCha8Rng, n: usize, c: usize, ignore_frac: f64) -> (Vec<f64>, Vec<u8>) {
    let logits: Vec<f64> = (0..n * c).map(|_| r.random_range(-3.0..3.0)).collect();
    let labels: Vec<u8> = (0..n)
        .map(|_| {
            if r.random_bool(ignore_frac) {
                IGNORE
            } else {
                r.random_range(0..c as u8)
            }
        })
        .collect();
    (logits, labels)
}

fn host_log_softmax(row: &[f64]) -> Vec<f64> {
    let m = row.iter().cloned().fold(f64::NEG_INFINITY, f64::max);
    let lse = m + row.iter().map(|x| (x - m).exp()).sum::<f64>().ln();
    row.iter().map(|x| x - lse).collect()
}

#[test]
fn ce_uniform_weights_is_mean_nll() {
    let mut r = ChaCha8Rng::seed_from_u64(1);
    for &(n, c) in &[(50usize, 5usize), (300, 20), (7, 2)] {
        let (logits, labels) = random_case(&mut r, n, c, 0.2);
        let mut sum = 0.0;
        let mut cnt = 0.0;
        for i in 0..n {
            if labels[i] != IGNORE {
                sum -= host_log_softmax(&logits[i * c..(i + 1) * c])[labels[i] as usize];
                cnt += 1.0;
            }
        }
        let want = sum / cnt;
        let x = tensor2::<B64>(&logits, [n, c]);
        let a = host(cross_entropy(x.clone(), &labels, IGNORE).unwrap())[0];
        let b = host(cross_entropy_weighted(x, &labels, &vec![2.5; c], IGNORE).unwrap())[0];
        assert!((a - want).abs() < 1e-12 * want.abs(), "{a} vs {want}");
        assert!((b - want).abs() < 1e-12 * want.abs(), "{b} vs {want}");
    }
}

/// Weighted CE by brute force: Σ w[y]·nll / Σ w[y] over non-ignored rows.
#[test]
fn ce_weighted_brute_force() {
    let mut r = ChaCha8Rng::seed_from_u64(2);
    let (n, c) = (200, 6);
    let (logits, labels) = random_case(&mut r, n, c, 0.3);
    let w: Vec<f64> = (0..c).map(|_| r.random_range(0.1..2.0)).collect();
    let (mut num, mut den) = (0.0, 0.0);
    for i in 0..n {
        if labels[i] != IGNORE {
            let y = labels[i] as usize;
            num -= w[y] * host_log_softmax(&logits[i * c..(i + 1) * c])[y];
            den += w[y];
        }
    }
    let got =
        host(cross_entropy_weighted(tensor2::<B64>(&logits, [n, c]), &labels, &w, 255).unwrap())[0];
    assert!((got - num / den).abs() < 1e-12 * got.abs());
}

#[test]
fn lovasz_perfect_prediction_is_zero() {
    let mut r = ChaCha8Rng::seed_from_u64(3);
    let (n, c) = (400, 8);
    let (_, labels) = random_case(&mut r, n, c, 0.1);
    // Exact one-hot probabilities on the labelled rows, random rows where ignored.
    let mut probs = vec![0.0; n * c];
    for i in 0..n {
        if labels[i] == IGNORE {
            probs[i * c + r.random_range(0..c)] = 1.0;
        } else {
            probs[i * c + labels[i] as usize] = 1.0;
        }
    }
    let got = host(lovasz_softmax(tensor2::<B64>(&probs, [n, c]), &labels, IGNORE).unwrap())[0];
    assert!(got.abs() < 1e-12, "{got}");
    // And from very confident logits.
    let logits: Vec<f64> = probs.iter().map(|p| 40.0 * p).collect();
    let x = tensor2::<B64>(&logits, [n, c]);
    let got = host(lovasz_softmax(softmax(x, 1), &labels, IGNORE).unwrap())[0];
    assert!(got.abs() < 1e-12, "{got}");
}

/// On hard (one-hot) predictions the Lovasz extension equals the set function: the loss is the
/// mean over present classes of 1 − IoU(prediction == c, label == c).
#[test]
fn lovasz_hard_prediction_is_one_minus_iou() {
    let mut r = ChaCha8Rng::seed_from_u64(4);
    for &(n, c) in &[(300usize, 5usize), (60, 3), (1000, 12)] {
        let (_, labels) = random_case(&mut r, n, c, 0.15);
        let pred: Vec<usize> = (0..n).map(|_| r.random_range(0..c)).collect();
        let mut probs = vec![0.0; n * c];
        for i in 0..n {
            probs[i * c + pred[i]] = 1.0;
        }
        let mut sum = 0.0;
        let mut present = 0.0;
        for k in 0..c {
            let (mut inter, mut union, mut any) = (0.0, 0.0, false);
            for i in 0..n {
                if labels[i] == IGNORE {
                    continue;
                }
                let g = labels[i] as usize == k;
                let p = pred[i] == k;
                any |= g;
                inter += (g && p) as u8 as f64;
                union += (g || p) as u8 as f64;
            }
            if any {
                sum += 1.0 - inter / union;
                present += 1.0;
            }
        }
        let want = sum / present;
        let got = host(lovasz_softmax(tensor2::<B64>(&probs, [n, c]), &labels, IGNORE).unwrap())[0];
        assert!((got - want).abs() < 1e-12, "n={n} c={c}: {got} vs {want}");
    }
}

/// geo_scal and sem_scal decrease as the logits move towards the one-hot target.
#[test]
fn scal_losses_decrease_towards_target() {
    let mut r = ChaCha8Rng::seed_from_u64(5);
    let (n, c) = (500, 10);
    let (logits, labels) = random_case(&mut r, n, c, 0.2);
    let mut prev = (f64::INFINITY, f64::INFINITY);
    for step in 0..8 {
        let alpha = step as f64 * 1.5;
        let moved: Vec<f64> = logits
            .iter()
            .enumerate()
            .map(|(j, &x)| {
                let (i, k) = (j / c, j % c);
                if labels[i] as usize == k {
                    x + alpha
                } else {
                    x
                }
            })
            .collect();
        let x = tensor2::<B64>(&moved, [n, c]);
        let geo = host(geo_scal_loss(x.clone(), &labels, 0, IGNORE).unwrap())[0];
        let sem = host(sem_scal_loss(x, &labels, IGNORE).unwrap())[0];
        assert!(
            geo < prev.0 && sem < prev.1,
            "step {step}: geo {geo} sem {sem} prev {prev:?}"
        );
        assert!(geo > 0.0 && sem > 0.0);
        prev = (geo, sem);
    }
    // Almost perfect predictions: both close to 0.
    assert!(prev.0 < 0.05 && prev.1 < 0.05, "{prev:?}");
}

/// Ignored rows do not influence any loss; with every row ignored the losses are 0 with a zero
/// gradient.
#[test]
fn ignored_rows_do_not_matter() {
    let mut r = ChaCha8Rng::seed_from_u64(6);
    let (n, c) = (120, 6);
    let (logits, labels) = random_case(&mut r, n, c, 0.4);
    let mut changed = logits.clone();
    for i in 0..n {
        if labels[i] == IGNORE {
            for k in 0..c {
                changed[i * c + k] = r.random_range(-10.0..10.0);
            }
        }
    }
    let w: Vec<f64> = (0..c).map(|k| 1.0 + k as f64).collect();
    for name in ["ce_weighted", "lovasz_softmax", "geo_scal", "sem_scal"] {
        let a = host(eval_loss(
            name,
            tensor2::<B64>(&logits, [n, c]),
            &labels,
            &w,
        ))[0];
        let b = host(eval_loss(
            name,
            tensor2::<B64>(&changed, [n, c]),
            &labels,
            &w,
        ))[0];
        assert!((a - b).abs() < 1e-12 * a.abs(), "{name}: {a} vs {b}");
        let all_ignored = vec![IGNORE; n];
        let x = tensor2::<B64>(&logits, [n, c]).require_grad();
        let l = eval_loss(name, x.clone(), &all_ignored, &w);
        assert_eq!(host(l.clone())[0], 0.0, "{name}");
        let g = host(x.grad(&l.backward()).unwrap());
        assert!(g.iter().all(|&v| v == 0.0), "{name}");
    }
}

#[test]
fn bad_labels_are_errors() {
    let x = tensor2::<B64>(&[0.0; 12], [4, 3]);
    assert!(cross_entropy(x.clone(), &[0, 1, 2], 255).is_err());
    assert!(cross_entropy(x.clone(), &[0, 1, 3, 255], 255).is_err());
    assert!(cross_entropy_weighted(x.clone(), &[0, 1, 2, 255], &[1.0; 2], 255).is_err());
    assert!(lovasz_softmax(x.clone(), &[0, 1, 7, 255], 255).is_err());
    assert!(geo_scal_loss(x.clone(), &[0, 1, 2], 0, 255).is_err());
    assert!(geo_scal_loss(x.clone(), &[0, 1, 2, 255], 5, 255).is_err());
    assert!(sem_scal_loss(x.clone(), &[0, 1, 2, 9], 255).is_err());
    assert!(mask_bce(x.clone(), tensor2::<B64>(&[0.0; 8], [4, 2])).is_err());
    assert!(dice_loss(x.clone(), tensor2::<B64>(&[0.0; 8], [2, 4])).is_err());
    assert!(depth_bce(x.clone(), &[Some(0), None, Some(3), None]).is_err());
    assert!(depth_bce(x, &[Some(0), None]).is_err());
}

fn sigmoid(x: f64) -> f64 {
    1.0 / (1.0 + (-x).exp())
}

#[test]
fn mask_bce_and_dice_by_hand() {
    let l3 = 3.0f64.ln();
    let logits = [0.0, l3, -l3, 2.0];
    let targets = [1.0, 0.0, 0.0, 1.0];
    let x = tensor2::<B64>(&logits, [2, 2]);
    let t = tensor2::<B64>(&targets, [2, 2]);
    // BCE: σ(0)=1/2 with t=1 → ln 2; σ(ln3)=3/4 with t=0 → ln 4; σ(−ln3)=1/4 with t=0 → ln(4/3);
    // σ(2) with t=1 → ln(1+e^−2).
    let b0 = (2.0f64.ln() + 4.0f64.ln()) / 2.0;
    let b1 = ((4.0f64 / 3.0).ln() + (1.0 + (-2.0f64).exp()).ln()) / 2.0;
    let per = host(mask_bce_per_mask(x.clone(), t.clone()).unwrap());
    assert!(
        (per[0] - b0).abs() < 1e-14 && (per[1] - b1).abs() < 1e-14,
        "{per:?}"
    );
    let m = host(mask_bce(x.clone(), t.clone()).unwrap())[0];
    assert!((m - (b0 + b1) / 2.0).abs() < 1e-14);
    // Dice: mask 0: s = [1/2, 3/4], t = [1, 0] → 1 − (2·½ + 1)/(5/4 + 1 + 1) = 1 − 2/3.25.
    let d0 = 1.0 - 2.0 / 3.25;
    let s2 = sigmoid(2.0);
    let d1 = 1.0 - (2.0 * s2 + 1.0) / (0.25 + s2 + 1.0 + 1.0);
    let per = host(dice_per_mask(x.clone(), t.clone()).unwrap());
    assert!(
        (per[0] - d0).abs() < 1e-14 && (per[1] - d1).abs() < 1e-14,
        "{per:?}"
    );
    let d = host(dice_loss(x, t).unwrap())[0];
    assert!((d - (d0 + d1) / 2.0).abs() < 1e-14);
    // Extreme logits stay finite and exact: BCE(100, 0) = 100 (+e^-100), BCE(-100, 0) ≈ 0.
    let x = tensor2::<B64>(&[100.0, -100.0, 100.0, -100.0], [2, 2]);
    let t = tensor2::<B64>(&[0.0, 0.0, 1.0, 1.0], [2, 2]);
    let per = host(mask_bce_per_mask(x, t).unwrap());
    assert!(
        (per[0] - 50.0).abs() < 1e-12 && (per[1] - 50.0).abs() < 1e-12,
        "{per:?}"
    );
}

/// Central finite differences of a scalar loss w.r.t. every input element vs autodiff (f64).
fn check_fd(x0: &[f64], shape: [usize; 2], f: &dyn Fn(Tensor<B64, 2>) -> Tensor<B64, 1>, tol: f64) {
    let x = tensor2::<B64>(x0, shape).require_grad();
    let l = f(x.clone());
    let g = host(x.grad(&l.backward()).unwrap());
    let h = 1e-6;
    for j in 0..x0.len() {
        let mut xp = x0.to_vec();
        xp[j] += h;
        let mut xm = x0.to_vec();
        xm[j] -= h;
        let fp = host(f(tensor2::<B64>(&xp, shape)))[0];
        let fm = host(f(tensor2::<B64>(&xm, shape)))[0];
        let fd = (fp - fm) / (2.0 * h);
        assert!(
            (fd - g[j]).abs() <= tol * (1.0 + fd.abs()),
            "element {j}: finite difference {fd} vs autodiff {}",
            g[j]
        );
    }
}

#[test]
fn dice_and_mask_bce_gradients_match_finite_differences() {
    let mut r = ChaCha8Rng::seed_from_u64(7);
    let (q, p) = (4, 9);
    let x0: Vec<f64> = (0..q * p).map(|_| r.random_range(-3.0..3.0)).collect();
    let t: Vec<f64> = (0..q * p).map(|_| r.random_range(0..2) as f64).collect();
    let tt = t.clone();
    check_fd(
        &x0,
        [q, p],
        &move |x| dice_loss(x, tensor2::<B64>(&tt, [q, p])).unwrap(),
        1e-7,
    );
    check_fd(
        &x0,
        [q, p],
        &move |x| mask_bce(x, tensor2::<B64>(&t, [q, p])).unwrap(),
        1e-7,
    );
}

#[test]
fn scal_and_depth_gradients_match_finite_differences() {
    let mut r = ChaCha8Rng::seed_from_u64(8);
    let (n, c) = (30, 5);
    let (x0, labels) = random_case(&mut r, n, c, 0.2);
    let l1 = labels.clone();
    check_fd(
        &x0,
        [n, c],
        &move |x| geo_scal_loss(x, &l1, 0, 255).unwrap(),
        1e-6,
    );
    let l2 = labels.clone();
    check_fd(
        &x0,
        [n, c],
        &move |x| sem_scal_loss(x, &l2, 255).unwrap(),
        1e-6,
    );
    let bins: Vec<Option<usize>> = labels
        .iter()
        .map(|&l| (l != 255).then_some(l as usize))
        .collect();
    check_fd(
        &x0,
        [n, c],
        &move |x| depth_bce(softmax(x, 1), &bins).unwrap(),
        1e-6,
    );
}

/// Depth BCE by hand: Σ over foreground rows of −ln p_b − Σ_{d≠b} ln(1 − p_d), / #fg.
#[test]
fn depth_bce_by_hand() {
    let probs = [0.5, 0.25, 0.25, 0.1, 0.6, 0.3, 0.2, 0.2, 0.6];
    let bins = [Some(0), None, Some(2)];
    let want = (-(0.5f64.ln()) - 2.0 * 0.75f64.ln() - 0.6f64.ln() - 2.0 * 0.8f64.ln()) / 2.0;
    let got = host(depth_bce(tensor2::<B64>(&probs, [3, 3]), &bins).unwrap())[0];
    assert!((got - want).abs() < 1e-14, "{got} vs {want}");
    let none = host(depth_bce(tensor2::<B64>(&probs, [3, 3]), &[None, None, None]).unwrap())[0];
    assert_eq!(none, 0.0);
    // A probability of exactly 0 at the target is capped at 100 as in PyTorch.
    let got = host(depth_bce(tensor2::<B64>(&[0.0, 1.0], [1, 2]), &[Some(0)]).unwrap())[0];
    assert_eq!(got, 200.0);
}
