//! `sample::bilinear_sample` (burn's `grid_sample_2d`, bilinear, zeros padding,
//! align_corners=false) against the PyTorch fixture `grid_sample_*` (files found through
//! `$SPARSEOCC_FIXTURES/reference/manifest.json`, an external folder: without it those tests print a
//! skip line): output, gradient w.r.t. the features and
//! w.r.t. the grid for a given upstream gradient. Also against a host brute force on random grids
//! that reach outside the map, on the autodiff and the plain NdArray backends.

#[path = "common/compare.rs"]
mod compare;
use burn::backend::{Autodiff, NdArray};
use burn::prelude::*;
use burn::tensor::Element;
use compare::rel_err;
use occ_model::sample::bilinear_sample;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use std::path::{Path, PathBuf};

type B64 = Autodiff<NdArray<f64>>;
type B32 = Autodiff<NdArray<f32>>;

/// `$SPARSEOCC_FIXTURES/reference`, or `None` (skip reported by `occ_testdata`) without the
/// external fixtures folder.
fn reference_dir() -> Option<PathBuf> {
    Some(occ_testdata::fixtures()?.join("reference"))
}

/// The manifest entry whose file stem is `stem`, read as f64 with its shape.
fn fixture(dir: &Path, stem: &str) -> (Vec<f64>, Vec<usize>) {
    let mpath = dir.join("manifest.json");
    let text =
        std::fs::read_to_string(&mpath).unwrap_or_else(|e| panic!("{}: {e}", mpath.display()));
    let json: serde_json::Value =
        serde_json::from_str(&text).unwrap_or_else(|e| panic!("{}: {e}", mpath.display()));
    let name = json["files"]
        .as_object()
        .expect("manifest.json: no `files` object")
        .keys()
        .find(|k| Path::new(k).file_stem().and_then(|s| s.to_str()) == Some(stem))
        .unwrap_or_else(|| panic!("manifest.json lists no file `{stem}.*`"))
        .clone();
    occ_testdata::read_npy(&dir.join(name))
}

fn shape4(s: &[usize]) -> [usize; 4] {
    s.try_into()
        .unwrap_or_else(|_| panic!("expected a 4-d array, got {s:?}"))
}

/// A tensor of the backend's float element type (explicit dtype: burn 0.21 shares one default
/// float dtype per device between `NdArray<f32>` and `NdArray<f64>` in a process).
fn t4<B: Backend>(v: &[f64], s: [usize; 4]) -> Tensor<B, 4> {
    let dtype = <B::FloatElem as Element>::dtype();
    Tensor::from_data(TensorData::new(v.to_vec(), s), (&Default::default(), dtype))
}

fn host<B: Backend, const D: usize>(t: Tensor<B, D>) -> Vec<f64> {
    t.into_data().convert::<f64>().to_vec::<f64>().unwrap()
}

/// Output and gradients (features, grid) of `sum(bilinear_sample(f, g) * up)`.
fn run<B: burn::tensor::backend::AutodiffBackend>(
    f: &[f64],
    fs: [usize; 4],
    g: &[f64],
    gs: [usize; 4],
    up: &[f64],
) -> (Vec<f64>, Vec<f64>, Vec<f64>) {
    let ft = t4::<B>(f, fs).require_grad();
    let gt = t4::<B>(g, gs).require_grad();
    let out = bilinear_sample(ft.clone(), gt.clone());
    let os = out.dims();
    let loss = (out.clone() * t4::<B>(up, os)).sum();
    let grads = loss.backward();
    (
        host(out),
        host(ft.grad(&grads).expect("no feature gradient")),
        host(gt.grad(&grads).expect("no grid gradient")),
    )
}

fn check_fixture<B: burn::tensor::backend::AutodiffBackend>(tol: f64) {
    let Some(dir) = reference_dir() else { return };
    let (f, fs) = fixture(&dir, "grid_sample_features");
    let (g, gs) = fixture(&dir, "grid_sample_grid");
    let (out_ref, os) = fixture(&dir, "grid_sample_out");
    let (up, us) = fixture(&dir, "grid_sample_upstream");
    let (gf_ref, gfs) = fixture(&dir, "grid_sample_grad_features");
    let (gg_ref, ggs) = fixture(&dir, "grid_sample_grad_grid");
    let (fs, gs) = (shape4(&fs), shape4(&gs));
    assert_eq!(os, us);
    assert_eq!(gfs, fs.to_vec());
    assert_eq!(ggs, gs.to_vec());
    let (out, gf, gg) = run::<B>(&f, fs, &g, gs, &up);
    assert_eq!(out.len(), out_ref.len(), "output shape");
    let (e_out, e_gf, e_gg) = (
        rel_err(&out, &out_ref),
        rel_err(&gf, &gf_ref),
        rel_err(&gg, &gg_ref),
    );
    eprintln!("grid_sample: out {e_out:.2e}, d/dfeatures {e_gf:.2e}, d/dgrid {e_gg:.2e}");
    assert!(e_out <= tol, "output relative error {e_out:e}");
    assert!(e_gf <= tol, "feature gradient relative error {e_gf:e}");
    assert!(e_gg <= tol, "grid gradient relative error {e_gg:e}");
}

