//! # occ-train
//!
//! The training and inference pipeline shared by the three models: SemanticKITTI-layout data to
//! batches ([`dataset`]), AdamW with a no-decay parameter group, warmup + cosine schedule
//! ([`schedule`]), clipping by global norm ([`grads`]); one model's benchmark run ([`bench`](mod@bench)).

pub mod bench;
pub mod config;
pub mod dataset;
pub mod error;
pub mod grads;
pub mod infer;
pub mod log;
pub mod mirror;
pub mod parallel;
pub mod run;
pub mod schedule;
pub mod shift;
#[cfg(test)]
mod test_support;
pub mod trainer;

pub use config::{DataConfig, RunConfig};
pub use error::TrainError;
