//! `record`: simulate a UR10 multiscopic capture, or import an image set, into an MCAP log.
//!
//! Exit codes: 0 ok, 1 error, 2 usage, 3 finished but incomplete (interrupted with Ctrl-C: the
//! log holds the sets completed so far, or the viewer layout beside the log could not be written).

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::process::ExitCode;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, AtomicU32, Ordering};
use std::time::Instant;

use anyhow::{Context, Result};
use clap::{Args, Parser, Subcommand};
use record::capture::{
    CameraAxis, ErrorInjection, Simulation, SimulationConfig, SimulationError, ViewExposure, ViewPoseError,
};
use record::cli::{Outcome, UsageError, exit_code, init_logging, parse_args, progress_bar, write_log_layout};
use record::import::{ImportError, ImportOverrides, import_set, plan_import};
use record::live::{LiveCapture, log_layout};
use record::log::{LogOptions, METADATA_NAME, OutputFile};
use record::rig::RigKind;
use record::scene::SceneKind;
use record::session::record_simulation;
use record::{ImageFormat, TOOL_VERSION};
use tracing::{error, info, warn};
use viz::stream::{Layout, Viewer, ViewerSink};

/// Record multiscopic captures (a simulated UR10 moving a camera in its image plane) as MCAP logs
/// with Foxglove schemas and ground truth, or import real image sets into the same format.
#[derive(Debug, Parser)]
#[command(
    name = "record",
    version,
    args_conflicts_with_subcommands = true,
    subcommand_negates_reqs = true
)]
#[command(
    after_help = "Examples:\n  record --rig five-view -o capture.mcap\n  record --scene workpiece --captures 3 --image-format png -o metal.mcap\n  record --rotation-error left:z:0.5 --offset-error top:z:1 -o misaligned.mcap\n  record import ../shared/data/middlebury2006-third-dev --focal-px 1246.67 -o middlebury.mcap"
)]
struct Cli {
    #[command(subcommand)]
    command: Option<Command>,
    #[command(flatten)]
    simulate: SimulateArgs,
    /// Only print errors.
    #[arg(short, long, global = true)]
    quiet: bool,
}

#[derive(Debug, Subcommand)]
enum Command {
    /// Import an image set (or a folder of sets, e.g. the Middlebury layout) into a log.
    Import(ImportArgs),
}

fn parse_resolution(text: &str) -> Result<(u32, u32), String> {
    let (w, h) = text
        .split_once(['x', 'X'])
        .ok_or_else(|| format!("'{text}' is not WIDTHxHEIGHT, e.g. 1920x1080"))?;
    let side = |s: &str| {
        s.trim()
            .parse::<u32>()
            .ok()
            .filter(|v| (8..=16384).contains(v))
            .ok_or_else(|| format!("'{s}' in '{text}' is not a side length in 8..=16384"))
    };
    Ok((side(w)?, side(h)?))
}

fn parse_positive_mm(text: &str) -> Result<f64, String> {
    let value: f64 = text.parse().map_err(|_| format!("'{text}' is not a number"))?;
    if value > 0.0 && value <= record::capture::MAX_BASELINE_MM {
        Ok(value)
    } else {
        Err(format!(
            "{value} mm is out of range: must be > 0 and ≤ {}",
            record::capture::MAX_BASELINE_MM
        ))
    }
}

fn parse_positive_m(text: &str) -> Result<f64, String> {
    let value: f64 = text.parse().map_err(|_| format!("'{text}' is not a number"))?;
    if value.is_finite() && value > 0.0 {
        Ok(value)
    } else {
        Err(format!("{value} m is out of range: must be a distance > 0"))
    }
}

fn parse_non_negative(text: &str) -> Result<f64, String> {
    match text.parse::<f64>() {
        Ok(v) if v.is_finite() && v >= 0.0 => Ok(v),
        _ => Err(format!("'{text}' is not a non-negative number")),
    }
}

