//! `replay train`: train MFuseNet on synthetic captures (see `replay::train`).

mod calibrate;
mod config;
mod options;

use std::path::PathBuf;

use anyhow::{Context, Result};
use cli::{Outcome, interrupt_flag, progress_bar};
use replay::train::{TrainPaths, train, variant_name};
use tracing::info;

pub use options::TrainArgs;

/// Runs `replay train`.
pub fn run(args: &TrainArgs, quiet: bool) -> Result<Outcome> {
    if let Some(file) = &args.calibrate {
        return calibrate::run(args, file, quiet);
    }
    let config = args.config()?;
    let variant = variant_name(config.views, config.architecture);
    let dir = args
        .dir
        .clone()
        .unwrap_or_else(|| PathBuf::from("train").join(&variant));
    let weights_out = args
        .weights_out
        .clone()
        .unwrap_or_else(|| dir.join(format!("{variant}.safetensors")));
    let stop = interrupt_flag(
        "interrupt: saving a checkpoint and the weights so far (interrupt again to abort; rerun to resume)",
        "aborted",
    );
    let command = std::env::args().collect::<Vec<_>>().join(" ");
    let stages: String = config
        .crop_stages
        .iter()
        .map(|s| format!(", {0}×{0} from step {1}", s.crop_px, s.from_step))
        .collect();
    info!(
        "training {variant} ({} steps, {}×{} crops{stages}, {} disparities) in {}",
        config.steps,
        config.crop_px,
        config.crop_px,
        config.num_disparities,
        dir.display()
    );
    let dataset_bar = progress_bar((config.train_sets + config.val_sets) as u64, quiet, "captures");
    dataset_bar.set_message("simulating captures and their cost volumes (cached)");
    let step_bar = progress_bar(config.steps, quiet, "steps");
    let summary = train(
        &config,
        &TrainPaths {
            dir: &dir,
            dataset: &args.dataset_dir,
            weights: &weights_out,
        },
        &command,
        &stop,
        &mut |done, _| {
            dataset_bar.set_position(done as u64);
        },
        &mut |report| {
            if report.step == 1 || step_bar.position() == 0 {
                dataset_bar.finish_and_clear();
            }
            step_bar.set_position(report.step);
            let validation = report.validation.map_or_else(String::new, |(avg, bad1)| {
                format!(" · val AvgErr {avg:.3} px Bad1 {bad1:.1} %")
            });
            step_bar.set_message(format!(
                "loss {:.3} (mean {:.3}) · {:.2} s/step{validation}",
                report.loss, report.mean_loss, report.seconds_per_step
            ));
        },
    )
    .with_context(|| format!("training in {}", dir.display()))?;
    step_bar.finish_and_clear();
    info!(
        "{} steps in {:.0} s (dataset {:.0} s): validation AvgErr {} px, Bad1 {} % → {} (curves: {}, {})",
        summary.steps_done,
        summary.train_seconds,
        summary.dataset_seconds,
        summary.val_avg_err_px.map_or("–".into(), |v| format!("{v:.3}")),
        summary.val_bad1_percent.map_or("–".into(), |v| format!("{v:.2}")),
        summary.weights.display(),
        dir.join("curves.csv").display(),
        dir.join("curves.rrd").display()
    );
    Ok(if summary.interrupted {
        Outcome::Incomplete
    } else {
        Outcome::Complete
    })
}
