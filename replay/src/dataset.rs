//! Image-set folders (e.g. `../shared/data/middlebury2006-third-dev`) as view sets, read through
//! `record`'s importer so that they take the same path as logs.

use std::path::Path;

use record::import::{ImportOverrides, import_set, plan_import};

use crate::ReplayError;
use crate::viewset::ViewSet;

/// Reads every set of a dataset folder as `record import` would: the settings given (`overrides`,
/// e.g. `--views`) over the folder's `multiscopic.toml` over the paper's three-view Middlebury
/// 2006 setting (view0, view1 (reference), view2; ground truth disp1 ÷ 12).
pub fn read_dataset_with(dir: &Path, overrides: &ImportOverrides) -> Result<Vec<ViewSet>, ReplayError> {
    plan_import(dir, overrides)?
        .iter()
        .enumerate()
        .map(|(index, (set_dir, config))| {
            let captured = import_set(set_dir, index as u32, config)?;
            ViewSet::from_captured(&captured)
        })
        .collect()
}

/// [`read_dataset_with`] without command-line settings.
pub fn read_dataset(dir: &Path) -> Result<Vec<ViewSet>, ReplayError> {
    read_dataset_with(dir, &ImportOverrides::default())
}

#[cfg(test)]
mod tests {
    use super::*;
    use fuse::fusion::Fusion;
    use fuse::graph_cuts::{EnergyParams, KzEnergy, Uniqueness, label_order};

    /// A `width × height` window of an RGB image at `(x0, y0)`.
    fn crop(image: &fuse::Image, x0: usize, y0: usize, width: usize, height: usize) -> fuse::Image {
        let c = image.channels;
        let mut data = Vec::with_capacity(width * height * c);
        for y in y0..y0 + height {
            data.extend_from_slice(&image.data[(y * image.width + x0) * c..(y * image.width + x0 + width) * c]);
        }
        fuse::Image::new(width, height, c, data).unwrap_or_else(|e| panic!("{e}"))
    }

    /// Graph cuts on a real Middlebury scene (a window of Aloe, three views, min fusion): every
    /// expansion's cut value is the energy of the configuration it leaves (recomputed from
    /// scratch), the energy never increases, and uniqueness holds in both neighbour views.
    #[test]
    fn graph_cut_expansions_on_real_images_never_raise_the_energy() {
        let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../shared/data/middlebury2006-third-dev");
        assert!(
            dir.is_dir(),
            "fixture missing: {} (the shared evaluation data must sit beside the checkout as ../shared/data)",
            dir.display()
        );
        let sets = read_dataset(&dir).unwrap_or_else(|e| panic!("{e}"));
        let set = sets.first().unwrap_or_else(|| panic!("no set in {}", dir.display()));
        let mut problem = set.problem(0, 24, false).unwrap_or_else(|e| panic!("{e}"));
        let (x0, y0, w, h) = (120, 100, 180, 120);
        problem.reference = crop(&problem.reference, x0, y0, w, h);
        for n in &mut problem.neighbours {
            n.image = crop(&n.image, x0, y0, w, h);
        }
        for (fusion, uniqueness) in [
            (Fusion::Min, Uniqueness::UsedViews),
            (Fusion::Mean, Uniqueness::AllViews),
        ] {
            let params = EnergyParams {
                uniqueness,
                ..EnergyParams::default()
            };
            let mut energy = KzEnergy::new(&problem, fusion, params).unwrap_or_else(|e| panic!("{e}"));
            let mut accepted = 0;
            let mut previous = energy.energy();
            for label in label_order(24, 3).into_iter().chain(label_order(24, 4)) {
                let e = energy.expand(label);
                let recomputed = energy.recompute_energy();
                assert_eq!(e.energy_before, previous, "{fusion:?} label {label}");
                if e.accepted {
                    // The cut's value is the energy of the configuration it leaves.
                    assert_eq!(e.energy_after, recomputed, "{fusion:?} label {label}");
                    assert!(e.energy_after < e.energy_before);
                    accepted += 1;
                } else {
                    assert!(e.energy_after >= e.energy_before, "{e:?}");
                    assert_eq!(recomputed, e.energy_before);
                }
                previous = recomputed;
            }
            assert!(energy.is_unique(), "{fusion:?}");
            assert!(accepted > 10, "{fusion:?}: {accepted} of 48 moves taken");
            // Most pixels are matched.
            assert!(
                energy.occluded_pixels() < w * h / 5,
                "{fusion:?}: {} occluded",
                energy.occluded_pixels()
            );
        }
    }
}
