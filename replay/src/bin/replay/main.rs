//! `replay`: run depth methods on the view sets of a multiscopic log, evaluate them, or train
//! MFuseNet. One module per subcommand; the pipelines live in the `replay` library.
//!
//! Exit codes: 0 ok, 1 error, 2 usage, 3 finished but something was wrong or lost (a cut-off
//! log was recovered, sets were incomplete, the viewer was lost, or training was interrupted).

mod check;
mod demo;
mod eval;
mod info;
mod plan;
mod recover;
mod run;
mod train;
mod watch;

use std::process::ExitCode;

use anyhow::Result;
use clap::{Parser, Subcommand};
use cli::{Outcome, UsageError};

/// mimalloc keeps the network's large, short-lived tensors' pages between layers (glibc maps and
/// unmaps every allocation over 32 MB and faults and zeroes it again): MFuseNet 5 % faster on a
/// Middlebury scene, for 80 MB more peak RSS.
#[global_allocator]
static GLOBAL: mimalloc::MiMalloc = mimalloc::MiMalloc;

/// mimalloc's `mi_option_purge_delay` (the same number in its v2 and v3 headers).
const MI_OPTION_PURGE_DELAY: i32 = 15;

/// The two C functions `replay` calls at start: mimalloc's option setter and Linux's `prctl`.
#[allow(unsafe_code)]
mod ffi {
    unsafe extern "C" {
        /// mimalloc's `void mi_option_set(mi_option_t option, long value)`.
        pub(super) fn mi_option_set(option: i32, value: std::ffi::c_long);
        /// Linux's `int prctl(int option, ...)`.
        #[cfg(target_os = "linux")]
        pub(super) fn prctl(option: std::ffi::c_int, ...) -> std::ffi::c_int;
    }
}

/// Linux's `PR_SET_THP_DISABLE` (`<linux/prctl.h>`).
#[cfg(target_os = "linux")]
const PR_SET_THP_DISABLE: std::ffi::c_int = 41;

/// No transparent huge pages for this process (`prctl(PR_SET_THP_DISABLE)`; mimalloc asks for
/// them with `madvise(MADV_HUGEPAGE)` on its arenas). On virtual machines that hand freed memory
/// back to the host (free page reporting) a fresh 2 MB page faults the host as well and is
/// written at 0.5–1.1 GB/s, against 10 GB/s for one freed a moment ago: how much of a run's
/// memory is fresh depends on how long ago the last process freed it. `bm-heuristic` at 1080p:
/// 0.559 s after 5 s idle and 0.366 s back to back with huge pages, 0.439 and 0.410 s without
/// (docs/benchmarks.md, "Fresh memory"). Small pages make the time independent of what ran
/// before, at the cost of the back-to-back best case. Child processes (a spawned viewer)
/// inherit the setting.
fn no_huge_pages() {
    #[cfg(target_os = "linux")]
    // SAFETY: `prctl(PR_SET_THP_DISABLE, 1, 0, 0, 0)` only sets a flag of this process; its
    // failure (an old kernel) leaves the default, which is correct, only slower.
    #[allow(unsafe_code)]
    unsafe {
        let _ = ffi::prctl(
            PR_SET_THP_DISABLE,
            1 as std::ffi::c_ulong,
            0 as std::ffi::c_ulong,
            0 as std::ffi::c_ulong,
            0 as std::ffi::c_ulong,
        );
    }
}

/// Never hand freed pages back to the OS while the process runs: by default mimalloc purges
/// them (`madvise(MADV_DONTNEED)`, about 600 calls and 1 GB for one SGM run at 1080p), and the
/// next buffer of the same size is faulted and zeroed by the kernel again, which costs more than
/// the method on hosts where fresh memory is dear. The cost is memory: what a run freed stays
/// counted in its RSS (the demo's peak 1.35 → 1.68 GB).
fn keep_freed_pages() {
    // mimalloc's own variable, when set, decides (e.g. `MIMALLOC_PURGE_DELAY=0` for the least
    // memory).
    if std::env::var_os("MIMALLOC_PURGE_DELAY").is_some() {
        return;
    }
    // SAFETY: `mi_option_set` only stores the value in mimalloc's option table (an atomic); the
    // option number is within the table and the value is one the header documents (-1 = never).
    #[allow(unsafe_code)]
    unsafe {
        ffi::mi_option_set(MI_OPTION_PURGE_DELAY, -1);
    }
}

/// `MULTISCOPIC_NO_AVX512=1`: the hot loops keep to 256-bit vectors (and MFuseNet's products to
/// what an AVX2 host runs) on a host with AVX-512, to measure here what an AVX2-only host runs;
/// `MULTISCOPIC_NO_AMX=1`: MFuseNet's bfloat16 products stay off Intel's matrix unit.
fn narrow_vectors_if_asked() {
    if std::env::var_os("MULTISCOPIC_NO_AVX512").is_some_and(|v| v != "0") {
        fuse::wide::set_enabled(false);
    }
    if std::env::var_os("MULTISCOPIC_NO_AMX").is_some_and(|v| v != "0") {
        fuse::nn::amx_kernel::set_enabled(false);
    }
}

