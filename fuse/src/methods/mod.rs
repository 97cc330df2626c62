//! Fusion methods behind one small trait, each with a serde `Config` and `Default`, listed in
//! one registry. Adding a method: one file here implementing [`Method`], plus one line in
//! [`registry`].

pub mod block_matching;
pub mod graph_cuts;
pub mod mfusenet;
pub mod sgm;

use serde::Serialize;
use serde::de::DeserializeOwned;

use crate::FuseError;
use crate::image::DisparityImage;
use crate::volume::Problem;

/// Progress callback: the fraction of the work done, in [0, 1].
pub type Progress<'a> = &'a (dyn Fn(f32) + Sync);

/// A depth method: a problem in, the reference view's disparity out.
pub trait Method: Send + Sync {
    /// Registry name (`bm-heuristic`, …).
    fn name(&self) -> &str;
    /// The effective configuration, as JSON (for run summaries).
    fn config_json(&self) -> Result<serde_json::Value, FuseError>;
    /// Computes the disparity of the reference view (`f32::INFINITY` = no estimate).
    fn run(&self, problem: &Problem, progress: Progress<'_>) -> Result<DisparityImage, FuseError>;
    /// [`Method::run`] for a caller that reads only what `needs` asks for: a method whose
    /// confidence costs time leaves it out (`confidence: None`) where `needs.confidence` is
    /// false, its disparities the same either way. Block matching and SGM skip it (5–7 % of
    /// their time at 1080p); the other methods always give it.
    fn run_for(&self, problem: &Problem, needs: Needs, progress: Progress<'_>) -> Result<DisparityImage, FuseError> {
        let _ = needs;
        self.run(problem, progress)
    }
    /// How the method will work on `problem` beyond its configuration, as JSON for run summaries
    /// and logs (MFuseNet: the pyramid level and the range its network sees); `null` when there
    /// is nothing to add.
    fn details(&self, _problem: &Problem) -> serde_json::Value {
        serde_json::Value::Null
    }
}

/// What a run's caller reads of a result besides the disparities ([`Method::run_for`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Needs {
    /// The per-pixel confidence ([`DisparityImage::confidence`]): its result files, the
    /// evaluation's sparsification curves, viewers and result logs read it; a workcell that
    /// keeps the depth alone does not.
    pub confidence: bool,
}

impl Needs {
    /// Everything a method gives (what [`Method::run`] computes).
    pub const ALL: Self = Self { confidence: true };
    /// The disparities alone.
    pub const DISPARITY: Self = Self { confidence: false };
}

impl Default for Needs {
    fn default() -> Self {
        Self::ALL
    }
}

/// Builds a method from its default configuration with optional JSON overrides.
pub type BuildMethod = fn(Option<&serde_json::Value>) -> Result<Box<dyn Method>, FuseError>;

/// The family of a method: methods of one family share their optimiser and differ in how the
/// neighbours' costs are fused; each family has a two-view stereo member to compare with.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, serde::Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Family {
    /// Block matching with winner-take-all.
    BlockMatching,
    /// Semi-global matching.
    Sgm,
    /// MFuseNet, the learned fusion.
    MFuseNet,
    /// Graph cuts (Kolmogorov–Zabih with occlusion and uniqueness, α-expansion).
    GraphCuts,
}

impl Family {
    /// The family's two-view stereo method.
    pub fn stereo_method(self) -> &'static str {
        match self {
            Family::BlockMatching => "bm-stereo",
            Family::Sgm => "sgm-stereo",
            Family::MFuseNet => "mfusenet-stereo",
            Family::GraphCuts => "gc-stereo",
        }
    }
}

/// A registry entry.
pub struct MethodEntry {
    /// Name used on the command line.
    pub name: &'static str,
    /// One line for `--list-methods`.
    pub summary: &'static str,
    /// The method's family.
    pub family: Family,
    /// Builds the method from its default configuration, with optional JSON overrides.
    pub build: BuildMethod,
}

/// Every method, in the order `--list-methods` shows them.
pub fn registry() -> Vec<&'static MethodEntry> {
    let mut entries = Vec::new();
    entries.extend(block_matching::ENTRIES);
    entries.extend(sgm::ENTRIES);
    entries.extend(graph_cuts::ENTRIES);
    entries.extend(mfusenet::ENTRIES);
    entries
}

/// The registry entry of a method name.
pub fn entry(name: &str) -> Option<&'static MethodEntry> {
    registry().into_iter().find(|e| e.name == name)
}

/// The stereo method a method is compared with: its family's, unless it is that one.
pub fn stereo_baseline_of(name: &str) -> Option<&'static str> {
    let stereo = entry(name)?.family.stereo_method();
    (stereo != name).then_some(stereo)
}

