//! Agreement with spconv 2.3.8: every case listed in `$SPARSEOCC_FIXTURES/spconv/manifest.json` is run
//! (layer reprs are parsed, weights matched by shape), output sites must match exactly and features to the
//! manifest's tolerance (1e-4). The folder is external: without it these tests print a skip line
//! (see `occ_testdata`).

mod common;

use burn::backend::NdArray;
use burn::prelude::*;
use burn::tensor::TensorData;
use occ_sparse::conv::sparse_conv3d;
use occ_sparse::{ConvGeometry, ConvKind, Coord, SparseMaxPool3dConfig, SparseTensor};
use occ_testdata::read_npy;
use serde_json::Value;
use std::path::Path;

type B = NdArray<f32>;

#[derive(Debug, Clone)]
struct Layer {
    kind: String,
    cin: usize,
    cout: usize,
    geom: ConvGeometry,
    output_padding: [usize; 3],
}

fn list_after(repr: &str, key: &str) -> Option<[usize; 3]> {
    let start = repr.find(&format!("{key}=["))? + key.len() + 2;
    let end = start + repr[start..].find(']')?;
    let v: Vec<usize> = repr[start..end]
        .split(',')
        .map(|s| s.trim().parse().ok())
        .collect::<Option<_>>()?;
    (v.len() == 3).then(|| [v[0], v[1], v[2]])
}

fn parse_layer(repr: &str) -> Layer {
    let kind = repr[..repr.find('(').expect("layer repr")].to_string();
    let args = &repr[kind.len() + 1..];
    let nums: Vec<usize> = args
        .split(',')
        .take(2)
        .map(|s| s.trim().parse().unwrap_or(0))
        .collect();
    let kernel = list_after(repr, "kernel_size").expect("kernel_size");
    Layer {
        kind,
        cin: nums[0],
        cout: nums[1],
        geom: ConvGeometry::new(kernel)
            .with_stride(list_after(repr, "stride").unwrap_or([1; 3]))
            .with_padding(list_after(repr, "padding").unwrap_or([0; 3]))
            .with_dilation(list_after(repr, "dilation").unwrap_or([1; 3])),
        output_padding: list_after(repr, "output_padding").unwrap_or([0; 3]),
    }
}

fn coords_from(v: &[i32]) -> Vec<Coord> {
    v.chunks(4).map(|c| [c[0], c[1], c[2], c[3]]).collect()
}

fn load_weight(path: &Path) -> (Tensor<B, 5>, Vec<usize>) {
    let (w, shape) = read_npy::<f32>(path);
    let t = Tensor::from_data(
        TensorData::new(w, [shape[0], shape[1], shape[2], shape[3], shape[4]]),
        &Default::default(),
    );
    (t, shape)
}

fn run_layers(
    input: SparseTensor<B>,
    layers: &[Layer],
    weights: &[Tensor<B, 5>],
) -> SparseTensor<B> {
    let mut x = input;
    let mut regular_geoms: Vec<ConvGeometry> = Vec::new();
    for (layer, w) in layers.iter().zip(weights) {
        x = match layer.kind.as_str() {
            "SubMConv3d" => sparse_conv3d(
                x,
                w.clone(),
                None,
                ConvKind::Submanifold,
                layer.geom,
                [0; 3],
            ),
            "SparseConv3d" => {
                regular_geoms.push(layer.geom);
                sparse_conv3d(x, w.clone(), None, ConvKind::Regular, layer.geom, [0; 3])
            }
            "SparseConvTranspose3d" => sparse_conv3d(
                x,
                w.clone(),
                None,
                ConvKind::Transposed,
                layer.geom,
                layer.output_padding,
            ),
            "SparseInverseConv3d" => {
                // spconv pairs it through indice_key with the regular conv of the same kernel.
                let g = *regular_geoms
                    .iter()
                    .rev()
                    .find(|g| g.kernel == layer.geom.kernel)
                    .expect("inverse conv without a matching regular conv");
                sparse_conv3d(x, w.clone(), None, ConvKind::Inverse, g, [0; 3])
            }
            other => panic!("unsupported spconv layer {other}"),
        }
        .unwrap_or_else(|e| panic!("{}: {e}", layer.kind));
    }
    x
}