/// Run multiscopic depth methods on the view sets of an MCAP log (from `record`), write the
/// results and evaluate them against ground truth.
#[derive(Debug, Parser)]
#[command(name = "replay", version, args_conflicts_with_subcommands = true)]
#[command(after_help = "Examples:\n  \
    replay demo                                         record a five-view capture and replay it (start here)\n  \
    replay capture.mcap --method mfusenet --out results  the learned fusion (shipped weights)\n  \
    replay capture.mcap --method all --rerun spawn       every method, shown in the Rerun viewer\n  \
    replay capture.mcap --method gc-heuristic --config '{\"fill_occlusions\": true}'   graph cuts, occlusions filled\n  \
    replay capture.mcap --method mfusenet --config '{\"flips\": true}'   the network and its mirror image averaged (twice the time)\n  \
    replay capture.mcap --method sgm-heuristic --config '{\"weighted_median\": {}}'   depth edges snapped to colour edges (mfusenet's default)\n  \
    replay --list-methods\n  \
    replay recover .capture.mcap.partial-4242 -o capture.mcap   finish what a crash left\n  \
    replay plan capture.mcap --neighbours left --budget 2   the views that would resolve most next\n  \
    replay eval ../shared/data/middlebury2006-third-dev --methods sgm-stereo,sgm-heuristic,mfusenet-stereo,mfusenet\n  \
    replay train --views 2                               train the three-view network on simulated captures\n  \
    replay watch captures/ --method sgm-heuristic --outputs depth   replay each log the cell writes into captures/")]
struct Cli {
    #[command(subcommand)]
    command: Option<Command>,
    #[command(flatten)]
    run: run::RunArgs,
    /// List the methods with one line each and exit.
    #[arg(long)]
    list_methods: bool,
    /// Only print errors.
    #[arg(short, long, global = true)]
    quiet: bool,
}

#[derive(Debug, Subcommand)]
enum Command {
    /// Evaluate methods over logs and dataset folders; prints the paper's table.
    Eval(eval::EvalArgs),
    /// Check the alignment of every view set of a log (exit 3 when a set fails).
    Check(check::CheckArgs),
    /// What a log or ROS 2 bag holds: its files and topics, what replay reads of them, the
    /// settled stations of a camera stream and the sets they form.
    Info(info::InfoArgs),
    /// Write what survived of a cut or corrupt log (e.g. the recorder's temporary file after a
    /// crash) as a finished, indexed log, and say what was lost (exit 3 when something was).
    Recover(recover::RecoverArgs),
    /// The next best views of a set: run a method, score the grid offsets not yet taken by the
    /// pixels they would resolve, check that the arm reaches them clear of the table.
    Plan(plan::PlanArgs),
    /// The one-command demo: record a simulated five-view capture, replay it with the best
    /// method, write the results (and the log) into one folder.
    Demo(demo::DemoArgs),
    /// Train MFuseNet on simulated captures (checkpoints, resume, curves); writes safetensors weights.
    Train(train::TrainArgs),
    /// Replay each finished log that appears in a folder, in one process that stays up (a
    /// workcell: methods built once, memory warm from set to set); results in OUT/<log name>/.
    Watch(watch::WatchArgs),
}

fn main() -> ExitCode {
    no_huge_pages();
    keep_freed_pages();
    narrow_vectors_if_asked();
    cli::main_with(|cli: &Cli| cli.quiet, |cli| dispatch(&cli))
}

fn dispatch(cli: &Cli) -> Result<Outcome> {
    if cli.list_methods {
        for entry in fuse::methods::registry() {
            println!("{:<16} {}", entry.name, entry.summary);
        }
        return Ok(Outcome::Complete);
    }
    match &cli.command {
        Some(Command::Eval(args)) => eval::run(args, cli.quiet),
        Some(Command::Demo(args)) => demo::run(args, cli.quiet),
        Some(Command::Check(args)) => check::run(args),
        Some(Command::Info(args)) => info::run(args),
        Some(Command::Recover(args)) => recover::run(args),
        Some(Command::Plan(args)) => plan::run(args),
        Some(Command::Train(args)) => train::run(args, cli.quiet),
        Some(Command::Watch(args)) => watch::run(args, cli.quiet),
        None => run::run(&cli.run, cli.quiet),
    }
}

/// `--config` as JSON (a usage error when it is not).
fn parse_overrides(text: Option<&str>) -> Result<Option<serde_json::Value>> {
    text.map(|t| {
        serde_json::from_str::<serde_json::Value>(t)
            .map_err(|e| UsageError(format!("--config is not JSON: {e}")).into())
    })
    .transpose()
}

/// The methods of `--method` (a name, a list or `all`) with their overrides and MFuseNet's
/// weights. Unknown names and bad overrides are usage errors; a bad weights file is an error
/// naming the file and tensor (exit 1).
fn build_methods(
    spec: &str,
    overrides: Option<&serde_json::Value>,
    weights: Option<&std::path::Path>,
) -> Result<Vec<Box<dyn fuse::methods::Method>>> {
    let names = replay::pipeline::method_names(spec);
    if names.is_empty() {
        return Err(UsageError("--method is empty (see --list-methods)".into()).into());
    }
    replay::pipeline::build_methods(&names, overrides, weights).map_err(|e| match e {
        fuse::FuseError::MFuseNet(_) => anyhow::Error::new(e),
        e => UsageError(e.to_string()).into(),
    })
}
