//! Benchmark of `render_voxels` on a full 256x256x32 driving-like grid (1280x720 output).
//!
//! `cargo run --release -p occ-viz --example bench_render [-- RUNS [OUT.png [SCENE]]]` prints one
//! JSON line with the median wall time in milliseconds; with OUT.png (`-` for none) it also
//! writes the render. SCENE is `driving` (default: the procedural street scene) or `random`
//! (worst case: every voxel occupied with probability 0.5, random classes).

#[path = "common/scene.rs"]
mod scene;

use std::time::Instant;

use occ_data::image::write_png;
use occ_geometry::VoxelGrid;
use occ_viz::{render_voxels, Palette, RenderOptions};

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let runs: usize = match args.first() {
        Some(a) => a.parse()?,
        None => 9,
    };
    let grid = VoxelGrid::semantic_kitti();
    let scene_name = args.get(2).map(String::as_str).unwrap_or("driving");
    let labels = match scene_name {
        "driving" => scene::driving_scene(grid.dims, 7),
        "random" => {
            use rand::{Rng, SeedableRng};
            let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(7);
            (0..grid.num_voxels())
                .map(|_| {
                    if rng.random_bool(0.5) {
                        rng.random_range(1..20u8)
                    } else {
                        0
                    }
                })
                .collect()
        }
        other => return Err(format!("unknown scene {other:?} (driving | random)").into()),
    };
    let occupied = labels.iter().filter(|&&c| c != 0 && c != 255).count();
    let mut opts = RenderOptions::new(Palette::SemanticKitti);
    opts.title = Some(format!("synthetic {scene_name} scene, 256x256x32"));
    // Warm-up (thread pool start, page faults).
    let img = render_voxels(&labels, &grid, &opts)?;
    let mut ms = Vec::with_capacity(runs);
    for _ in 0..runs.max(1) {
        let t = Instant::now();
        let out = render_voxels(&labels, &grid, &opts)?;
        ms.push(t.elapsed().as_secs_f64() * 1e3);
        std::hint::black_box(out);
    }
    let mut sorted = ms.clone();
    sorted.sort_by(f64::total_cmp);
    let median = sorted[sorted.len() / 2];
    if let Some(path) = args.get(1).filter(|p| p.as_str() != "-") {
        write_png(std::path::Path::new(path), &img)?;
    }
    println!(
        "{{\"bench\":\"render_voxels\",\"scene\":\"{}\",\"dims\":[{},{},{}],\"occupied_voxels\":{},\"width\":{},\"height\":{},\"threads\":{},\"runs\":{},\"median_ms\":{:.2},\"min_ms\":{:.2},\"max_ms\":{:.2}}}",
        scene_name,
        grid.dims[0],
        grid.dims[1],
        grid.dims[2],
        occupied,
        opts.width,
        opts.height,
        rayon::current_num_threads(),
        ms.len(),
        median,
        sorted[0],
        sorted[sorted.len() - 1]
    );
    Ok(())
}
