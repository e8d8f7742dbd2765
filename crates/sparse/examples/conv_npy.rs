//! Runs one sparse convolution on .npy inputs and writes .npy outputs; prints one JSON line of timings.
//!
//! ```text
//! cargo run --release -p occ-sparse --example conv_npy -- --coords C.npy --feats F.npy --weight W.npy \
//!     --spatial-shape X,Y,Z --kernel kx,ky,kz --stride s --padding p [--subm] [--repeat R] \
//!     --out-coords OC.npy --out-feats OF.npy
//! ```
//! coords int32 [N,4] (b,x,y,z); feats float32 [N,Cin]; weight float32 [Cout,kx,ky,kz,Cin]. Outputs are sorted
//! by (b,x,y,z). `ms_kernel_map` is the time to build the map (and output sites) on a fresh coordinate set;
//! `ms_compute_median` the median over R runs of the feature compute with that map. File I/O is excluded.
//! Optional: `--dilation d`, `--transposed`, `--batch-size B` (default: max batch index + 1).

use burn::backend::NdArray;
use burn::prelude::*;
use burn::tensor::TensorData;
use npyz::WriterBuilder;
use occ_sparse::backend::sparse_conv;
use occ_sparse::kernel_map::{conv_map, MapKind};
use occ_sparse::{ConvGeometry, CoordSet, SparseTensor};
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::Instant;

type B = NdArray<f32>;

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

fn read_npy<T: npyz::Deserialize>(path: &PathBuf) -> Result<(Vec<T>, Vec<usize>), String> {
    let bytes = std::fs::read(path).map_err(|e| format!("{}: {e}", path.display()))?;
    let npy = npyz::NpyFile::new(&bytes[..]).map_err(|e| format!("{}: {e}", path.display()))?;
    let shape: Vec<usize> = npy.shape().iter().map(|&s| s as usize).collect();
    if npy.order() == npyz::Order::Fortran {
        return Err(format!(
            "{}: Fortran-order array; save it C-contiguous (numpy.ascontiguousarray)",
            path.display()
        ));
    }
    let v = npy
        .into_vec::<T>()
        .map_err(|e| format!("{}: {e}", path.display()))?;
    Ok((v, shape))
}

fn write_npy<T: npyz::Serialize + npyz::AutoSerialize + Copy>(
    path: &Path,
    data: &[T],
    shape: &[u64],
) -> Result<(), String> {
    // The project's atomic writer: a fresh temporary name beside `path`, renamed when complete.
    occ_data::formats::io::write_atomic_io(path, |f| {
        let mut w = npyz::WriteOptions::<T>::new()
            .default_dtype()
            .shape(shape)
            .writer(std::io::BufWriter::new(f))
            .begin_nd()?;
        w.extend(data.iter().copied())?;
        w.finish()
    })
    .map_err(|e| format!("{}: {e}", path.display()))
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

    let (c, cs) = read_npy::<i32>(&coords_p)?;
    let (f, fs) = read_npy::<f32>(&feats_p)?;
    let (w, ws) = read_npy::<f32>(&weight_p)?;
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
    let batch = batch.unwrap_or_else(|| {
        coords
            .iter()
            .map(|c| c[0].max(0) as usize + 1)
            .max()
            .unwrap_or(1)
    });
    let dev = Default::default();
    let feats = Tensor::<B, 2>::from_data(TensorData::new(f, [fs[0], fs[1]]), &dev);
    let (cout, kv, cin) = (ws[0], kernel.iter().product::<usize>(), ws[4]);
    let weight = Tensor::<B, 3>::from_data(TensorData::new(w, [cout, kv, cin]), &dev);
    let geom = ConvGeometry::new(kernel)
        .with_stride(stride)
        .with_padding(padding)
        .with_dilation(dilation);
    let kind = if subm {
        MapKind::Submanifold
    } else if transposed {
        MapKind::Transposed {
            output_padding: [0; 3],
        }
    } else {
        MapKind::Regular
    };

    // Kernel map on a fresh set (nothing cached).
    let set = Arc::new(
        CoordSet::new(coords, shape, batch).map_err(|e| format!("{}: {e}", coords_p.display()))?,
    );
    let t0 = Instant::now();
    let (out_set, map) = conv_map(&set, kind, geom).map_err(|e| e.to_string())?;
    let ms_map = t0.elapsed().as_secs_f64() * 1e3;

    let mut times = Vec::new();
    let mut out = None;
    for _ in 0..repeat.max(1) {
        let t0 = Instant::now();
        let y = sparse_conv::<B>(feats.clone(), weight.clone(), map.clone(), false);
        let y = y.into_data(); // force completion
        times.push(t0.elapsed().as_secs_f64() * 1e3);
        out = Some(y);
    }
    times.sort_by(f64::total_cmp);
    let median = times[times.len() / 2];
    let out = Tensor::<B, 2>::from_data(out.expect("at least one run"), &dev);
    let st = SparseTensor::from_parts(out_set, out)
        .map_err(|e| e.to_string())?
        .sorted();
    let oc: Vec<i32> = st.coords().iter().flat_map(|c| c.iter().copied()).collect();
    write_npy(&oc_p, &oc, &[st.num_active() as u64, 4])?;
    write_npy(
        &of_p,
        &st.feats_to_vec(),
        &[st.num_active() as u64, cout as u64],
    )?;
    println!(
        "{{\"n_out\":{},\"pairs\":{},\"ms_kernel_map\":{:.3},\"ms_compute_median\":{:.3}}}",
        st.num_active(),
        map.num_pairs(),
        ms_map,
        median
    );
    Ok(())
}

fn main() {
    if let Err(e) = run() {
        eprintln!("error: {e}");
        std::process::exit(2);
    }
}