#[test]
fn grid_sample_fixture_f64() {
    check_fixture::<B64>(1e-10);
}

#[test]
fn grid_sample_fixture_f32() {
    check_fixture::<B32>(1e-4);
}

/// The plain (non-autodiff) NdArray kernel gives the same output.
#[test]
fn grid_sample_fixture_forward_ndarray() {
    let Some(dir) = reference_dir() else { return };
    let (f, fs) = fixture(&dir, "grid_sample_features");
    let (g, gs) = fixture(&dir, "grid_sample_grid");
    let (out_ref, _) = fixture(&dir, "grid_sample_out");
    let out = host(bilinear_sample(
        t4::<NdArray<f64>>(&f, shape4(&fs)),
        t4::<NdArray<f64>>(&g, shape4(&gs)),
    ));
    assert!(rel_err(&out, &out_ref) < 1e-12);
}

/// Host brute force of PyTorch's bilinear `grid_sample` (zeros padding, align_corners=False).
fn brute_force(f: &[f64], fs: [usize; 4], g: &[f64], gs: [usize; 4]) -> Vec<f64> {
    let [n, c, h, w] = fs;
    let [_, ho, wo, _] = gs;
    let mut out = vec![0.0; n * c * ho * wo];
    for b in 0..n {
        for i in 0..ho {
            for j in 0..wo {
                let gi = ((b * ho + i) * wo + j) * 2;
                let x = ((g[gi] + 1.0) * w as f64 - 1.0) / 2.0;
                let y = ((g[gi + 1] + 1.0) * h as f64 - 1.0) / 2.0;
                let (x0, y0) = (x.floor(), y.floor());
                for (dx, dy) in [(0.0, 0.0), (1.0, 0.0), (0.0, 1.0), (1.0, 1.0)] {
                    let (xi, yi) = (x0 + dx, y0 + dy);
                    if xi < 0.0 || yi < 0.0 || xi >= w as f64 || yi >= h as f64 {
                        continue;
                    }
                    let wx = if dx == 0.0 { 1.0 - (x - x0) } else { x - x0 };
                    let wy = if dy == 0.0 { 1.0 - (y - y0) } else { y - y0 };
                    for ch in 0..c {
                        let v = f[((b * c + ch) * h + yi as usize) * w + xi as usize];
                        out[((b * c + ch) * ho + i) * wo + j] += wx * wy * v;
                    }
                }
            }
        }
    }
    out
}

#[test]
fn random_grids_match_brute_force_and_finite_differences() {
    let mut r = ChaCha8Rng::seed_from_u64(11);
    let fs = [2, 3, 5, 7];
    let gs = [2, 4, 6, 2];
    let f: Vec<f64> = (0..fs.iter().product())
        .map(|_| r.random_range(-1.0..1.0))
        .collect();
    // Reaching outside [-1, 1] to exercise the zero padding.
    let g: Vec<f64> = (0..gs.iter().product())
        .map(|_| r.random_range(-1.3..1.3))
        .collect();
    let want = brute_force(&f, fs, &g, gs);
    let os = [2, 3, 4, 6];
    let up: Vec<f64> = (0..os.iter().product())
        .map(|_| r.random_range(-1.0..1.0))
        .collect();
    let (out, gf, gg) = run::<B64>(&f, fs, &g, gs, &up);
    assert!(rel_err(&out, &want) < 1e-12);
    let plain = host(bilinear_sample(
        t4::<NdArray<f64>>(&f, fs),
        t4::<NdArray<f64>>(&g, gs),
    ));
    assert!(rel_err(&plain, &want) < 1e-12);
    let objective = |f: &[f64], g: &[f64]| -> f64 {
        brute_force(f, fs, g, gs)
            .iter()
            .zip(&up)
            .map(|(a, b)| a * b)
            .sum()
    };
    let h = 1e-6;
    for k in 0..f.len() {
        let (mut fp, mut fm) = (f.clone(), f.clone());
        fp[k] += h;
        fm[k] -= h;
        let fd = (objective(&fp, &g) - objective(&fm, &g)) / (2.0 * h);
        assert!(
            (fd - gf[k]).abs() < 1e-7,
            "d/dfeature {k}: {fd} vs {}",
            gf[k]
        );
    }
    for k in 0..g.len() {
        let (mut gp, mut gm) = (g.clone(), g.clone());
        gp[k] += h;
        gm[k] -= h;
        let fd = (objective(&f, &gp) - objective(&f, &gm)) / (2.0 * h);
        assert!((fd - gg[k]).abs() < 1e-6, "d/dgrid {k}: {fd} vs {}", gg[k]);
    }
}
