//! The command-line front end of a training run ([`occ_train::run`]), shared by `train` and `demo`:
//! the run on the binary's backend, progress bars made as each phase starts, the printed milestones
//! and validation table, and `RUN/curves.png`.

use crate::backend::{self, Infer, Train};
use crate::progress;
use anyhow::Result;
use indicatif::ProgressBar;
use occ_eval::format_table;
use occ_train::run::{train_run, RunOutcome, RunProgress, RunSpec, Validation};
use occ_train::RunConfig;
use std::path::Path;

/// Trains with `cfg` on `data` into `out` ([`occ_train::run::train_run`] on the binary's backend,
/// with progress bars); validates on `cfg.data.val_sequences` when `validate`, printing the table;
/// writes `out/curves.png`.
pub fn run_with(
    cfg: &RunConfig,
    data: &Path,
    out: &Path,
    resume: bool,
    validate: bool,
) -> Result<RunOutcome<Infer>> {
    let mut bars = Bars::default();
    let spec = RunSpec {
        cfg,
        data,
        out,
        resume,
        validate,
    };
    let outcome = train_run::<Train>(spec, &backend::device(), &backend::describe(), &mut |p| {
        bars.show(p, cfg)
    })?;
    if let Some(v) = &outcome.validation {
        report_validation(v, cfg);
    }
    crate::curves::write_curves(
        out,
        outcome
            .validation
            .as_ref()
            .map(|v| (v.report.iou, v.report.miou)),
    )?;
    Ok(outcome)
}

/// The progress bars of a run, each made when its phase starts.
#[derive(Default)]
struct Bars {
    check: Option<ProgressBar>,
    steps: Option<ProgressBar>,
    predict: Option<ProgressBar>,
}

/// Sets a bar (made on first use) to `done` of `total`.
fn advance<'b>(
    bar: &'b mut Option<ProgressBar>,
    name: &str,
    done: usize,
    total: usize,
) -> &'b ProgressBar {
    let pb = bar.get_or_insert_with(|| progress::bar(total as u64, name));
    pb.set_length(total as u64);
    pb.set_position(done as u64);
    pb
}

impl Bars {
    /// Drives the bars of a run and prints its milestones.
    fn show(&mut self, p: RunProgress, cfg: &RunConfig) {
        match p {
            RunProgress::CheckData { done, total } => {
                advance(&mut self.check, "check data", done, total);
            }
            RunProgress::Started { frames, parameters } => {
                if let Some(pb) = self.check.take() {
                    pb.finish_and_clear();
                }
                let workers = match cfg.train.devices {
                    1 => String::new(),
                    n => format!(
                        ", {n} data-parallel workers of {} frames",
                        cfg.train.batch_size / n
                    ),
                };
                eprintln!(
                    "training {} on {frames} frames ({}), {} steps, {parameters} parameters, {}{workers}",
                    cfg.model.kind.name(),
                    cfg.data.train_sequences.join(","),
                    cfg.train.steps,
                    backend::describe()
                );
            }
            RunProgress::Step { step, total, log } => {
                let rate = log.frames as f64 / log.seconds.max(1e-9);
                advance(&mut self.steps, "train", step, total)
                    .set_message(format!("loss {:.3}, {rate:.2} frames/s", log.loss));
                if std::env::var_os("CI").is_some() && (step % 25 == 0 || step == total) {
                    eprintln!(
                        "  step {step}/{total} loss {:.4} ({:.2} s/step, {rate:.2} frames/s)",
                        log.loss, log.seconds
                    );
                }
            }
            RunProgress::Trained(summary) => {
                if let Some(pb) = self.steps.take() {
                    pb.finish_and_clear();
                }
                eprintln!(
                    "trained {} steps in {:.1} s (loss {:.3} -> {:.3}){}",
                    summary.steps,
                    summary.train_seconds,
                    summary.first_loss,
                    summary.last_loss,
                    summary
                        .resumed_from
                        .map(|s| format!(", resumed from step {s}"))
                        .unwrap_or_default()
                );
            }
            RunProgress::Predict { done, total } => {
                if done >= total {
                    if let Some(pb) = self.predict.take() {
                        pb.finish_and_clear();
                    }
                } else {
                    advance(&mut self.predict, "predict", done, total);
                }
            }
        }
    }
}

/// Predicts and scores the validation sequences with bars ([`occ_train::run::validate_on`]) and
/// prints the table.
pub fn validate_with_bars(
    model: &occ_model::OccNet<Infer>,
    cfg: &RunConfig,
    data: &Path,
    pred_root: &Path,
) -> Result<Validation> {
    let mut bars = Bars::default();
    let v =
        occ_train::run::validate_on(model, cfg, data, pred_root, &backend::device(), &mut |p| {
            bars.show(p, cfg)
        })?;
    report_validation(&v, cfg);
    Ok(v)
}

/// Prints the official table and a one-line summary of a validation.
pub fn report_validation(v: &Validation, cfg: &RunConfig) {
    println!("{}", format_table(&v.report));
    eprintln!(
        "validation ({}): IoU {:.3}, mIoU {:.3}, {:.3} s per frame",
        cfg.data.val_sequences.join(","),
        v.report.iou,
        v.report.miou,
        v.seconds_per_frame
    );
}
