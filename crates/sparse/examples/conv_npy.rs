//! Runs one sparse convolution on .npy inputs and writes .npy outputs; prints one JSON line of timings.
//!
//! ```text
//! cargo run --release -p occ-sparse --example conv_npy -- --coords C.npy --feats F.npy --weight W.npy \
//!     --spatial-shape X,Y,Z --kernel kx,ky,kz --stride s --padding p [--subm] [--repeat R] \
//!     --out-coords OC.npy --out-feats OF.npy
//! ```
//! coords int32 [N,4] (b,x,y,z); feats float32 [N,Cin]; weight float32 [Cout,kx,ky,kz,Cin]. Outputs are sorted
//! by (b,x,y,z). `ms_kernel_map` is the time to build the map (and output sites) on a fresh coordinate set;
//! `ms_compute_median` the median over R runs of the feature compute, `ms_total_median` of the whole call
//! (validation and sorting of the input, map, compute, output). File I/O is excluded. Inputs may be
//! C- or Fortran-order (`occ_sparse::arrays::conv3d_arrays` does the work; the Python package calls the same).
//! Optional: `--dilation d`, `--transposed`, `--batch-size B` (default: max batch index + 1).

use occ_data::formats::npy::{read_npy, write_npy, NpyValues};
use occ_sparse::arrays::{conv3d_arrays, ArrayConvKind, ArrayConvSpec};
use std::path::{Path, PathBuf};

fn triple(s: &str, what: &str) -> Result<[usize; 3], String> {
    let v: Vec<usize> = s
        .split(',')
        .map(|p| {
            p.trim()
                .parse::<usize>()
                .map_err(|e| format!("{what} '{s}': {e}"))
        })
        .collect::<Result<_, _>>()?;
    match v.len() {
        1 => Ok([v[0]; 3]),
        3 => Ok([v[0], v[1], v[2]]),
        _ => Err(format!(
            "{what} '{s}': expected 1 or 3 comma-separated integers"
        )),
    }
}

/// Reads an `.npy` array (C or Fortran order) of the expected dtype.
fn read_as<T>(
    path: &Path,
    pick: impl Fn(NpyValues) -> Option<Vec<T>>,
    dtype: &str,
) -> Result<(Vec<T>, Vec<usize>), String> {
    let a = read_npy(path).map_err(|e| e.to_string())?;
    let name = a.values.dtype_name();
    let v = pick(a.values)
        .ok_or_else(|| format!("{}: dtype {name}, expected {dtype}", path.display()))?;
    Ok((v, a.shape))
}

