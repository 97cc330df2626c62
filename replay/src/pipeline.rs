//! The per-set pipeline every subcommand shares (`replay LOG`, `eval`, `demo`): keep the
//! requested neighbours, build the matching problem (rectified if asked), run each method, check
//! the set's alignment and measure each result against the ground truth (the occlusion mask made
//! once per set, beside the problem).
//! The summaries written as JSON are the serde types here.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::sync::OnceLock;
use std::time::Instant;

use fuse::methods::{Method, Needs};
use fuse::{DisparityImage, Problem};
use serde::Serialize;

use crate::ReplayError;
use crate::check::{SetCheck, check_set};
use crate::outputs::SetOutputs;
use crate::regions::RegionMetrics;
use crate::viewset::ViewSet;

/// How sets are run.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct RunOptions {
    /// Disparities searched (default: the log's range for the set, else
    /// [`ViewSet::default_num_disparities`]).
    pub num_disparities: Option<usize>,
    /// Smallest disparity searched (signed: negative for a converged rig; default: the log's
    /// range for the set, else 0).
    pub min_disparity: Option<i32>,
    /// Only these neighbours (all when empty).
    pub neighbours: Vec<String>,
    /// De-rotate the neighbours and resample their costs by their real baseline ratio.
    pub rectify: bool,
}

/// The method names of `--method`: `all`, or a comma-separated list.
pub fn method_names(spec: &str) -> Vec<String> {
    if spec == "all" {
        fuse::methods::registry().iter().map(|e| e.name.to_owned()).collect()
    } else {
        spec.split(',')
            .map(str::trim)
            .filter(|n| !n.is_empty())
            .map(str::to_owned)
            .collect()
    }
}

/// The configuration overrides of method `name`: `overrides` as given, plus `{"weights": FILE}`
/// for the MFuseNet family when a weights file was given (other families have no weights).
pub fn overrides_for(
    name: &str,
    overrides: Option<&serde_json::Value>,
    weights: Option<&Path>,
) -> Option<serde_json::Value> {
    let learned = fuse::methods::entry(name).is_some_and(|e| e.family == fuse::methods::Family::MFuseNet);
    match (weights, learned) {
        (Some(path), true) => {
            let mut merged = overrides.and_then(|o| o.as_object().cloned()).unwrap_or_default();
            merged.insert(
                "weights".to_owned(),
                serde_json::Value::String(path.display().to_string()),
            );
            Some(serde_json::Value::Object(merged))
        }
        _ => overrides.cloned(),
    }
}

/// Builds the methods by name with their overrides (and MFuseNet's weights file).
pub fn build_methods(
    names: &[String],
    overrides: Option<&serde_json::Value>,
    weights: Option<&Path>,
) -> Result<Vec<Box<dyn Method>>, fuse::FuseError> {
    names
        .iter()
        .map(|name| fuse::methods::build(name, overrides_for(name, overrides, weights).as_ref()))
        .collect()
}

/// A set ready for the methods.
#[derive(Debug)]
pub struct PreparedSet<'a> {
    /// The set as read.
    pub set: &'a ViewSet,
    /// The set with the requested neighbours only (the set itself, not a copy, when every
    /// neighbour is requested).
    pub selected: std::borrow::Cow<'a, ViewSet>,
    /// The matching problem.
    pub problem: Problem,
    /// Smallest disparity searched.
    pub min_disparity: i32,
    /// Disparities searched.
    pub num_disparities: usize,
    /// The alignment report of the set ([`Self::alignment`]), made when first asked for.
    alignment: OnceLock<SetCheck>,
    /// The reference's ground-truth disparity ([`ViewSet::ground_truth_disparity`]), made once.
    truth: Option<Vec<f32>>,
    /// Pixels of the reference occluded in some neighbour, from the ground truth
    /// ([`Self::occluded`]), made with the problem.
    occluded: Option<Vec<bool>>,
    /// How far the alignment check's image-based shift search reaches (px).
    check_reach_px: usize,
}

/// One method's result on a set.
#[derive(Debug, Clone)]
pub struct MethodResult {
    /// The disparity of the reference view.
    pub disparity: DisparityImage,
    /// Seconds the method took.
    pub seconds: f64,
    /// Metrics against ground truth (overall, occluded, visible, specular), when known.
    pub regions: Option<RegionMetrics>,
    /// How the method worked beyond its configuration (`fuse::methods::Method::details`:
    /// MFuseNet's pyramid level and the range its network saw), `null` when nothing.
    pub details: serde_json::Value,
}

impl<'a> PreparedSet<'a> {
    /// Selects the neighbours and builds the problem. The alignment check and the occlusion
    /// mask wait until asked for ([`Self::alignment`], [`Self::occluded`]), so that neither
    /// delays the methods: `replay LOG` makes them while it writes the first result.
    pub fn new(set: &'a ViewSet, options: &RunOptions) -> Result<Self, ReplayError> {
        let (min_disparity, num_disparities) = set.search_range(options.min_disparity, options.num_disparities);
        // The image-based shift search must reach the disparities searched.
        let end = min_disparity.saturating_add(i32::try_from(num_disparities).unwrap_or(i32::MAX));
        let check_reach_px = min_disparity.unsigned_abs().max(end.unsigned_abs()) as usize;
        let selected = if options.neighbours.is_empty() {
            std::borrow::Cow::Borrowed(set)
        } else {
            std::borrow::Cow::Owned(set.with_neighbours(&options.neighbours)?)
        };
        // The occlusion mask (from the ground truth, for the evaluation) beside the problem's
        // construction, whose passes leave a thread idle, rather than after the method.
        let (problem, (truth, occluded)) = rayon::join(
            || selected.problem(min_disparity, num_disparities, options.rectify),
            || {
                let truth = set.ground_truth_disparity();
                let occluded = truth.as_deref().map(|truth| set.occlusion_mask(truth));
                (truth, occluded)
            },
        );
        Ok(Self {
            set,
            problem: problem?,
            selected,
            min_disparity,
            num_disparities,
            alignment: OnceLock::new(),
            truth,
            occluded,
            check_reach_px,
        })
    }