/// Builds a method by name.
pub fn build(name: &str, overrides: Option<&serde_json::Value>) -> Result<Box<dyn Method>, FuseError> {
    match entry(name) {
        Some(entry) => (entry.build)(overrides),
        None => Err(FuseError::UnknownMethod {
            name: name.to_owned(),
            known: registry().iter().map(|e| e.name).collect::<Vec<_>>().join(", "),
        }),
    }
}

/// Applies JSON overrides (an object of fields) to a configuration; unknown fields are errors.
pub fn apply_overrides<C: Serialize + DeserializeOwned>(
    config: C,
    overrides: Option<&serde_json::Value>,
) -> Result<C, FuseError> {
    let Some(overrides) = overrides else {
        return Ok(config);
    };
    let mut value = serde_json::to_value(&config).map_err(|e| FuseError::ConfigJson {
        value: "the defaults".to_owned(),
        reason: e.to_string(),
    })?;
    match (value.as_object_mut(), overrides.as_object()) {
        (Some(base), Some(changes)) => {
            for (key, change) in changes {
                if !base.contains_key(key) {
                    return Err(FuseError::Config {
                        field: "config",
                        value: key.clone(),
                        reason: "unknown field",
                    });
                }
                base.insert(key.clone(), change.clone());
            }
        }
        _ => {
            return Err(FuseError::Config {
                field: "config",
                value: overrides.to_string(),
                reason: "overrides must be a JSON object",
            });
        }
    }
    serde_json::from_value(value).map_err(|e| FuseError::ConfigJson {
        value: overrides.to_string(),
        reason: e.to_string(),
    })
}

/// A configuration with a fusion rule: the registry builds each family's methods from its
/// defaults with the rule of the entry ([`configure`]).
pub trait FusedConfig: Default + Serialize + DeserializeOwned {
    /// Sets the cost fusion over the neighbours.
    fn set_fusion(&mut self, fusion: crate::fusion::Fusion);
}

/// The defaults of `C` with `fusion` and the JSON `overrides` applied.
pub fn configure<C: FusedConfig>(
    fusion: crate::fusion::Fusion,
    overrides: Option<&serde_json::Value>,
) -> Result<C, FuseError> {
    let mut config = C::default();
    config.set_fusion(fusion);
    apply_overrides(config, overrides)
}

/// The [`Method`] functions every method's struct with `name` and `config` fields answers alike.
macro_rules! name_and_config {
    () => {
        fn name(&self) -> &str {
            self.name
        }

        fn config_json(&self) -> Result<serde_json::Value, FuseError> {
            super::config_json(self.name, &self.config)
        }
    };
}
pub(crate) use name_and_config;

