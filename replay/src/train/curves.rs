//! The training curves: `curves.csv` (step, loss, validation; read back on resume) and
//! `curves.rrd` for Rerun.

use std::collections::HashMap;
use std::path::Path;

use serde::{Deserialize, Serialize};

use super::{RunFiles, TrainError, file_error};

/// One row of `curves.csv`.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub(super) struct CurveRow {
    /// Step done.
    pub(super) step: u64,
    /// Its loss.
    pub(super) loss: f32,
    /// Validation AvgErr (px), at the steps that validated.
    pub(super) val_avg_err_px: Option<f64>,
    /// Validation Bad1 (%), likewise.
    #[serde(alias = "val_bad1")]
    pub(super) val_bad1_percent: Option<f64>,
}

/// The rows of `curves.csv` up to step `up_to`, for a resumed run. A missing file gives none
/// (the curves restart there, with a warning); a file that does not parse is an error.
pub(super) fn read_curves(path: &Path, up_to: u64) -> Result<Vec<CurveRow>, TrainError> {
    let mut reader = match csv::Reader::from_path(path) {
        Ok(reader) => reader,
        Err(e) if matches!(e.kind(), csv::ErrorKind::Io(io) if io.kind() == std::io::ErrorKind::NotFound) => {
            tracing::warn!("{} is missing: the curves restart at the checkpoint", path.display());
            return Ok(Vec::new());
        }
        Err(e) => return Err(file_error(path, e.to_string())),
    };
    let mut rows = Vec::new();
    for row in reader.deserialize::<CurveRow>() {
        let row = row.map_err(|e| file_error(path, e.to_string()))?;
        if row.step <= up_to {
            rows.push(row);
        }
    }
    Ok(rows)
}

/// Writes `curves.csv` and `curves.rrd` (the mean loss over windows of 25 steps, and the
/// validations).
pub(super) fn write_curves(files: &RunFiles, history: &[CurveRow]) -> Result<(), TrainError> {
    let path = files.curves_csv();
    let mut writer = csv::Writer::from_path(&path).map_err(|e| file_error(&path, e.to_string()))?;
    for row in history {
        writer.serialize(row).map_err(|e| file_error(&path, e.to_string()))?;
    }
    writer.flush().map_err(|e| file_error(&path, e.to_string()))?;
    let mut series: HashMap<&str, Vec<(i64, f64)>> = HashMap::new();
    for chunk in history.chunks(25) {
        if let Some(last) = chunk.last() {
            let mean = chunk.iter().map(|r| f64::from(r.loss)).sum::<f64>() / chunk.len() as f64;
            series.entry("train/loss").or_default().push((last.step as i64, mean));
        }
    }
    for r in history {
        if let (Some(avg), Some(bad1)) = (r.val_avg_err_px, r.val_bad1_percent) {
            series.entry("val/avg_err_px").or_default().push((r.step as i64, avg));
            series
                .entry("val/bad1_percent")
                .or_default()
                .push((r.step as i64, bad1));
        }
    }
    let mut series: Vec<(&str, Vec<(i64, f64)>)> = series.into_iter().collect();
    series.sort_by(|a, b| a.0.cmp(b.0));
    viz::stream::write_curves(&files.curves_rrd(), "mfusenet_training", &series)
        .map_err(|e| file_error(&files.curves_rrd(), e.to_string()))
}
