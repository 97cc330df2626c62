//! Evaluation of methods over many view sets: the paper's table (RMS, AvgErr, Bad0.5, Bad1,
//! Bad2 over pixels with known ground truth, averaged per scene) and the change against the
//! stereo method of the same family (`bm-*` against `bm-stereo`, `sgm-*` against `sgm-stereo`,
//! `mfusenet` against `mfusenet-stereo`; the family is on the method's registry entry).

use std::time::Instant;

use fuse::metrics::{Metrics, average};
use serde::Serialize;

use crate::ReplayError;
use crate::pipeline::{PreparedSet, RunOptions};
use crate::regions::{RankedErrors, Sparsification};
use crate::viewset::ViewSet;

/// One method's row of the table.
#[derive(Debug, Clone, Serialize)]
pub struct EvalRow {
    /// Method name.
    pub method: String,
    /// Metrics averaged over scenes.
    pub mean: Metrics,
    /// Averaged over the scenes' pixels occluded in at least one neighbour of the full set.
    pub occluded: Option<Metrics>,
    /// Averaged over specular (glossy or mirror) pixels, where the sets have surface classes.
    pub specular: Option<Metrics>,
    /// Per-scene metrics.
    pub scenes: Vec<(String, Metrics)>,
    /// The sparsification curve averaged over the scenes (AvgErr of the most confident 50, 75
    /// and 90 % of each scene's pixels).
    pub sparsification: Option<Sparsification>,
    /// The curve of every scene's pixels pooled and ranked together: what one confidence
    /// threshold for all scenes keeps (a scene the method finds hard gives up more pixels).
    pub sparsification_pooled: Option<Sparsification>,
    /// The stereo method compared against.
    pub baseline: Option<String>,
    /// Relative change of AvgErr against the baseline (%; negative = better).
    pub avg_err_change_percent: Option<f64>,
    /// Relative change of RMS against the baseline (%).
    pub rms_change_percent: Option<f64>,
    /// Total run time of the method over all scenes (s).
    pub seconds: f64,
}

/// The stereo method of a method's family (from its registry entry).
pub fn baseline_of(method: &str) -> Option<String> {
    fuse::methods::stereo_baseline_of(method).map(str::to_owned)
}

/// How methods are run during an evaluation.
#[derive(Debug, Clone, Default)]
pub struct EvalOptions {
    /// Disparities searched (default: per set, see `ViewSet::search_range`).
    pub num_disparities: Option<usize>,
    /// Smallest disparity searched, signed (default: per set, see `ViewSet::search_range`).
    pub min_disparity: Option<i32>,
    /// Configuration overrides for every method.
    pub overrides: Option<serde_json::Value>,
    /// Only these neighbours (all when empty).
    pub neighbours: Vec<String>,
    /// Resample each neighbour's costs by its real baseline ratio (from the poses).
    pub rectify: bool,
    /// MFuseNet weights instead of the shipped ones.
    pub weights: Option<std::path::PathBuf>,
    /// Express every error in pixels of disparity at this baseline (m) and take as "occluded" the
    /// pixels a view at this baseline in any of the four axis directions would not see (predicted
    /// from the ground truth): sets captured at different baselines (an adaptive rig that chose
    /// twice the baseline) then compare on the same depth errors and the same pixels. `None` =
    /// each set's own baseline and occlusions.
    pub at_baseline_m: Option<f64>,
}

/// `values` times `scale`, borrowed as they are for 1 (no common baseline asked for).
fn scaled(values: &[f32], scale: f64) -> std::borrow::Cow<'_, [f32]> {
    if scale == 1.0 {
        return values.into();
    }
    values
        .iter()
        .map(|v| (f64::from(*v) * scale) as f32)
        .collect::<Vec<_>>()
        .into()
}