fn parse_pose_error(text: &str) -> Result<ViewPoseError, String> {
    let parts: Vec<&str> = text.split(':').collect();
    let [role, axis, value] = parts.as_slice() else {
        return Err(format!("'{text}' is not ROLE:AXIS:VALUE, e.g. left:z:0.5"));
    };
    let axis = match axis.to_ascii_lowercase().as_str() {
        "x" => CameraAxis::X,
        "y" => CameraAxis::Y,
        "z" | "roll" => CameraAxis::Z,
        other => return Err(format!("axis '{other}' in '{text}' is not x, y or z")),
    };
    let value: f64 = value
        .parse()
        .ok()
        .filter(|v: &f64| v.is_finite())
        .ok_or_else(|| format!("'{value}' in '{text}' is not a number"))?;
    Ok(ViewPoseError {
        role: (*role).to_owned(),
        axis,
        value,
    })
}

fn parse_exposure(text: &str) -> Result<ViewExposure, String> {
    let (role, gain) = text
        .split_once(':')
        .ok_or_else(|| format!("'{text}' is not ROLE:GAIN, e.g. right:1.2"))?;
    let gain: f64 = gain
        .parse()
        .ok()
        .filter(|g: &f64| g.is_finite() && *g > 0.0)
        .ok_or_else(|| format!("gain '{gain}' in '{text}' is not a positive number"))?;
    Ok(ViewExposure {
        role: role.to_owned(),
        gain,
    })
}

fn parse_triple(text: &str) -> Result<[f64; 3], String> {
    let values: Vec<f64> = text
        .split(',')
        .map(|s| {
            s.trim()
                .parse::<f64>()
                .map_err(|_| format!("'{s}' in '{text}' is not a number"))
        })
        .collect::<Result<_, _>>()?;
    <[f64; 3]>::try_from(values).map_err(|_| format!("'{text}' is not three comma-separated numbers X,Y,Z"))
}

