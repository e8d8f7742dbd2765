//! Host time of a sparse U-Net's kernel maps per frame (SparseOcc++'s: four levels, SubM 3x3x3 at
//! each, strided k3 s2 p1 between them, the inverse convolutions back up), built with their host
//! pairs ([`conv_map`], the CPU path) or deferred ([`conv_map_deferred`], the cubecl backends:
//! only the strided outputs' sites on the host, the tables on the device).
//!
//! `cargo run --release -p occ-sparse --example map_host_ms -- [--repeat R]`
//! On a ground plane plus boxes in a 256x256x32 grid (SemanticKITTI's), one JSON line per mode.

use occ_sparse::kernel_map::{conv_map, conv_map_deferred, inverse_of, MapKind};
use occ_sparse::{ConvGeometry, CoordSet};
use std::sync::Arc;
use std::time::Instant;

type Build = fn(
    &Arc<CoordSet>,
    MapKind,
    ConvGeometry,
) -> occ_sparse::error::Result<(Arc<CoordSet>, Arc<occ_sparse::KernelMap>)>;

mod scene;

/// SemanticKITTI's grid, 400 boxes: 250,959 voxels.
fn scene() -> Vec<[i32; 4]> {
    let spec = scene::SceneSpec {
        shape: [256, 256, 32],
        ground_z: 4,
        slope: 180,
        boxes: 400,
        box_z: 5,
        extent: [(3, 16), (3, 24), (3, 20)],
    };
    scene::driving_scene(&spec, 7)
}

/// The maps of one frame and their transposes; returns how many.
fn frame(coords: &[[i32; 4]], build: Build) -> usize {
    let subm = ConvGeometry::new([3, 3, 3]);
    let down = ConvGeometry::new([3, 3, 3])
        .with_stride([2; 3])
        .with_padding([1; 3]);
    let mut set = Arc::new(CoordSet::new(coords.to_vec(), [256, 256, 32], 1).unwrap());
    let mut maps = Vec::new();
    let mut sets = Vec::new();
    for level in 0..4 {
        maps.push(build(&set, MapKind::Submanifold, subm).unwrap().1);
        if level < 3 {
            let (next, map) = build(&set, MapKind::Regular, down).unwrap();
            maps.push(map);
            sets.push(set);
            set = next;
        }
    }
    for _ in 0..3 {
        let (parent, map) = inverse_of(&set, down).unwrap();
        maps.push(map);
        set = parent;
    }
    // Backward passes use every map's transpose.
    let transposes: Vec<_> = maps.iter().map(|m| m.transposed()).collect();
    maps.len() + transposes.len()
}

fn main() {
    let mut repeat = 5;
    let args: Vec<String> = std::env::args().collect();
    if let Some(i) = args.iter().position(|a| a == "--repeat") {
        repeat = args.get(i + 1).and_then(|v| v.parse().ok()).unwrap_or(5);
    }
    let coords = scene();
    let modes: [(&str, Build); 2] = [("host_pairs", conv_map), ("deferred", conv_map_deferred)];
    for (name, build) in modes {
        let mut times = Vec::new();
        let mut maps = 0;
        for _ in 0..repeat {
            let t0 = Instant::now();
            maps = frame(&coords, build);
            // The set's own construction (validation, hash index) is timed in both modes.
            times.push(t0.elapsed().as_secs_f64() * 1e3);
        }
        times.sort_by(f64::total_cmp);
        println!(
            "{{\"mode\": \"{name}\", \"voxels\": {}, \"maps\": {maps}, \"median_ms\": {:.1}, \"min_ms\": {:.1}}}",
            coords.len(),
            times[times.len() / 2],
            times[0]
        );
    }
}
