//! `record`: simulate a UR10 multiscopic capture, or import an image set, into an MCAP log.
//!
//! Exit codes: 0 ok, 1 error, 2 usage, 3 finished but incomplete (interrupted with Ctrl-C,
//! SIGTERM or SIGHUP: the log holds the sets completed so far, or the viewer layout beside the
//! log could not be written).

//!
//! One module per subcommand (`simulate`: `record` itself; `import`), the value parsers in
//! `parse`; the pipelines are the library's `record::session`.

mod import;
mod options;
mod parse;
mod simulate;

use std::process::ExitCode;

use clap::{Parser, Subcommand};

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
    simulate: options::SimulateArgs,
    /// Only print errors.
    #[arg(short, long, global = true)]
    quiet: bool,
}

#[derive(Debug, Subcommand)]
enum Command {
    /// Import an image set (or a folder of sets, e.g. the Middlebury layout) into a log.
    Import(import::ImportArgs),
}

fn main() -> ExitCode {
    cli::main_with(
        |cli: &Cli| cli.quiet,
        |cli| match cli.command {
            Some(Command::Import(args)) => import::run(&args, cli.quiet),
            None => simulate::run(&cli.simulate, cli.quiet),
        },
    )
}
