//! What the `record` and `replay` binaries share: exit codes, usage errors, logging set-up,
//! progress bars, the interrupt flag (Ctrl-C, SIGTERM, SIGHUP), the mapping from a run's outcome
//! to the process exit code, and the report of the viewer layout written beside a log.
//! Libraries never depend on it.

use std::path::Path;
use std::process::ExitCode;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, AtomicU32, Ordering};

pub use indicatif::ProgressBar;
use indicatif::ProgressStyle;

/// Exit code of an error.
pub const EXIT_ERROR: u8 = 1;
/// Exit code of invalid usage (as clap uses).
pub const EXIT_USAGE: u8 = 2;
/// Exit code of a run that finished but lost or flagged something.
pub const EXIT_INCOMPLETE: u8 = 3;

/// An error that is the user's input, not the program's: exit 2.
#[derive(Debug, thiserror::Error)]
#[error("{0}")]
pub struct UsageError(pub String);

/// How a run ended.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Outcome {
    /// Everything done.
    Complete,
    /// Finished, but something was wrong or lost (exit 3).
    Incomplete,
}

/// Parses the command line; on a usage error or `--help`, prints clap's message and returns the
/// exit code to leave with.
pub fn parse_args<P: clap::Parser>() -> Result<P, ExitCode> {
    P::try_parse().map_err(|error| {
        let code = error.exit_code();
        let _ = error.print();
        ExitCode::from(code.clamp(0, 255) as u8)
    })
}

/// The body of a binary's `main`: parses the command line (clap's message and exit code on a
/// usage error or `--help`), sets up logging (`quiet` says whether the arguments asked for
/// errors only), runs, and turns the outcome into the exit code.
pub fn main_with<P: clap::Parser>(
    quiet: impl Fn(&P) -> bool,
    run: impl FnOnce(P) -> anyhow::Result<Outcome>,
) -> ExitCode {
    let args: P = match parse_args() {
        Ok(args) => args,
        Err(code) => return code,
    };
    init_logging(quiet(&args));
    exit_code(run(args))
}

/// Logs to stderr at `info` (or `error` when quiet), overridable with `RUST_LOG`.
pub fn init_logging(quiet: bool) {
    let level = if quiet { "error" } else { "info" };
    tracing_subscriber::fmt()
        .with_env_filter(
            tracing_subscriber::EnvFilter::try_from_default_env()
                .unwrap_or_else(|_| tracing_subscriber::EnvFilter::new(level)),
        )
        .with_writer(std::io::stderr)
        .with_target(false)
        .init();
}

/// The exit code of a run; errors are printed with their causes.
pub fn exit_code(result: anyhow::Result<Outcome>) -> ExitCode {
    match result {
        Ok(Outcome::Complete) => ExitCode::SUCCESS,
        Ok(Outcome::Incomplete) => ExitCode::from(EXIT_INCOMPLETE),
        Err(error) => {
            let usage = error.chain().any(|cause| cause.is::<UsageError>());
            eprintln!("error: {error:#}");
            ExitCode::from(if usage { EXIT_USAGE } else { EXIT_ERROR })
        }
    }
}

/// A progress bar on stderr counting `unit`s (hidden when quiet; indicatif hides it off a
/// terminal).
pub fn progress_bar(total: u64, quiet: bool, unit: &str) -> ProgressBar {
    if quiet {
        return ProgressBar::hidden();
    }
    let bar = ProgressBar::new(total);
    let template =
        format!("{{spinner}} [{{elapsed_precise}}] {{bar:32}} {{pos}}/{{len}} {unit} ({{eta}} left) {{msg}}");
    if let Ok(style) = ProgressStyle::with_template(&template) {
        bar.set_style(style);
    }
    bar
}

/// Reports the viewer layout written beside a log (`record::live::write_log_blueprint`'s
/// result): how to open both, or why it could not be written; false when it failed (the run
/// then exits 3).
pub fn report_log_layout(log_path: &Path, written: Result<std::path::PathBuf, impl std::fmt::Display>) -> bool {
    match written {
        Ok(blueprint) => {
            tracing::info!(
                "open it in Rerun with its layout: rerun {} {}",
                log_path.display(),
                blueprint.display()
            );
            true
        }
        Err(e) => {
            tracing::error!("viewer layout of {} not written: {e}", log_path.display());
            false
        }
    }
}

/// A flag that the first Ctrl-C (SIGINT), SIGTERM or SIGHUP raises (printing `first`, so that the
/// run can finish what it has: a shutdown or a job scheduler's `kill` ends a recording or a
/// training run as cleanly as Ctrl-C); a second one prints `abort` and exits 130 at once. A
/// process started with SIGHUP ignored (`nohup`) keeps ignoring it.
pub fn interrupt_flag(first: &'static str, abort: &'static str) -> Arc<AtomicBool> {
    let stop = Arc::new(AtomicBool::new(false));
    let presses = AtomicU32::new(0);
    let flag = Arc::clone(&stop);
    let nohup = hangup::ignored();
    let installed = ctrlc::set_handler(move || {
        // Not `eprintln!`: it panics when the terminal is gone (a hang-up), and a panic here
        // would end the handler's thread.
        use std::io::Write;
        if presses.fetch_add(1, Ordering::SeqCst) == 0 {
            flag.store(true, Ordering::SeqCst);
            let _ = writeln!(std::io::stderr(), "\n{first}");
        } else {
            let _ = writeln!(std::io::stderr(), "\n{abort}");
            std::process::exit(130);
        }
    });
    if let Err(error) = installed {
        tracing::warn!("interrupt handler not installed: {error}");
    }
    if nohup {
        hangup::ignore();
    }
    stop
}

/// SIGHUP's disposition, which ctrlc's handler replaces: under `nohup` it is ignored, and must
/// stay so.
#[cfg(unix)]
#[allow(unsafe_code)]
mod hangup {
    use nix::sys::signal::{SaFlags, SigAction, SigHandler, SigSet, Signal, sigaction};

    fn ignoring() -> SigAction {
        SigAction::new(SigHandler::SigIgn, SaFlags::empty(), SigSet::empty())
    }

    /// Whether SIGHUP is ignored now.
    pub(super) fn ignored() -> bool {
        // SAFETY: swaps in SIG_IGN and puts the previous action back at once; no handler is
        // installed that was not there before, and SIG_IGN runs no code.
        unsafe {
            match sigaction(Signal::SIGHUP, &ignoring()) {
                Ok(previous) => {
                    let _ = sigaction(Signal::SIGHUP, &previous);
                    matches!(previous.handler(), SigHandler::SigIgn)
                }
                Err(_) => false,
            }
        }
    }

    /// Ignore SIGHUP again.
    pub(super) fn ignore() {
        // SAFETY: SIG_IGN runs no code.
        unsafe {
            let _ = sigaction(Signal::SIGHUP, &ignoring());
        }
    }
}

#[cfg(not(unix))]
mod hangup {
    pub(super) fn ignored() -> bool {
        false
    }
    pub(super) fn ignore() {}
}
