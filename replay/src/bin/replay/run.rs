//! `replay LOG --method …`: run methods on the sets of a log, write and show the results.

use std::path::PathBuf;

use anyhow::{Context, Result};
use clap::Args;
use cli::ProgressBar;
use cli::{Outcome, UsageError, progress_bar};
use replay::pipeline::RunOptions;
use replay::run::{Progress, RunRequest, replay_log};
use viz::stream::ViewerSink;

/// Arguments of `replay LOG`.
#[derive(Debug, Args)]
pub struct RunArgs {
    /// The log to replay.
    pub(crate) log: Option<PathBuf>,
    /// Method (see --list-methods); several comma-separated, or `all`.
    #[arg(long, default_value = "sgm-heuristic")]
    pub(crate) method: String,
    /// Method configuration overrides as a JSON object, e.g. '{"block_radius_px": 3}'.
    #[arg(long, value_name = "JSON")]
    pub(crate) config: Option<String>,
    /// Output directory for the result files.
    #[arg(long, default_value = "results")]
    pub(crate) out: PathBuf,
    /// Which result files each set gets: `all`, `none`, or a comma-separated list of
    /// disparity (PFM), colormap (PNG), depth (PFM in m, 16-bit PNG in mm), confidence (PFM,
    /// PNG), points (PLY), error (PNG and the signed error as PFM, with ground truth); `summary.json` and the metrics are
    /// always written. A workcell that needs only the depth: `--outputs depth` (block matching
    /// and SGM then skip their confidence, 5–7 % of their time, unless ground truth, the viewer
    /// or `--out-mcap` reads it).
    #[arg(long, default_value = "all", value_name = "FILES", value_parser = parse_outputs)]
    pub(crate) outputs: replay::outputs::ResultFiles,
    /// Disparities searched (default: the log's range for the set, else width/15 rounded up to
    /// a multiple of 16); at most 1024.
    #[arg(long)]
    pub(crate) num_disparities: Option<usize>,
    /// Smallest disparity searched, signed: negative for a converged rig, whose points beyond
    /// the distance its views converge at shift the other way (default: the log's range for the
    /// set, else 0), e.g. --min-disparity -8.
    #[arg(long, value_name = "PX", allow_hyphen_values = true)]
    pub(crate) min_disparity: Option<i32>,
    /// Only these sets (indexes, comma-separated).
    #[arg(long, value_delimiter = ',')]
    pub(crate) sets: Vec<u32>,
    /// Only images logged at least this many seconds after the log's first message.
    #[arg(long, value_name = "SECS")]
    pub(crate) start: Option<f64>,
    /// Only images logged at most this many seconds after the log's first message.
    #[arg(long, value_name = "SECS")]
    pub(crate) end: Option<f64>,
    /// Only these neighbours (roles, comma-separated), e.g. left,right for three views of a five-view set.
    #[arg(long, value_delimiter = ',')]
    pub(crate) neighbours: Vec<String>,
    /// Correct what the logged poses allow: de-rotate each neighbour (homography), resample its costs by its real baseline ratio.
    #[arg(long)]
    pub(crate) rectify: bool,
    /// Also write the results as a new MCAP log (with the input's metadata), readable by Foxglove.
    #[arg(long, value_name = "FILE")]
    pub(crate) out_mcap: Option<PathBuf>,
    /// The --out-mcap log's messages: mcap (Foxglove schemas) or ros2 (sensor_msgs Image 32FC1
    /// disparity, depth and confidence, stereo_msgs DisparityImage, PointCloud2, CameraInfo, in
    /// the reference image's frame and stamp: rviz and Foxglove show them beside the bag).
    /// Default: ros2 for a ROS 2 bag, else mcap.
    #[arg(long, value_enum, value_name = "FORMAT")]
    pub(crate) out_format: Option<replay::outputs::ResultFormat>,
    /// Show the run in the Rerun viewer: `spawn` (start a viewer), `save FILE.rrd`, or
    /// `connect [URL]` (default rerun+http://127.0.0.1:9876/proxy).
    #[arg(long, num_args = 1..=2, value_names = ["MODE", "ARG"])]
    pub(crate) rerun: Vec<String>,
    /// MFuseNet weights (safetensors, e.g. from `replay train` or exported from PyTorch) instead of the shipped ones.
    #[arg(long, value_name = "FILE")]
    pub(crate) weights: Option<PathBuf>,
    #[command(flatten)]
    pub(crate) stream: crate::info::StreamArgs,
}

pub(crate) fn parse_outputs(spec: &str) -> Result<replay::outputs::ResultFiles, String> {
    replay::outputs::ResultFiles::parse(spec).map_err(|e| e.to_string())
}

/// A method's progress bar, cleared when the method is done.
struct Bar(ProgressBar);

impl Progress for Bar {
    fn set(&self, fraction: f32) {
        self.0.set_position((fraction * 100.0) as u64);
    }
}

impl Drop for Bar {
    fn drop(&mut self) {
        self.0.finish_and_clear();
    }
}

/// A method's progress bar with `message`, drawn unless `quiet` (`replay LOG`, `replay watch`).
pub(crate) fn method_progress(message: &str, quiet: bool) -> Box<dyn Progress> {
    let bar = progress_bar(100, quiet, "%");
    bar.set_message(message.to_owned());
    Box::new(Bar(bar))
}

/// Runs `replay LOG`.
pub fn run(args: &RunArgs, quiet: bool) -> Result<Outcome> {
    let Some(log) = &args.log else {
        return Err(UsageError("no log given: replay LOG --method NAME (or --list-methods)".into()).into());
    };
    let overrides = crate::parse_overrides(args.config.as_deref())?;
    let methods = crate::build_methods(&args.method, overrides.as_ref(), args.weights.as_deref())?;
    if !args.rerun.is_empty() {
        ViewerSink::parse(&args.rerun).map_err(|e| UsageError(e.to_string()))?;
    }
    let request = RunRequest {
        log,
        methods: &methods,
        method_spec: &args.method,
        options: RunOptions {
            num_disparities: args.num_disparities,
            min_disparity: args.min_disparity,
            neighbours: args.neighbours.clone(),
            rectify: args.rectify,
        },
        sets: &args.sets,
        start_secs: args.start,
        end_secs: args.end,
        stream: args.stream.options(),
        out: &args.out,
        outputs: args.outputs,
        out_mcap: args.out_mcap.as_deref(),
        out_format: args.out_format,
        rerun: &args.rerun,
    };
    let progress = |message: &str| method_progress(message, quiet);
    let report = replay_log(&request, &progress).with_context(|| format!("replaying {}", log.display()))?;
    Ok(if report.lost_anything {
        Outcome::Incomplete
    } else {
        Outcome::Complete
    })
}
