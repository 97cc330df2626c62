//! `replay`: reads multiscopic logs written by `record` (or foreign logs with the same Foxglove
//! topics), rebuilds the aligned view sets, runs the fusion methods of `fuse` and evaluates them
//! against ground truth.
//!
//! - [`check`]: alignment checks of each set against the ideal rig;
//! - [`log`]: reading a log into [`viewset::ViewSet`]s (recovering what a cut-off log holds);
//! - [`salvage`]: the record walk under it that reads a cut chunk as far as it goes and skips a
//!   corrupt one;
//! - [`recover`]: `replay recover`, what survived rewritten as a finished log;
//! - [`dataset`]: image-set folders (the Middlebury layout) as view sets, through `record import`;
//! - [`demo`]: the one-command demo's capture;
//! - [`eval`]: methods over many sets, the paper's table;
//! - [`run`]: `replay LOG`, every method on every set, with its files, viewer and summary;
//! - [`outputs`]: result files per set.

pub mod check;
pub mod dataset;
pub mod demo;
pub mod eval;
pub mod foreign;
pub mod log;
pub mod outputs;
pub mod pipeline;
pub mod plan;
pub mod recover;
pub mod regions;
pub mod ros2;
pub mod run;
pub mod salvage;
pub mod train;
pub mod undistort;
pub mod viewer;
pub mod viewset;
pub mod watch;

/// Errors of replay; each names the topic, set and field it is about.
#[derive(Debug, thiserror::Error)]
pub enum ReplayError {
    /// The bytes are not a readable MCAP log.
    #[error("not a readable MCAP log")]
    Mcap {
        /// Cause.
        #[source]
        source: mcap::McapError,
    },
    /// No image of a camera stream has a pose.
    #[error(
        "no image on {topic} has a camera pose: the first (stamp {stamp_nanos} ns, frame '{frame}') has none because {reason}"
    )]
    NoPose {
        /// The image topic.
        topic: String,
        /// The image's frame id.
        frame: String,
        /// Its stamp (ns).
        stamp_nanos: u64,
        /// Why.
        reason: String,
    },
    /// A ROS 2 bag directory cannot be listed.
    #[error(transparent)]
    Bag {
        /// Cause.
        source: ::ros2::bag::BagError,
    },
    /// A file could not be read.
    #[error("cannot read '{path}'")]
    Io {
        /// File.
        path: std::path::PathBuf,
        /// Cause.
        #[source]
        source: std::io::Error,
    },
    /// A capture event does not parse.
    #[error("capture event at log time {log_time} on {topic} is malformed")]
    BadEvent {
        /// Topic.
        topic: &'static str,
        /// Log time (ns).
        log_time: u64,
        /// Cause.
        #[source]
        source: serde_json::Error,
    },
    /// A message a set needs is absent.
    #[error("set {set} view '{role}': no message on {topic} at log time {log_time}")]
    MissingMessage {
        /// Set.
        set: u32,
        /// Role.
        role: String,
        /// Topic.
        topic: String,
        /// Log time.
        log_time: u64,
    },
    /// A set lacks a view.
    #[error("set {set}: no '{role}' view")]
    MissingView {
        /// Set.
        set: u32,
        /// Role.
        role: String,
    },
    /// A message does not decode.
    #[error("set {set} topic {topic}: cannot decode {schema}: {reason}")]
    Decode {
        /// Set.
        set: u32,
        /// Topic.
        topic: String,
        /// Expected schema.
        schema: &'static str,
        /// Cause.
        reason: String,
    },
    /// An image encoding replay does not read.
    #[error(
        "set {set} topic {topic}: unsupported image encoding '{encoding}' (supported: rgb8, bgr8, rgba8, bgra8, mono8, png; from ROS 2 also mono16 and jpeg)"
    )]
    UnknownEncoding {
        /// Set.
        set: u32,
        /// Topic.
        topic: String,
        /// Encoding found.
        encoding: String,
    },
    /// A field holds an impossible value.
    #[error("set {set} topic {topic}: field {field} is invalid: {value}")]
    BadField {
        /// Set.
        set: u32,
        /// Topic.
        topic: String,
        /// Field.
        field: &'static str,
        /// The value, as text.
        value: String,
    },
    /// A `/tf` transform whose rotation is not a rotation (zero or not finite).
    #[error(
        "topic {topic}: transform {parent_frame} → {child_frame} at log time {log_time} has rotation (x, y, z, w) = {rotation_xyzw:?}, which is not a rotation (a zero or non-finite quaternion; leave the field out for no rotation)"
    )]
    BadTransform {
        /// Topic.
        topic: String,
        /// Parent frame id.
        parent_frame: String,
        /// Child frame id.
        child_frame: String,
        /// Log time (ns).
        log_time: u64,
        /// The quaternion as logged.
        rotation_xyzw: [f64; 4],
    },
    /// A view's size differs from the reference.
    #[error(
        "set {set} view '{role}' ({topic}) is {width}x{height}, the reference is {reference_width}x{reference_height}"
    )]
    SizeMismatch {
        /// Set.
        set: u32,
        /// Role.
        role: String,
        /// Topic.
        topic: String,
        /// Width.
        width: u32,
        /// Height.
        height: u32,
        /// Reference width.
        reference_width: u32,
        /// Reference height.
        reference_height: u32,
    },
    /// The algorithms rejected the set.
    #[error("set {set}")]
    Fuse {
        /// Set.
        set: u32,
        /// Cause.
        #[source]
        source: fuse::FuseError,
    },
    /// Importing a dataset folder failed.
    #[error(transparent)]
    Import(#[from] record::import::ImportError),
    /// The log holds no complete set, or none of those asked for.
    #[error("{} holds no complete view set to replay", path.display())]
    NoSets {
        /// The log.
        path: std::path::PathBuf,
    },
    /// A method failed on a set.
    #[error("set {set}: {method}")]
    InSet {
        /// Set.
        set: u32,
        /// Method.
        method: String,
        /// Cause.
        #[source]
        source: Box<ReplayError>,
    },
    /// A method's configuration does not serialise.
    #[error("method configuration")]
    MethodConfig(#[source] fuse::FuseError),
    /// Writing a result file failed.
    #[error(transparent)]
    Files(#[from] viz::files::FileError),
    /// Writing the result log failed.
    #[error("writing the result log")]
    ResultLog(#[from] record::log::LogError),
    /// A table could not be written as CSV.
    #[error("writing CSV")]
    Csv(#[from] csv::Error),
    /// A summary could not be serialised.
    #[error("serialising a summary")]
    Json(#[from] serde_json::Error),
}
