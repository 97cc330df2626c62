//! Image-set folders (e.g. `../shared/data/middlebury2006-third-dev`) as view sets, read through
//! `record`'s importer so that they take the same path as logs.

use std::path::Path;

use record::import::{ImportConfig, find_set_dirs, import_set};

use crate::ReplayError;
use crate::viewset::ViewSet;

/// Focal length of the Middlebury 2006 scenes at third size (3740 px / 3).
pub const MIDDLEBURY_THIRD_FOCAL_PX: f64 = 3740.0 / 3.0;

/// Reads every set of a dataset folder with the importer's defaults (the paper's three-view
/// Middlebury setting: view0, view1 (reference), view2; ground truth disp1 ÷ 12).
pub fn read_dataset(dir: &Path) -> Result<Vec<ViewSet>, ReplayError> {
    let config = ImportConfig {
        focal_px: Some(MIDDLEBURY_THIRD_FOCAL_PX),
        ..ImportConfig::default()
    };
    find_set_dirs(dir, &config)?
        .iter()
        .enumerate()
        .map(|(index, set_dir)| {
            let captured = import_set(set_dir, index as u32, &config)?;
            ViewSet::from_captured(&captured)
        })
        .collect()
}
