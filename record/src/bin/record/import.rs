//! `record import DIR`: a folder of images (one set, or one per sub-folder) into a log.

use std::path::PathBuf;
use std::time::Instant;

use anyhow::Result;
use clap::Args;
use cli::{Outcome, UsageError, progress_bar, report_log_layout};
use record::import::ImportOverrides;
use record::live::log_layout;
use record::session::{SessionError, record_import};
use tracing::info;

#[derive(Debug, Args)]
#[command(
    after_help = "View files carry their offset in baselines (FILE@DX on a line, FILE@DX:DY on a grid; the \
view at 0 is the reference). Images: PNG (8/16 bit), PPM/PGM, JPEG, TIFF, BMP. Ground truth: PNG/PGM/TIFF \
(0 = unknown) or PFM (inf = unknown), value ÷ --ground-truth-scale = disparity to a direct neighbour. A \
calib.txt (Middlebury 2014) in a set folder gives focal length, principal point, baseline and doffs. A \
multiscopic.toml beside the images (or above the set folders) holds the same settings; flags override it. \
Without either: Middlebury 2006 third size, view0@-1,view1@0,view2@1, disp1 ÷ 12, 40 mm, f = 1246.67 px.\n\n\
Examples:\n  \
record import ../shared/data/middlebury2006-third-dev -o middlebury.mcap\n  \
record import middlebury/Aloe --views view0@-1,view1@0,view2@1,view3@2,view4@3 -o aloe5.mcap\n  \
record import tsukuba --views scene1.row3.col1.ppm@-2,scene1.row3.col2.ppm@-1,scene1.row3.col3.ppm@0,\\\n    \
scene1.row3.col4.ppm@1,scene1.row3.col5.ppm@2 --ground-truth truedisp.row3.col3.pgm --ground-truth-scale 16 \\\n    \
--focal-px 615 --baseline-mm 100 -o tsukuba.mcap\n  \
record import middlebury2014/Adirondack --views im0.png@0,im1.png@1 --ground-truth disp0.pfm -o adirondack.mcap"
)]
pub struct ImportArgs {
    /// Folder with the view files of one set, or with one sub-folder per set (Middlebury layout).
    dir: PathBuf,
    /// Output log (a ROS 2 bag directory with `--format ros2`, unless it ends in .mcap).
    #[arg(short, long, default_value = "import.mcap")]
    output: PathBuf,
    /// Log format: mcap (our own log, Foxglove schemas) or ros2 (a ROS 2 bag: sensor_msgs, tf2, CDR).
    #[arg(long, value_enum, default_value = "mcap")]
    format: record::session::LogFormat,
    #[command(flatten)]
    settings: ImportOverrides,
    /// Smallest disparity to search (px, signed: negative for a converged rig), written into the
    /// log for replay (as `min_disparity` in multiscopic.toml).
    #[arg(long, value_name = "PX", allow_hyphen_values = true)]
    min_disparity: Option<i32>,
    /// Disparities to search (1 … 1024), written into the log for replay (as `num_disparities`
    /// in multiscopic.toml).
    #[arg(long, value_name = "N", value_parser = clap::value_parser!(u32).range(1..=1024))]
    num_disparities: Option<u32>,
    /// Do not write the viewer layout beside the log (`<log stem>.rbl`, opened with
    /// `rerun LOG.mcap LOG.rbl`).
    #[arg(long)]
    no_blueprint: bool,
}

/// Runs `record import`.
pub fn run(args: &ImportArgs, quiet: bool) -> Result<Outcome> {
    let started = Instant::now();
    let bar = progress_bar(0, quiet, "sets");
    let imported = record_import(
        &args.dir,
        &args.settings,
        args.min_disparity,
        args.num_disparities,
        &record::session::Output {
            path: args.output.clone(),
            format: args.format,
            zstd_level: record::log::DEFAULT_ZSTD_LEVEL,
        },
        |set| {
            bar.suspend(|| info!("{}", describe_set(set)));
            bar.inc(1);
        },
    )
    .map_err(|e| match e {
        SessionError::Plan(e) | SessionError::Import { source: e, .. } if e.is_usage() => {
            UsageError(e.to_string()).into()
        }
        e => anyhow::Error::new(e),
    })?;
    bar.finish_and_clear();
    crate::simulate::report(&imported.path, imported.sets.len() as u32, started);
    let layout_lost = !args.no_blueprint
        && args.format == record::session::LogFormat::Mcap
        && imported.sets.first().is_some_and(|set| {
            !report_log_layout(
                &imported.path,
                record::live::write_log_blueprint(&imported.path, &log_layout(set)),
            )
        });
    Ok(if layout_lost {
        Outcome::Incomplete
    } else {
        Outcome::Complete
    })
}

/// One line on an imported set: its views with their grid offsets, size, baseline, focal length.
fn describe_set(set: &record::CapturedSet) -> String {
    let Some(first) = set.views.first() else {
        return format!("{}: no views", set.name);
    };
    let views: Vec<String> = set
        .views
        .iter()
        .map(|v| format!("{} {:?}", v.role, v.grid_offset))
        .collect();
    format!(
        "{}: {} views ({}), {}x{}, baseline {} mm, f {:.2} px{}",
        set.name,
        set.views.len(),
        views.join(", "),
        first.camera.width,
        first.camera.height,
        set.baseline_m * 1000.0,
        first.camera.fx,
        if first.depth_m.is_some() { ", ground truth" } else { "" }
    )
}