fn run() -> Result<(), String> {
    let mut args = std::env::args().skip(1);
    let (mut coords_p, mut feats_p, mut weight_p, mut oc_p, mut of_p) =
        (None, None, None, None, None);
    let (mut shape, mut kernel) = (None, None);
    let (mut stride, mut padding, mut dilation) = ([1; 3], [0; 3], [1; 3]);
    let (mut subm, mut transposed, mut repeat, mut batch) = (false, false, 5usize, None);
    while let Some(a) = args.next() {
        let mut val = || args.next().ok_or_else(|| format!("{a} needs a value"));
        match a.as_str() {
            "--coords" => coords_p = Some(PathBuf::from(val()?)),
            "--feats" => feats_p = Some(PathBuf::from(val()?)),
            "--weight" => weight_p = Some(PathBuf::from(val()?)),
            "--out-coords" => oc_p = Some(PathBuf::from(val()?)),
            "--out-feats" => of_p = Some(PathBuf::from(val()?)),
            "--spatial-shape" => shape = Some(triple(&val()?, "--spatial-shape")?),
            "--kernel" => kernel = Some(triple(&val()?, "--kernel")?),
            "--stride" => stride = triple(&val()?, "--stride")?,
            "--padding" => padding = triple(&val()?, "--padding")?,
            "--dilation" => dilation = triple(&val()?, "--dilation")?,
            "--repeat" => repeat = val()?.parse().map_err(|e| format!("--repeat: {e}"))?,
            "--batch-size" => {
                batch = Some(
                    val()?
                        .parse::<usize>()
                        .map_err(|e| format!("--batch-size: {e}"))?,
                )
            }
            "--subm" => subm = true,
            "--transposed" => transposed = true,
            other => return Err(format!("unknown argument {other}")),
        }
    }
    let need = |o: Option<PathBuf>, n: &str| o.ok_or_else(|| format!("missing {n}"));
    let (coords_p, feats_p, weight_p) = (
        need(coords_p, "--coords")?,
        need(feats_p, "--feats")?,
        need(weight_p, "--weight")?,
    );
    let (oc_p, of_p) = (need(oc_p, "--out-coords")?, need(of_p, "--out-feats")?);
    let shape = shape.ok_or("missing --spatial-shape")?;
    let kernel = kernel.ok_or("missing --kernel")?;

    let (c, cs) = read_as(
        &coords_p,
        |v| match v {
            NpyValues::I32(v) => Some(v),
            _ => None,
        },
        "int32",
    )?;
    let (f, fs) = read_as(
        &feats_p,
        |v| match v {
            NpyValues::F32(v) => Some(v),
            _ => None,
        },
        "float32",
    )?;
    let (w, ws) = read_as(
        &weight_p,
        |v| match v {
            NpyValues::F32(v) => Some(v),
            _ => None,
        },
        "float32",
    )?;
    if cs.len() != 2 || cs[1] != 4 {
        return Err(format!(
            "{}: coords must be int32 [N,4], got {cs:?}",
            coords_p.display()
        ));
    }
    if fs.len() != 2 || fs[0] != cs[0] {
        return Err(format!(
            "{}: feats must be float32 [N={},Cin], got {fs:?}",
            feats_p.display(),
            cs[0]
        ));
    }
    if ws.len() != 5 || ws[1..4] != kernel || ws[4] != fs[1] {
        return Err(format!(
            "{}: weight must be [Cout,{},{},{},Cin={}], got {ws:?}",
            weight_p.display(),
            kernel[0],
            kernel[1],
            kernel[2],
            fs[1]
        ));
    }
    let coords: Vec<[i32; 4]> = c.chunks(4).map(|r| [r[0], r[1], r[2], r[3]]).collect();
    let spec = ArrayConvSpec {
        spatial_shape: shape,
        kernel,
        stride,
        padding,
        dilation,
        kind: ArrayConvKind::from_flags(subm, transposed),
        batch_size: batch,
    };
    // Each repeat builds the kernel map on a fresh coordinate set (nothing cached) and computes.
    let mut times = Vec::new();
    let mut totals = Vec::new();
    let mut out = None;
    for _ in 0..repeat.max(1) {
        let t0 = std::time::Instant::now();
        let o = conv3d_arrays(coords.clone(), &f, fs[1], &w, ws[0], &spec)
            .map_err(|e| format!("{}: {e}", coords_p.display()))?;
        totals.push(t0.elapsed().as_secs_f64() * 1e3);
        times.push(o.ms_compute);
        out = Some(o);
    }
    times.sort_by(f64::total_cmp);
    let median = times[times.len() / 2];
    totals.sort_by(f64::total_cmp);
    let total = totals[totals.len() / 2];
    let out = out.expect("at least one run");
    let oc: Vec<i32> = out.coords.iter().flat_map(|c| c.iter().copied()).collect();
    let n_out = out.coords.len();
    write_npy(&oc_p, &[n_out, 4], &oc).map_err(|e| e.to_string())?;
    write_npy(&of_p, &[n_out, out.c_out], &out.feats).map_err(|e| e.to_string())?;
    println!(
        "{{\"n_out\":{},\"pairs\":{},\"ms_kernel_map\":{:.3},\"ms_compute_median\":{:.3},\"ms_total_median\":{:.3}}}",
        n_out, out.pairs, out.ms_kernel_map, median, total
    );
    Ok(())
}

fn main() {
    if let Err(e) = run() {
        eprintln!("error: {e}");
        std::process::exit(2);
    }
}