/// A method's configuration as JSON ([`Method::config_json`]).
pub fn config_json<C: Serialize>(method: &str, config: &C) -> Result<serde_json::Value, FuseError> {
    serde_json::to_value(config).map_err(|e| FuseError::ConfigJson {
        value: method.to_owned(),
        reason: e.to_string(),
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn registry_names_are_unique_and_buildable() {
        let names: Vec<&str> = registry().iter().map(|e| e.name).collect();
        let mut sorted = names.clone();
        sorted.sort_unstable();
        sorted.dedup();
        assert_eq!(sorted.len(), names.len());
        for name in names {
            let method = build(name, None).unwrap_or_else(|e| panic!("{name}: {e}"));
            assert_eq!(method.name(), name);
        }
        assert!(matches!(build("nope", None), Err(FuseError::UnknownMethod { .. })));
        let overrides = serde_json::json!({"no_such_field": 1});
        assert!(build("bm-heuristic", Some(&overrides)).is_err());
        assert_eq!(stereo_baseline_of("sgm-heuristic"), Some("sgm-stereo"));
        assert_eq!(stereo_baseline_of("mfusenet"), Some("mfusenet-stereo"));
        assert_eq!(stereo_baseline_of("gc-min"), Some("gc-stereo"));
        assert_eq!(stereo_baseline_of("bm-stereo"), None);
        assert_eq!(stereo_baseline_of("nope"), None);
    }

    #[test]
    fn each_family_fits_its_sub_pixel_curve_and_a_configuration_chooses() {
        use crate::wta::SubpixelFit;
        // Measured (docs/methods.md, "Sub-pixel fit"): the lines for SGM's census sums and MFuseNet's
        // refined estimate over them, the parabola for block matching's BT sums.
        let fit = |name: &str, overrides: Option<&serde_json::Value>| {
            build(name, overrides)
                .and_then(|m| m.config_json())
                .map(|c| c["subpixel_fit"].clone())
                .unwrap_or_else(|e| panic!("{name}: {e}"))
        };
        for (name, expected) in [
            ("sgm-heuristic", SubpixelFit::Equiangular),
            ("sgm-stereo", SubpixelFit::Equiangular),
            ("mfusenet", SubpixelFit::Equiangular),
            ("bm-heuristic", SubpixelFit::Parabola),
        ] {
            assert_eq!(fit(name, None), serde_json::json!(expected), "{name}");
        }
        let parabola = serde_json::json!({"subpixel_fit": "parabola"});
        assert_eq!(fit("sgm-mean", Some(&parabola)), serde_json::json!("parabola"));
        let wrong = serde_json::json!({"subpixel_fit": "cubic"});
        assert!(build("sgm-mean", Some(&wrong)).is_err());
    }

    /// A textured fronto-parallel plane at disparity `d` seen from a line of five: views at
    /// −2, −1, +1 and +2 baselines, shifted by `offset · d`.
    fn line_of_five(d: i64) -> Problem {
        let view = |shift: i64| crate::image::textured_view(64, 32, shift);
        crate::volume::plane_along_x(view, &[("left2", -2), ("left", -1), ("right", 1), ("right2", 2)], d, 16)
    }

    #[test]
    fn every_method_recovers_a_plane_seen_from_views_at_twice_the_baseline() {
        let d = 5;
        let problem = line_of_five(d);
        // Only the views at ±2: their costs must be sampled at 2·d.
        let far_only = Problem {
            neighbours: problem
                .neighbours
                .iter()
                .filter(|n| n.offset[0].abs() == 2)
                .cloned()
                .collect(),
            ..problem.clone()
        };
        for entry in registry() {
            for (what, p) in [("line of five", &problem), ("±2 only", &far_only)] {
                let method = build(entry.name, None).unwrap_or_else(|e| panic!("{}: {e}", entry.name));
                let disparity = method
                    .run(p, &|_| {})
                    .unwrap_or_else(|e| panic!("{} on {what}: {e}", entry.name));
                let (w, h) = (disparity.width, disparity.height);
                // Away from the borders (2·d px leave the outer views), nearly every pixel at d.
                let interior: Vec<f32> = (4..h - 4)
                    .flat_map(|y| (12..w - 12).map(move |x| (x, y)))
                    .map(|(x, y)| disparity.data[y * w + x])
                    .collect();
                let close = interior.iter().filter(|v| (**v - d as f32).abs() < 0.5).count();
                assert!(
                    close * 10 >= interior.len() * 9,
                    "{} on {what}: {close} of {} interior pixels at d = {d}",
                    entry.name,
                    interior.len()
                );
            }
        }
    }

    #[test]
    fn every_method_is_surer_of_texture_than_of_a_blank_wall() {
        // The plane at 5 px, its right half blank in every view: no cost curve, distribution or
        // label there has a peak to be sure of.
        let mut problem = line_of_five(5);
        let blank = |image: &mut crate::Image| {
            let (w, c) = (image.width, image.channels);
            for (i, v) in image.data.iter_mut().enumerate() {
                if (i / c) % w >= w / 2 {
                    *v = 128;
                }
            }
        };
        blank(&mut problem.reference);
        for n in &mut problem.neighbours {
            blank(&mut n.image);
        }
        for entry in registry() {
            let method = build(entry.name, None).unwrap_or_else(|e| panic!("{}: {e}", entry.name));
            let out = method
                .run(&problem, &|_| {})
                .unwrap_or_else(|e| panic!("{}: {e}", entry.name));
            let confidence = out
                .confidence
                .unwrap_or_else(|| panic!("{} gives no confidence", entry.name));
            assert_eq!(confidence.len(), out.data.len(), "{}", entry.name);
            assert!(
                confidence.iter().all(|c| (0.0..=1.0).contains(c)),
                "{}: a confidence outside [0, 1]",
                entry.name
            );
            let w = out.width;
            let values = |columns: std::ops::Range<usize>| -> Vec<f32> {
                (4..out.height - 4)
                    .flat_map(|y| columns.clone().map(move |x| y * w + x))
                    .map(|i| confidence[i])
                    .collect()
            };
            let (textured, mut flat) = (values(12..w / 2 - 8), values(w / 2 + 8..w - 4));
            // The chance that a textured pixel ranks above a blank one (ties count half): what
            // a robot keeping its most confident pixels relies on. Not 1: SGM's paths carry the
            // texture's evidence into the blank half (sgm-min 69 %: its summed costs have a peak
            // there; ranking by the data term alone passes 100 % here but ranks worse on
            // Middlebury, docs/experiments.md), graph cuts' min fusion finds few margins
            // (gc-min 68 %); block matching, gc-heuristic and mfusenet 99–100 %.
            flat.sort_by(f32::total_cmp);
            let above: f64 = textured
                .iter()
                .map(|t| {
                    let below = flat.partition_point(|f| f < t);
                    let tied = flat[below..].partition_point(|f| f <= t);
                    below as f64 + 0.5 * tied as f64
                })
                .sum();
            let ranked = above / (textured.len() * flat.len()) as f64;
            assert!(
                ranked >= 0.65,
                "{}: a textured pixel ranks above a blank one {:.0} % of the time",
                entry.name,
                100.0 * ranked
            );
        }
    }
}
