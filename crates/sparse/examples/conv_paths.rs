//! A/B of the two fused host compute orders on one convolution given as `.npy` files (the layout
//! of `conv_npy`): offset-major (`host::conv_forward_by_offset`) and output-major
//! (`host::conv_forward_by_output`), run alternately on the same kernel map so that machine load
//! hits both alike. Prints one JSON line: pairs per output row, min and median ms of each, and the
//! largest difference between their outputs.
//!
//! ```text
//! cargo run --release -p occ-sparse --example conv_paths -- DIR X,Y,Z KX,KY,KZ S P D BATCH KIND [R]
//! ```
//! `DIR` holds `coords.npy` (int32 [N,4]), `feats.npy` (float32 [N,Cin]) and `weight.npy` (float32
//! [Cout,kx,ky,kz,Cin]); `S`, `P`, `D` are stride, padding and dilation (one integer or three);
//! `KIND` is `subm`, `regular` or `transposed`; `R` runs of each (default 9).

use occ_data::formats::npy::{read_npy, NpyValues};
use occ_sparse::host::{conv_forward_by_offset, conv_forward_by_output, WeightView};
use occ_sparse::kernel_map::{conv_map, MapKind};
use occ_sparse::{ConvGeometry, CoordSet};
use std::path::Path;
use std::sync::Arc;
use std::time::Instant;

fn triple(s: &str) -> Result<[usize; 3], String> {
    let v: Vec<usize> = s
        .split(',')
        .map(|p| p.trim().parse().map_err(|e| format!("'{s}': {e}")))
        .collect::<Result<_, _>>()?;
    match v[..] {
        [a] => Ok([a; 3]),
        [a, b, c] => Ok([a, b, c]),
        _ => Err(format!("'{s}': expected 1 or 3 integers")),
    }
}

fn read(dir: &Path, name: &str) -> Result<(NpyValues, Vec<usize>), String> {
    let p = dir.join(name);
    let a = read_npy(&p).map_err(|e| format!("{}: {e}", p.display()))?;
    Ok((a.values, a.shape))
}

fn median_min(mut t: Vec<f64>) -> (f64, f64) {
    t.sort_by(f64::total_cmp);
    (t[0], t[t.len() / 2])
}

fn run() -> Result<(), String> {
    let a: Vec<String> = std::env::args().skip(1).collect();
    if a.len() < 8 {
        return Err("usage: conv_paths DIR X,Y,Z KX,KY,KZ S P D BATCH KIND [R]".into());
    }
    let dir = Path::new(&a[0]);
    let (shape, kernel) = (triple(&a[1])?, triple(&a[2])?);
    let (stride, padding, dilation) = (triple(&a[3])?, triple(&a[4])?, triple(&a[5])?);
    let batch: usize = a[6].parse().map_err(|e| format!("BATCH: {e}"))?;
    let kind = match a[7].as_str() {
        "subm" => MapKind::Submanifold,
        "regular" => MapKind::Regular,
        "transposed" => MapKind::Transposed {
            output_padding: [0; 3],
        },
        k => return Err(format!("KIND '{k}': subm, regular or transposed")),
    };
    let runs: usize = match a.get(8) {
        Some(r) => r.parse().map_err(|e| format!("R: {e}"))?,
        None => 9,
    };
    let (NpyValues::I32(c), _) = read(dir, "coords.npy")? else {
        return Err("coords.npy: expected int32".into());
    };
    let (NpyValues::F32(x), xs) = read(dir, "feats.npy")? else {
        return Err("feats.npy: expected float32".into());
    };
    let (NpyValues::F32(w), ws) = read(dir, "weight.npy")? else {
        return Err("weight.npy: expected float32".into());
    };
    let coords: Vec<[i32; 4]> = c.chunks(4).map(|r| [r[0], r[1], r[2], r[3]]).collect();
    let set = Arc::new(CoordSet::new(coords, shape, batch).map_err(|e| e.to_string())?);
    let geom = ConvGeometry::new(kernel)
        .with_stride(stride)
        .with_padding(padding)
        .with_dilation(dilation);
    let (_, map) = conv_map(&set, kind, geom).map_err(|e| e.to_string())?;
    let wv = WeightView {
        d0: ws[0],
        k: kernel.iter().product(),
        d2: xs[1],
        transposed: false,
    };
    map.by_output(); // built once per map, like the map itself
    let (mut ta, mut tb, mut diff) = (Vec::new(), Vec::new(), 0.0f32);
    for _ in 0..runs.max(1) {
        let t0 = Instant::now();
        let ya = conv_forward_by_offset::<f32>(&x, &w, wv, &map);
        ta.push(t0.elapsed().as_secs_f64() * 1e3);
        let t0 = Instant::now();
        let yb = conv_forward_by_output::<f32>(&x, &w, wv, &map)
            .ok_or("no fused kernels on this CPU or for these widths")?;
        tb.push(t0.elapsed().as_secs_f64() * 1e3);
        diff = ya
            .iter()
            .zip(&yb)
            .map(|(p, q)| (p - q).abs())
            .fold(diff, f32::max);
    }
    let ((amin, amed), (bmin, bmed)) = (median_min(ta), median_min(tb));
    println!(
        "{{\"pairs_per_output\":{:.3},\"offset_major_ms\":[{amin:.3},{amed:.3}],\"output_major_ms\":[{bmin:.3},{bmed:.3}],\"max_abs_diff\":{diff:.3e}}}",
        map.num_pairs() as f64 / map.n_out().max(1) as f64
    );
    Ok(())
}

fn main() {
    if let Err(e) = run() {
        eprintln!("error: {e}");
        std::process::exit(2);
    }
}