/// Runs `methods` on every set with ground truth and tabulates the results.
pub fn evaluate_sets(
    sets: &[ViewSet],
    methods: &[String],
    options: &EvalOptions,
    mut on_progress: impl FnMut(&str, &str),
) -> Result<Vec<EvalRow>, ReplayError> {
    let mut rows = Vec::new();
    for name in methods {
        let overrides = crate::pipeline::overrides_for(name, options.overrides.as_ref(), options.weights.as_deref());
        let method =
            fuse::methods::build(name, overrides.as_ref()).map_err(|source| ReplayError::Fuse { set: 0, source })?;
        let mut scenes = Vec::new();
        let mut occluded = Vec::new();
        let mut specular = Vec::new();
        let mut curves = Vec::new();
        let mut pooled = RankedErrors::default();
        let started = Instant::now();
        for set in sets {
            if set.ground_truth_depth_m.is_none() {
                continue;
            }
            on_progress(name, &set.name);
            let prepared = PreparedSet::new(
                set,
                &RunOptions {
                    num_disparities: options.num_disparities,
                    min_disparity: options.min_disparity,
                    neighbours: options.neighbours.clone(),
                    rectify: options.rectify,
                },
            )?;
            let result = prepared.run(method.as_ref(), &|_| {})?;
            // Per pixel of disparity at the set's baseline, this many at the common one.
            let scale = options.at_baseline_m.map_or(1.0, |b| b / set.baseline_m);
            let missing_error_px = prepared.num_disparities as f64 * scale;
            let estimate = scaled(&result.disparity.data, scale);
            let truth = set.ground_truth_disparity().map(|t| scaled(&t, scale).into_owned());
            if let (Some(confidence), Some(truth)) = (&result.disparity.confidence, &truth) {
                pooled.extend(RankedErrors::new(&estimate, confidence, truth, missing_error_px));
            }
            let regions = match (options.at_baseline_m, &truth) {
                (Some(_), Some(truth)) => crate::regions::region_metrics(
                    &estimate,
                    result.disparity.confidence.as_deref(),
                    truth,
                    &crate::regions::hidden_from_axis_views(set.reference.camera.width as usize, truth),
                    set.surface_class.as_deref(),
                    missing_error_px,
                ),
                _ => result.regions,
            };
            if let Some(metrics) = regions {
                scenes.push((set.name.clone(), metrics.all));
                occluded.extend(metrics.occluded);
                specular.extend(metrics.specular);
                curves.extend(metrics.sparsification);
            }
        }
        let seconds = started.elapsed().as_secs_f64();
        let per_scene: Vec<Metrics> = scenes.iter().map(|(_, m)| *m).collect();
        if let Some(mean) = average(&per_scene) {
            rows.push(EvalRow {
                method: name.clone(),
                mean,
                occluded: average(&occluded),
                specular: average(&specular),
                scenes,
                // Only when every scene has a curve, so that the mean is over the same scenes.
                sparsification: if curves.len() == per_scene.len() {
                    Sparsification::average(&curves)
                } else {
                    None
                },
                sparsification_pooled: if curves.len() == per_scene.len() {
                    pooled.curve()
                } else {
                    None
                },
                baseline: None,
                avg_err_change_percent: None,
                rms_change_percent: None,
                seconds,
            });
        }
    }
    let snapshot = rows.clone();
    for row in &mut rows {
        if let Some(baseline) = baseline_of(&row.method)
            && let Some(base) = snapshot.iter().find(|r| r.method == baseline)
        {
            row.avg_err_change_percent =
                Some(100.0 * (row.mean.avg_err_px - base.mean.avg_err_px) / base.mean.avg_err_px);
            row.rms_change_percent = Some(100.0 * (row.mean.rms - base.mean.rms) / base.mean.rms);
            row.baseline = Some(baseline);
        }
    }
    Ok(rows)
}

fn change(value: Option<f64>) -> String {
    value.map_or_else(|| "–".to_owned(), |v| format!("{v:+.1} %"))
}

fn region(metrics: Option<Metrics>) -> String {
    metrics.map_or_else(|| "–".to_owned(), |m| format!("{:.3}", m.avg_err_px))
}

/// The table as Markdown.
pub fn markdown(rows: &[EvalRow]) -> String {
    let mut out = String::from(
        "| method | scenes | RMS | AvgErr | Bad0.5 (%) | Bad1 (%) | Bad2 (%) | AvgErr vs stereo | RMS vs stereo | AvgErr occluded | AvgErr specular | AvgErr most confident 50 / 75 / 90 % | most confident 75 % ÷ all, per scene / pooled | time (s) |\n",
    );
    out.push_str("|---|---|---|---|---|---|---|---|---|---|---|---|---|---|\n");
    for r in rows {
        let sparsification = r.sparsification.map_or_else(
            || "–".to_owned(),
            |s| {
                format!(
                    "{:.3} / {:.3} / {:.3}",
                    s.avg_err_top50_px, s.avg_err_top75_px, s.avg_err_top90_px
                )
            },
        );
        let ratio =
            |curve: Option<Sparsification>| curve.map_or_else(|| "–".to_owned(), |c| format!("{:.2}", c.top75_ratio()));
        let ratios = format!("{} / {}", ratio(r.sparsification), ratio(r.sparsification_pooled));
        out.push_str(&format!(
            "| {} | {} | {:.3} | {:.3} | {:.2} | {:.2} | {:.2} | {} | {} | {} | {} | {} | {} | {:.1} |\n",
            r.method,
            r.scenes.len(),
            r.mean.rms,
            r.mean.avg_err_px,
            r.mean.bad_0_5,
            r.mean.bad_1,
            r.mean.bad_2,
            change(r.avg_err_change_percent),
            change(r.rms_change_percent),
            region(r.occluded),
            region(r.specular),
            sparsification,
            ratios,
            r.seconds
        ));
    }
    out
}