#[derive(Debug, Args)]
struct SimulateArgs {
    /// Watch the capture in the Rerun viewer: `spawn` (start a viewer), `save FILE.rrd`, or
    /// `connect [URL]` (default rerun+http://127.0.0.1:9876/proxy).
    #[arg(long, num_args = 1..=2, value_names = ["MODE", "ARG"])]
    rerun: Vec<String>,
    /// View layout: five-view (centre, left, right, top, bottom), three-view, stereo, grid3x3,
    /// line5 (five in a row at −2 … 2 baselines).
    #[arg(long, value_enum, default_value = "five-view")]
    rig: RigKind,
    /// Distance between the centre view and each direct neighbour (mm).
    #[arg(long, default_value = "20", value_parser = parse_positive_mm)]
    baseline_mm: f64,
    /// A converged rig: every view's principal point shifted so that a plane at this distance
    /// (m) has disparity 0 (nearer points positive, farther negative; the log carries the signed
    /// working range, which replay searches).
    #[arg(long, value_name = "DIST", value_parser = parse_positive_m)]
    converge_m: Option<f64>,
    /// Number of view sets, each from a different arm station.
    #[arg(long, default_value = "1", value_parser = clap::value_parser!(u32).range(1..=10_000))]
    captures: u32,
    /// Scene: toy (textured toys), workpiece (reflective metal part on a metal table), random (from the seed).
    #[arg(long, value_enum, default_value = "toy")]
    scene: SceneKind,
    /// Seed of the scene, stations, noise and errors.
    #[arg(long, default_value = "0")]
    seed: u64,
    /// Image size WIDTHxHEIGHT (the paper's IMX322: 1920x1080).
    #[arg(long, default_value = "1920x1080", value_parser = parse_resolution)]
    resolution: (u32, u32),
    /// Horizontal field of view (degrees).
    #[arg(long, default_value = "60", value_parser = clap::value_parser!(u32).range(5..=150))]
    fov_deg: u32,
    /// Image encoding in the log: raw (foxglove.RawImage rgb8) or png (foxglove.CompressedImage).
    #[arg(long, value_enum, default_value = "raw")]
    image_format: ImageFormat,
    /// Anti-aliasing samples per pixel (4 = rotated grid).
    #[arg(long, default_value = "4", value_parser = clap::value_parser!(u32).range(1..=64))]
    samples_per_pixel: u32,
    /// Sensor noise, standard deviation in 8-bit levels.
    #[arg(long, default_value = "1.0", value_parser = parse_non_negative)]
    noise_sigma: f64,
    /// Robot repeatability: radius of the random flange position error (mm; UR10: 0.1).
    #[arg(long, default_value = "0.1", value_parser = parse_non_negative)]
    repeatability_mm: f64,
    /// Inject a rotation into a view's commanded pose: ROLE:AXIS:DEG (axis z = roll). Repeatable.
    #[arg(long, value_parser = parse_pose_error, value_name = "ROLE:AXIS:DEG")]
    rotation_error: Vec<ViewPoseError>,
    /// Inject an offset into a view's commanded pose: ROLE:AXIS:MM (axis z = out of plane). Repeatable.
    #[arg(long, value_parser = parse_pose_error, value_name = "ROLE:AXIS:MM")]
    offset_error: Vec<ViewPoseError>,
    /// Hand-eye calibration error, translation X,Y,Z (mm, flange frame).
    #[arg(long, value_parser = parse_triple, value_name = "X,Y,Z", allow_hyphen_values = true)]
    hand_eye_error_mm: Option<[f64; 3]>,
    /// Hand-eye calibration error, rotation RX,RY,RZ (degrees).
    #[arg(long, value_parser = parse_triple, value_name = "RX,RY,RZ", allow_hyphen_values = true)]
    hand_eye_error_deg: Option<[f64; 3]>,
    /// Random exposure change per view: gain uniform in [1-J, 1+J].
    #[arg(long, default_value = "0", value_parser = parse_non_negative, value_name = "J")]
    exposure_jitter: f64,
    /// Force a view's exposure gain: ROLE:GAIN. Repeatable.
    #[arg(long, value_parser = parse_exposure, value_name = "ROLE:GAIN")]
    exposure: Vec<ViewExposure>,
    /// Output log.
    #[arg(short, long, default_value = "capture.mcap")]
    output: PathBuf,
    /// zstd level of the log's chunks (1 fastest … 19 smallest).
    #[arg(long, default_value = "3", value_parser = clap::value_parser!(u32).range(1..=19))]
    zstd_level: u32,
    /// Do not write the viewer layout beside the log (`<log stem>.rbl`, opened with
    /// `rerun LOG.mcap LOG.rbl`).
    #[arg(long)]
    no_blueprint: bool,
}

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
struct ImportArgs {
    /// Folder with the view files of one set, or with one sub-folder per set (Middlebury layout).
    dir: PathBuf,
    /// Output log.
    #[arg(short, long, default_value = "import.mcap")]
    output: PathBuf,
    #[command(flatten)]
    settings: ImportOverrides,
    /// Smallest disparity to search (px, signed: negative for a converged rig), written into the
    /// log for replay (as `min_disparity` in multiscopic.toml).
    #[arg(long, value_name = "PX", allow_hyphen_values = true)]
    min_disparity: Option<i32>,
    /// Disparities to search, written into the log for replay (as `num_disparities` in
    /// multiscopic.toml).
    #[arg(long, value_name = "N", value_parser = clap::value_parser!(u32).range(1..=1024))]
    num_disparities: Option<u32>,
    /// Do not write the viewer layout beside the log (`<log stem>.rbl`, opened with
    /// `rerun LOG.mcap LOG.rbl`).
    #[arg(long)]
    no_blueprint: bool,
}

fn main() -> ExitCode {
    let cli: Cli = match parse_args() {
        Ok(cli) => cli,
        Err(code) => return code,
    };
    init_logging(cli.quiet);
    let result = match cli.command {
        Some(Command::Import(args)) => run_import(&args),
        None => run_simulation(&cli.simulate, cli.quiet),
    };
    exit_code(result)
}

