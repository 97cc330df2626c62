//! `replay train --calibrate FILE`: the refined readout's locking curve added to a weights file.

use std::path::Path;

use anyhow::{Context, Result};
use cli::{Outcome, progress_bar};
use replay::train::calibrate_locking;
use tracing::info;

use super::options::TrainArgs;

/// Fits the locking curve of `file` and writes it (to `--weights-out`, else `file`).
pub(crate) fn run(args: &TrainArgs, file: &Path, quiet: bool) -> Result<Outcome> {
    let file = file.to_path_buf();
    let out = args.weights_out.clone().unwrap_or_else(|| file.clone());
    let bar = progress_bar(0, quiet, "captures");
    bar.set_message("the training captures' cost volumes (cached)");
    let fitted = calibrate_locking(&file, &args.dataset_dir, &out, &mut |done, total| {
        bar.set_length(total as u64);
        bar.set_position(done as u64);
    })
    .with_context(|| format!("fitting the locking curve of {}", file.display()))?;
    bar.finish_and_clear();
    info!(
        "locking curve {:?} → {}; on the {} training pixels it was fitted on, the fit's offsets were {:.4} px off the truth's on average, {:.4} px with the curve (half of it, inference's default: {:.4} px)",
        fitted.curve.0,
        out.display(),
        fitted.pixels,
        fitted.error_before_px,
        fitted.error_after_px,
        fitted.error_half_px,
    );
    Ok(Outcome::Complete)
}
