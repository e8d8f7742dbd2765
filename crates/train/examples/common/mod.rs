//! What the diagnostic examples share: their command line, `RUN_DIR DATA_DIR SEQ [FRAMES]`.

use occ_geometry::VoxelGrid;
use occ_model::{ModelBackend, OccNet};
use occ_train::dataset::Dataset;
use occ_train::RunConfig;
use std::error::Error;
use std::path::Path;

/// A trained run and the frames to look at: the run's configuration, the grid it predicts on, the
/// trained network, sequence `SEQ` of `DATA_DIR` (loading the LiDAR scans too: the diagnostic
/// oracles read them, no other forward pass does) and how many of its frames to look at (`FRAMES`,
/// default all).
pub type Diagnosed<B> = (RunConfig, VoxelGrid, OccNet<B>, Dataset, usize);

/// Opens `RUN_DIR` and sequence `SEQ` of `DATA_DIR` from the command line of example `name`.
pub fn open_run<B: ModelBackend>(
    name: &str,
    device: &B::Device,
) -> Result<Diagnosed<B>, Box<dyn Error>> {
    let args: Vec<String> = std::env::args().collect();
    if args.len() < 4 {
        return Err(format!("usage: {name} RUN_DIR DATA_DIR SEQ [FRAMES]").into());
    }
    let (cfg, grid, model) = occ_train::trainer::load_run::<B>(Path::new(&args[1]), device)?;
    let mut ds = Dataset::open(Path::new(&args[2]), &cfg.data, &[args[3].clone()], &[])?;
    ds.set_load_points(true);
    let frames: usize = args
        .get(4)
        .map(|s| s.parse())
        .transpose()?
        .unwrap_or(ds.len());
    Ok((cfg, grid, model, ds, frames))
}