fn simulation_config(args: &SimulateArgs) -> SimulationConfig {
    SimulationConfig {
        rig: args.rig,
        baseline_mm: args.baseline_mm,
        captures: args.captures,
        scene: args.scene,
        seed: args.seed,
        width: args.resolution.0,
        height: args.resolution.1,
        horizontal_fov_deg: f64::from(args.fov_deg),
        image_format: args.image_format,
        samples_per_pixel: args.samples_per_pixel,
        noise_sigma_levels: args.noise_sigma,
        errors: ErrorInjection {
            repeatability_mm: args.repeatability_mm,
            rotation_deg: args.rotation_error.clone(),
            offset_mm: args.offset_error.clone(),
            hand_eye_translation_mm: args.hand_eye_error_mm.unwrap_or_default(),
            hand_eye_rotation_deg: args.hand_eye_error_deg.unwrap_or_default(),
            exposure_jitter: args.exposure_jitter,
            exposure: args.exposure.clone(),
        },
        converge_m: args.converge_m,
        ..SimulationConfig::default()
    }
}

fn interrupt_flag() -> Arc<AtomicBool> {
    let stop = Arc::new(AtomicBool::new(false));
    let presses = AtomicU32::new(0);
    let flag = Arc::clone(&stop);
    let installed = ctrlc::set_handler(move || {
        if presses.fetch_add(1, Ordering::SeqCst) == 0 {
            flag.store(true, Ordering::SeqCst);
            eprintln!("\ninterrupt: finishing the log with the sets completed so far (Ctrl-C again to abort)");
        } else {
            eprintln!("\naborted: no log written");
            std::process::exit(130);
        }
    });
    if let Err(error) = installed {
        warn!("Ctrl-C handler not installed: {error}");
    }
    stop
}

fn run_simulation(args: &SimulateArgs, quiet: bool) -> Result<Outcome> {
    let started = Instant::now();
    let config = simulation_config(args);
    let mut sim = Simulation::new(config.clone()).map_err(|e| match e {
        SimulationError::InvalidConfig { .. } | SimulationError::UnknownRole { .. } => {
            anyhow::Error::new(UsageError(e.to_string()))
        }
        other => anyhow::Error::new(other),
    })?;
    let stop = interrupt_flag();
    let views_per_set = config.rig.capture_order().len() as u64;
    let bar = progress_bar(u64::from(config.captures) * views_per_set, quiet, "views");
    info!(
        "recording {} {} set(s) of the {} scene at {}x{}, baseline {} mm → {}",
        config.captures,
        config.rig.name(),
        config.scene_name(),
        config.width,
        config.height,
        config.baseline_mm,
        args.output.display()
    );
    let mut viewer_lost = false;
    let viewer = if args.rerun.is_empty() {
        None
    } else {
        let sink = ViewerSink::parse(&args.rerun).map_err(|e| UsageError(e.to_string()))?;
        let layout = Layout {
            roles: config.rig.capture_order().iter().map(|s| s.role.to_owned()).collect(),
            ..Layout::default()
        };
        match Viewer::create("multiscopic_record", &sink, &layout) {
            Ok(viewer) => match LiveCapture::new(viewer, sim.arm().clone()) {
                Ok(live) => Some(live),
                Err(e) => {
                    error!("Rerun: {e}\n  (the recording goes on; the log is still written)");
                    viewer_lost = true;
                    None
                }
            },
            Err(e) => {
                error!("{e}\n  (the recording goes on; the log is still written)");
                viewer_lost = true;
                None
            }
        }
    };
    let viewer_error = std::cell::Cell::new(None::<viz::stream::VizError>);
    let mut layout_of_log = None;
    let outcome = record_simulation(
        &mut sim,
        &args.output,
        args.zstd_level,
        &stop,
        |set, view| {
            bar.set_message(format!("set {set} {}", view.role));
            bar.inc(1);
            if let Some(live) = &viewer
                && let Err(e) = live.view(view)
            {
                viewer_error.set(Some(e));
            }
        },
        |set| {
            layout_of_log.get_or_insert_with(|| log_layout(set));
            bar.suspend(|| {
                info!(
                    "set {}/{} done ({} views)",
                    set.index + 1,
                    config.captures,
                    set.views.len()
                )
            });
            if let Some(live) = &viewer
                && let Err(e) = live.motion(set)
            {
                viewer_error.set(Some(e));
            }
        },
    )
    .with_context(|| format!("recording {}", args.output.display()))?;
    if let Some(live) = viewer
        && let Err(e) = live.finish()
    {
        viewer_error.set(Some(e));
    }
    if let Some(e) = viewer_error.take() {
        error!("Rerun: {e}");
        viewer_lost = true;
    }
    bar.finish_and_clear();
    let Some(path) = &outcome.path else {
        eprintln!("interrupted before the first set was complete: no log written");
        return Ok(Outcome::Incomplete);
    };
    report(path, outcome.completed_sets, started);
    if !args.no_blueprint
        && let Some(layout) = &layout_of_log
        && !write_log_layout(path, layout)
    {
        viewer_lost = true;
    }
    if outcome.interrupted() {
        warn!(
            "interrupted: the log holds {} of {} requested sets",
            outcome.completed_sets, outcome.requested_sets
        );
        return Ok(Outcome::Incomplete);
    }
    if viewer_lost {
        return Ok(Outcome::Incomplete);
    }
    Ok(Outcome::Complete)
}

