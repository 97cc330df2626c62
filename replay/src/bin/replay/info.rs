//! `replay info LOG`: what a log or ROS 2 bag holds and what replay takes from it (topics,
//! stations of a camera stream, sets with their views), and the options that steer how a camera
//! stream becomes sets (shared with `replay LOG` and `replay check`).

use std::path::PathBuf;

use anyhow::{Context, Result};
use clap::Args;
use cli::Outcome;
use replay::foreign::{StationFrame, StreamOptions};

/// How a camera stream (a ROS 2 bag of a real arm, a log without capture events) becomes sets.
#[derive(Debug, Clone, Args)]
pub struct StreamArgs {
    /// Only the images of this topic, e.g. /camera/camera/color/image_raw (default: every colour
    /// or grey image topic, of the camera frame with the most colour images).
    #[arg(long, value_name = "TOPIC")]
    pub(crate) image_topic: Option<String>,
    /// Camera poses in this frame (default: the root of the camera's transform tree, e.g.
    /// base_link or world).
    #[arg(long, value_name = "FRAME")]
    pub(crate) base_frame: Option<String>,
    /// Which frame of a settled station becomes its view: the middle one, the first, the last,
    /// or the mean of them all (less noise).
    #[arg(long, value_enum, default_value = "middle")]
    pub(crate) station_frame: StationFrame,
}

impl StreamArgs {
    /// The library's options.
    pub(crate) fn options(&self) -> StreamOptions {
        StreamOptions {
            image_topic: self.image_topic.clone(),
            base_frame: self.base_frame.clone(),
            station_frame: self.station_frame,
        }
    }
}

/// Arguments of `replay info`.
#[derive(Debug, Args)]
#[command(after_help = "Examples:\n  \
replay info capture.mcap\n  \
replay info my_bag/                      a ROS 2 bag directory (metadata.yaml, my_bag_0.mcap, …)\n  \
replay info my_bag/ --image-topic /camera/camera/color/image_raw --base-frame base_link")]
pub struct InfoArgs {
    /// The log: an MCAP file, or a ROS 2 bag directory.
    log: PathBuf,
    #[command(flatten)]
    stream: StreamArgs,
    /// Print JSON.
    #[arg(long)]
    json: bool,
}

/// Runs `replay info`.
pub fn run(args: &InfoArgs) -> Result<Outcome> {
    let info = replay::log::describe(
        &args.log,
        &replay::log::ReadOptions {
            stream: args.stream.options(),
            ..replay::log::ReadOptions::default()
        },
    )
    .with_context(|| format!("reading {}", args.log.display()))?;
    if args.json {
        println!("{}", serde_json::to_string_pretty(&info)?);
    } else {
        print!("{}", info.to_text());
    }
    Ok(if info.lost.is_empty() {
        Outcome::Complete
    } else {
        Outcome::Incomplete
    })
}