#[test]
fn spconv_cases_agree() {
    let Some(fixtures) = occ_testdata::fixtures() else {
        return;
    };
    let dir = fixtures.join("spconv");
    let manifest: Value = serde_json::from_str(
        &std::fs::read_to_string(dir.join("manifest.json")).expect("spconv/manifest.json"),
    )
    .expect("manifest json");
    let shape: Vec<usize> = serde_json::from_value(manifest["spatial_shape_xyz"].clone()).unwrap();
    let shape = [shape[0], shape[1], shape[2]];
    let batch = manifest["batch"].as_u64().unwrap() as usize;
    let tol = manifest["tolerance"].as_f64().unwrap_or(1e-4);
    let (ci, cshape) = read_npy::<i32>(&dir.join("input_coords_bxyz.npy"));
    let (fi, fshape) = read_npy::<f32>(&dir.join("input_feats.npy"));
    assert_eq!(cshape[0], fshape[0]);
    let coords = coords_from(&ci);
    let feats = Tensor::<B, 2>::from_data(
        TensorData::new(fi, [fshape[0], fshape[1]]),
        &Default::default(),
    );

    let cases = manifest["cases"].as_object().expect("cases");
    assert!(!cases.is_empty());
    for (name, case) in cases {
        let reprs: Vec<String> = if let Some(l) = case.get("layers") {
            serde_json::from_value(l.clone()).unwrap()
        } else {
            vec![case["layer"].as_str().expect("layer").to_string()]
        };
        let layers: Vec<Layer> = reprs.iter().map(|r| parse_layer(r)).collect();
        // Weights: `<case>_weight.npy` for one layer; otherwise the `weight_shapes` entries, matched to the
        // layers by shape [Cout, k, Cin].
        let weights: Vec<Tensor<B, 5>> = if layers.len() == 1 {
            vec![load_weight(&dir.join(format!("{name}_weight.npy"))).0]
        } else {
            let ws = case["weight_shapes"].as_object().expect("weight_shapes");
            layers
                .iter()
                .map(|l| {
                    let want = [
                        l.cout,
                        l.geom.kernel[0],
                        l.geom.kernel[1],
                        l.geom.kernel[2],
                        l.cin,
                    ];
                    let hits: Vec<&String> = ws
                        .iter()
                        .filter(|(_, s)| {
                            serde_json::from_value::<Vec<usize>>((*s).clone()).unwrap() == want
                        })
                        .map(|(k, _)| k)
                        .collect();
                    assert_eq!(hits.len(), 1, "{name}: weight for {l:?}");
                    load_weight(&dir.join(format!("{}.npy", hits[0]))).0
                })
                .collect()
        };
        let input = SparseTensor::new(coords.clone(), feats.clone(), shape, batch).unwrap();
        let out = run_layers(input, &layers, &weights).sorted();

        let (oc, _) = read_npy::<i32>(&dir.join(format!("{name}_out_coords_bxyz.npy")));
        let (of, ofs) = read_npy::<f32>(&dir.join(format!("{name}_out_feats.npy")));
        let expected_coords = coords_from(&oc);
        assert_eq!(out.coords(), &expected_coords[..], "{name}: output sites");
        if let Some(n) = case["n_out"].as_u64() {
            assert_eq!(out.num_active(), n as usize, "{name}: n_out");
        }
        if let Some(s) = case.get("out_spatial_shape_xyz") {
            let s: Vec<usize> = serde_json::from_value(s.clone()).unwrap();
            assert_eq!(out.spatial_shape().to_vec(), s, "{name}: out spatial shape");
        }
        assert_eq!(out.channels(), ofs[1]);
        let got = out.feats_to_vec();
        let err = got
            .iter()
            .zip(&of)
            .map(|(a, b)| (a - b).abs())
            .fold(0.0f32, f32::max);
        assert!((err as f64) <= tol, "{name}: max abs err {err} > {tol}");
        eprintln!("{name}: {} sites, max abs err {err:.2e}", out.num_active());
    }
}

/// Sparse max pooling against a brute-force maximum over the active inputs in each window, on the
/// spconv fixture's input sites.
#[test]
fn max_pool_matches_brute_force() {
    let Some(fixtures) = occ_testdata::fixtures() else {
        return;
    };
    let dir = fixtures.join("spconv");
    let (ci, _) = read_npy::<i32>(&dir.join("input_coords_bxyz.npy"));
    let (fi, fshape) = read_npy::<f32>(&dir.join("input_feats.npy"));
    let coords = coords_from(&ci);
    let c = fshape[1];
    let shape = [48, 40, 8];
    let batch = 1 + coords.iter().map(|c| c[0]).max().unwrap() as usize;
    for (k, s, p) in [
        ([2, 2, 2], [2, 2, 2], [0, 0, 0]),
        ([3, 3, 3], [2, 2, 2], [1, 1, 1]),
        ([3, 3, 1], [1, 1, 1], [1, 1, 0]),
    ] {
        let feats = Tensor::<B, 2>::from_data(
            TensorData::new(fi.clone(), [fshape[0], c]),
            &Default::default(),
        );
        let input = SparseTensor::new(coords.clone(), feats, shape, batch).unwrap();
        let pool = SparseMaxPool3dConfig::new(k)
            .with_stride(Some(s))
            .with_padding(p)
            .init();
        let out = pool.forward(input).unwrap();
        let got = out.feats_to_vec();
        let index: std::collections::HashMap<Coord, usize> =
            coords.iter().enumerate().map(|(i, &c)| (c, i)).collect();
        for (row, o) in out.coords().iter().enumerate() {
            let mut best = vec![f32::NEG_INFINITY; c];
            let mut any = false;
            for kx in 0..k[0] {
                for ky in 0..k[1] {
                    for kz in 0..k[2] {
                        let i = [
                            o[0],
                            o[1] * s[0] as i32 - p[0] as i32 + kx as i32,
                            o[2] * s[1] as i32 - p[1] as i32 + ky as i32,
                            o[3] * s[2] as i32 - p[2] as i32 + kz as i32,
                        ];
                        if let Some(&r) = index.get(&i) {
                            any = true;
                            for ch in 0..c {
                                best[ch] = best[ch].max(fi[r * c + ch]);
                            }
                        }
                    }
                }
            }
            assert!(any, "output site {o:?} has no active input");
            assert_eq!(
                &got[row * c..(row + 1) * c],
                &best[..],
                "pool {k:?} at {o:?}"
            );
        }
    }
}