fn report(path: &Path, sets: u32, started: Instant) {
    let size = std::fs::metadata(path).map(|m| m.len()).unwrap_or(0);
    info!(
        "wrote {} ({:.1} MB, {} set(s)) in {:.1} s",
        path.display(),
        size as f64 / 1e6,
        sets,
        started.elapsed().as_secs_f64()
    );
}

fn run_import(args: &ImportArgs) -> Result<Outcome> {
    let started = Instant::now();
    let usage = |e: ImportError| {
        if e.is_usage() {
            anyhow::Error::new(UsageError(e.to_string()))
        } else {
            anyhow::Error::new(e)
        }
    };
    let mut plan = plan_import(&args.dir, &args.settings).map_err(usage)?;
    for (_, config) in &mut plan {
        config.min_disparity = args.min_disparity.or(config.min_disparity);
        config.num_disparities = args.num_disparities.or(config.num_disparities);
    }
    // Every set is read before the log is started: a bad file stops the import with nothing
    // written.
    let bar = progress_bar(plan.len() as u64, false, "sets");
    let mut sets = Vec::with_capacity(plan.len());
    for (index, (dir, config)) in plan.iter().enumerate() {
        bar.set_message(dir.display().to_string());
        let set = import_set(dir, index as u32, config)
            .map_err(usage)
            .with_context(|| format!("importing {}", dir.display()))?;
        info!(
            "{}: {} views ({}), {}x{}, baseline {} mm, f {:.2} px{}",
            set.name,
            set.views.len(),
            set.views
                .iter()
                .map(|v| format!("{} {:?}", v.role, v.grid_offset))
                .collect::<Vec<_>>()
                .join(", "),
            set.views[0].camera.width,
            set.views[0].camera.height,
            set.baseline_m * 1000.0,
            set.views[0].camera.fx,
            if set.views[0].depth_m.is_some() {
                ", ground truth"
            } else {
                ""
            }
        );
        sets.push(set);
        bar.inc(1);
    }
    bar.finish_and_clear();
    let (output, writer) = OutputFile::create(&args.output).context("cannot start the output log")?;
    let mut log = LogOptions::new().create(writer)?;
    let mut layout_of_log = None;
    for set in &sets {
        layout_of_log.get_or_insert_with(|| log_layout(set));
        log.write_set(set, None)?;
    }
    let mut metadata = BTreeMap::new();
    metadata.insert("tool".to_owned(), "record import".to_owned());
    metadata.insert("tool_version".to_owned(), TOOL_VERSION.to_owned());
    metadata.insert("source".to_owned(), format!("import:{}", args.dir.display()));
    let configs: Vec<_> = plan.iter().map(|(_, config)| config).collect();
    metadata.insert("config".to_owned(), serde_json::to_string(&configs)?);
    metadata.insert("completed_sets".to_owned(), sets.len().to_string());
    log.write_metadata(METADATA_NAME, metadata)?;
    let writer = log.finish()?;
    let path = output.commit(writer)?;
    report(&path, sets.len() as u32, started);
    if !args.no_blueprint
        && let Some(layout) = &layout_of_log
        && !write_log_layout(&path, layout)
    {
        return Ok(Outcome::Incomplete);
    }
    Ok(Outcome::Complete)
}