    /// The set's alignment report (`replay check`'s), made on the first call.
    pub fn alignment(&self) -> &SetCheck {
        self.alignment
            .get_or_init(|| check_set(self.set, self.check_reach_px, crate::check::PixelLimits::default()))
    }

    /// The reference's ground-truth disparity ([`ViewSet::ground_truth_disparity`], made once;
    /// `None` without ground truth).
    pub fn truth(&self) -> Option<&[f32]> {
        self.truth.as_deref()
    }

    /// Pixels of the reference occluded in some neighbour of the whole set (from the ground
    /// truth; `None` without one).
    pub fn occluded(&self) -> Option<&[bool]> {
        self.occluded.as_deref()
    }

    /// Runs a method and evaluates it; `progress` gets the fraction done.
    pub fn run(&self, method: &dyn Method, progress: &(dyn Fn(f32) + Sync)) -> Result<MethodResult, ReplayError> {
        let mut result = self.run_unevaluated(method, Needs::ALL, progress)?;
        result.regions = self.evaluate(&result.disparity);
        Ok(result)
    }

    /// Runs a method without evaluating it (`regions` is `None`): `replay LOG` evaluates while
    /// it writes the result files ([`crate::outputs::write_set_outputs_evaluating`]). `needs`
    /// says what of the result is read besides the disparities (a method may then skip its
    /// confidence: [`Method::run_for`]).
    pub fn run_unevaluated(
        &self,
        method: &dyn Method,
        needs: Needs,
        progress: &(dyn Fn(f32) + Sync),
    ) -> Result<MethodResult, ReplayError> {
        let started = Instant::now();
        let disparity = method
            .run_for(&self.problem, needs, progress)
            .map_err(|source| ReplayError::Fuse {
                set: self.set.index,
                source,
            })?;
        Ok(MethodResult {
            disparity,
            seconds: started.elapsed().as_secs_f64(),
            regions: None,
            details: method.details(&self.problem),
        })
    }

    /// Metrics of a disparity against the set's ground truth (overall, occluded, visible,
    /// specular), when it has one.
    pub fn evaluate(&self, disparity: &DisparityImage) -> Option<RegionMetrics> {
        let evaluating = Instant::now();
        let regions = self.truth.as_deref().zip(self.occluded()).and_then(|(truth, mask)| {
            crate::regions::region_metrics(
                &disparity.data,
                disparity.confidence.as_deref(),
                truth,
                mask,
                self.set.surface_class.as_deref(),
                self.num_disparities as f64,
            )
        });
        tracing::debug!(
            "set {}: evaluated in {:.3} s",
            self.set.index,
            evaluating.elapsed().as_secs_f64()
        );
        regions
    }
}

/// One method on one set, as `summary.json` and the result log record it.
#[derive(Debug, Clone, Serialize)]
pub struct SetSummary {
    /// Method name.
    pub method: String,
    /// Files written and metrics.
    pub outputs: SetOutputs,
    /// Seconds the method took.
    pub seconds: f64,
    /// Smallest disparity searched.
    pub min_disparity: i32,
    /// Disparities searched.
    pub num_disparities: usize,
    /// The set's alignment report.
    pub alignment: SetCheck,
    /// How the method worked beyond its configuration ([`MethodResult::details`]).
    #[serde(skip_serializing_if = "serde_json::Value::is_null")]
    pub details: serde_json::Value,
}

/// `summary.json` of a `replay LOG` run.
#[derive(Debug, Clone, Serialize)]
pub struct RunSummary {
    /// `replay`.
    pub tool: &'static str,
    /// Its version.
    pub tool_version: &'static str,
    /// The log replayed.
    pub log: PathBuf,
    /// `--method` as given.
    pub method: String,
    /// The methods run.
    pub methods: Vec<String>,
    /// Their effective configurations (one object for one method, else an array).
    pub config: serde_json::Value,
    /// `--min-disparity` as given (`null`: each set's range, see [`SetSummary`]).
    pub min_disparity: Option<i32>,
    /// Per set and method.
    pub sets: Vec<SetSummary>,
    /// Sets skipped as incomplete, with the reason.
    pub incomplete_sets: Vec<(u32, String)>,
    /// Why the log's scan stopped early, when it did.
    pub truncation: Option<String>,
    /// The log's metadata records.
    pub log_metadata: BTreeMap<String, BTreeMap<String, String>>,
    /// `--rerun` as given.
    pub rerun: Vec<String>,
    /// Seconds spent on the viewer.
    pub rerun_seconds: f64,
    /// Whether the viewer was lost.
    pub rerun_lost: bool,
    /// Seconds of the whole run.
    pub seconds: f64,
}