/// One line of `eval.csv`: a method on a scene, or its mean over the scenes (`scene` = `mean`,
/// which alone carries the change against stereo and the sparsification curves).
#[derive(Debug, Serialize)]
struct CsvLine<'a> {
    method: &'a str,
    scene: &'a str,
    rms_px: f64,
    avg_err_px: f64,
    bad_0_5_percent: f64,
    bad_1_percent: f64,
    bad_2_percent: f64,
    pixels: usize,
    missing: usize,
    avg_err_change_percent: Option<f64>,
    avg_err_top50_px: Option<f64>,
    avg_err_top75_px: Option<f64>,
    avg_err_top90_px: Option<f64>,
    pooled_avg_err_top50_px: Option<f64>,
    pooled_avg_err_top75_px: Option<f64>,
    pooled_avg_err_top90_px: Option<f64>,
    pooled_avg_err_all_px: Option<f64>,
}

/// Rounds for the table (4 decimals; the JSON keeps every digit).
fn round4(v: f64) -> f64 {
    (v * 1e4).round() / 1e4
}

/// The rows as CSV (RFC 4180: scene names with commas or quotes are quoted), one line per method
/// and scene plus one per method for its mean.
pub fn csv(rows: &[EvalRow]) -> Result<String, ReplayError> {
    let mut writer = ::csv::Writer::from_writer(Vec::new());
    for r in rows {
        let scenes = r.scenes.iter().map(|(s, m)| (s.as_str(), m, false));
        for (scene, m, mean) in scenes.chain(std::iter::once(("mean", &r.mean, true))) {
            let curve = r.sparsification.as_ref().filter(|_| mean);
            let pooled = r.sparsification_pooled.as_ref().filter(|_| mean);
            writer.serialize(CsvLine {
                method: &r.method,
                scene,
                rms_px: round4(m.rms),
                avg_err_px: round4(m.avg_err_px),
                bad_0_5_percent: round4(m.bad_0_5),
                bad_1_percent: round4(m.bad_1),
                bad_2_percent: round4(m.bad_2),
                pixels: m.pixels,
                missing: m.missing,
                avg_err_change_percent: r.avg_err_change_percent.filter(|_| mean).map(round4),
                avg_err_top50_px: curve.map(|c| round4(c.avg_err_top50_px)),
                avg_err_top75_px: curve.map(|c| round4(c.avg_err_top75_px)),
                avg_err_top90_px: curve.map(|c| round4(c.avg_err_top90_px)),
                pooled_avg_err_top50_px: pooled.map(|c| round4(c.avg_err_top50_px)),
                pooled_avg_err_top75_px: pooled.map(|c| round4(c.avg_err_top75_px)),
                pooled_avg_err_top90_px: pooled.map(|c| round4(c.avg_err_top90_px)),
                pooled_avg_err_all_px: pooled.map(|c| round4(c.avg_err_all_px)),
            })?;
        }
    }
    let bytes = writer
        .into_inner()
        .map_err(|e| ReplayError::Csv(e.into_error().into()))?;
    Ok(String::from_utf8_lossy(&bytes).into_owned())
}

/// The view sets of `replay eval`'s inputs: a folder is read as `record import` reads it (with
/// `dataset`'s settings), a file or a ROS 2 bag directory as a log whose sets are renamed `STEM/SET` so that several logs
/// keep apart in the table.
pub fn read_inputs(
    inputs: &[std::path::PathBuf],
    dataset: &record::import::ImportOverrides,
) -> Result<Vec<ViewSet>, ReplayError> {
    let mut sets = Vec::new();
    for input in inputs {
        if input.is_dir() && !crate::log::is_bag_directory(input) {
            sets.extend(crate::dataset::read_dataset_with(input, dataset)?);
            continue;
        }
        let contents = crate::log::read_log_file(input)?;
        let stem = input
            .file_stem()
            .map(|s| s.to_string_lossy().into_owned())
            .unwrap_or_default();
        for mut set in contents.sets {
            set.name = format!("{stem}/{}", set.name);
            sets.push(set);
        }
    }
    Ok(sets)
}

/// Writes `eval.md`, `eval.csv` and `eval.json` into `dir`.
pub fn write_tables(dir: &std::path::Path, rows: &[EvalRow]) -> Result<(), ReplayError> {
    let io = |path: std::path::PathBuf| move |source| ReplayError::Io { path, source };
    std::fs::create_dir_all(dir).map_err(io(dir.to_path_buf()))?;
    let files = [
        ("eval.md", markdown(rows)),
        ("eval.csv", csv(rows)?),
        ("eval.json", serde_json::to_string_pretty(rows)?),
    ];
    for (name, text) in files {
        let path = dir.join(name);
        std::fs::write(&path, text).map_err(io(path.clone()))?;
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_csv_quotes_scene_names_and_has_the_curves_on_the_mean_row_only() {
        let metrics = Metrics {
            rms: 1.0,
            avg_err_px: 0.5,
            bad_0_5: 10.0,
            bad_1: 5.0,
            bad_2: 2.0,
            bad_0_07: 40.0,
            pixels: 100,
            missing: 0,
            bias: 0.0,
        };
        let row = EvalRow {
            method: "mfusenet".into(),
            mean: metrics,
            occluded: None,
            specular: None,
            scenes: vec![("Aloe".into(), metrics), ("log, \"quoted\"/Baby1".into(), metrics)],
            sparsification: Some(Sparsification {
                avg_err_top50_px: 0.1,
                avg_err_top75_px: 0.2,
                avg_err_top90_px: 0.3,
                avg_err_all_px: 0.5,
                oracle_avg_err_px: [0.0; 3],
            }),
            sparsification_pooled: Some(Sparsification {
                avg_err_top50_px: 0.15,
                avg_err_top75_px: 0.25,
                avg_err_top90_px: 0.35,
                avg_err_all_px: 0.5,
                oracle_avg_err_px: [0.0; 3],
            }),
            baseline: None,
            avg_err_change_percent: None,
            rms_change_percent: None,
            seconds: 1.0,
        };
        let table = csv(std::slice::from_ref(&row)).unwrap_or_else(|e| panic!("{e}"));
        let mut reader = ::csv::Reader::from_reader(table.as_bytes());
        let header = reader.headers().unwrap_or_else(|e| panic!("{e}")).clone();
        let records: Vec<::csv::StringRecord> = reader.records().map(|r| r.unwrap_or_else(|e| panic!("{e}"))).collect();
        assert_eq!(records.len(), 3, "two scenes and the mean: {table}");
        let field = |record: &::csv::StringRecord, name: &str| {
            let at = header
                .iter()
                .position(|h| h == name)
                .unwrap_or_else(|| panic!("no column {name}: {table}"));
            record.get(at).unwrap_or_default().to_owned()
        };
        // A scene name with a comma and quotes survives the round trip.
        assert_eq!(field(&records[1], "scene"), "log, \"quoted\"/Baby1");
        assert_eq!(field(&records[2], "scene"), "mean");
        assert_eq!(field(&records[2], "avg_err_px"), "0.5");
        for (column, value) in [
            ("avg_err_top50_px", "0.1"),
            ("avg_err_top75_px", "0.2"),
            ("avg_err_top90_px", "0.3"),
            ("pooled_avg_err_top50_px", "0.15"),
            ("pooled_avg_err_top75_px", "0.25"),
            ("pooled_avg_err_top90_px", "0.35"),
            ("pooled_avg_err_all_px", "0.5"),
        ] {
            assert_eq!(field(&records[2], column), value, "{column} on the mean row");
            assert_eq!(field(&records[0], column), "", "{column} on a scene's row");
        }
        assert!(
            markdown(&[row]).contains("| 0.40 / 0.50 |"),
            "the ratios per scene and pooled"
        );
    }

    #[test]
    fn baselines_are_the_family_stereo_method() {
        assert_eq!(baseline_of("bm-heuristic").as_deref(), Some("bm-stereo"));
        assert_eq!(baseline_of("sgm-min").as_deref(), Some("sgm-stereo"));
        assert_eq!(baseline_of("bm-stereo"), None);
    }
}
