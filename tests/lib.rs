//! Helpers for the end-to-end tests: locating (and building) the real binaries, the Python
//! reference clients, and reading logs back through the `mcap` crate.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::process::{Command, Output};
use std::sync::OnceLock;

use foxglove::messages::{FrameTransforms, RawImage};
use nalgebra::{Isometry3, Quaternion, Translation3, UnitQuaternion};
use record::log::{CAPTURE_EVENTS_TOPIC, CaptureEvent, TF_TOPIC};

/// The workspace root.
pub fn workspace_root() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .parent()
        .map(Path::to_path_buf)
        .unwrap_or_else(|| PathBuf::from("."))
}

/// `../shared/data` beside the checkout, where the real evaluation scenes live.
pub fn shared_data() -> PathBuf {
    workspace_root().join("../shared/data")
}

/// The Middlebury 2006 dev scenes (`../shared/data/middlebury2006-third-dev`, or one scene of
/// them); a missing folder fails the test with where it must be.
pub fn middlebury_dev(scene: &str) -> PathBuf {
    let path = shared_data().join("middlebury2006-third-dev").join(scene);
    assert!(
        path.is_dir(),
        "fixture missing: {} (the shared evaluation data must sit beside the checkout as ../shared/data)",
        path.display()
    );
    path
}

/// The strings of a JSON array (none when it is not one).
pub fn json_strings(value: &serde_json::Value) -> Vec<&str> {
    value
        .as_array()
        .into_iter()
        .flatten()
        .filter_map(serde_json::Value::as_str)
        .collect()
}

/// Path of a workspace binary in the profile the tests run with, built on first use so that the
/// tests never run a stale binary.
pub fn binary(name: &str) -> PathBuf {
    static BUILT: OnceLock<Result<(), String>> = OnceLock::new();
    let profile_dir = std::env::current_exe()
        .ok()
        .and_then(|exe| exe.parent().and_then(Path::parent).map(Path::to_path_buf))
        .unwrap_or_else(|| workspace_root().join("target/debug"));
    let built = BUILT.get_or_init(|| {
        let cargo = std::env::var("CARGO").unwrap_or_else(|_| "cargo".into());
        let mut command = Command::new(cargo);
        command
            .current_dir(workspace_root())
            .args(["build", "--workspace", "--bins", "--quiet"]);
        if profile_dir.ends_with("release") {
            command.arg("--release");
        }
        match command.status() {
            Ok(status) if status.success() => Ok(()),
            Ok(status) => Err(format!("cargo build of the binaries failed: {status}")),
            Err(e) => Err(format!("cannot run cargo to build the binaries: {e}")),
        }
    });
    if let Err(message) = built {
        panic!("{message}");
    }
    profile_dir.join(name)
}

/// Runs a command and returns its output (panics only if it cannot start).
pub fn run(command: &mut Command) -> Output {
    match command.output() {
        Ok(output) => output,
        Err(e) => panic!("cannot run {command:?}: {e}"),
    }
}

/// Runs `record` with arguments.
pub fn record(args: &[&str]) -> Output {
    run(Command::new(binary("record")).args(args))
}

/// Records `dir/name` with `args` (quietly), asserts success and returns the log's path.
pub fn record_log(dir: &Path, name: &str, args: &[&str]) -> PathBuf {
    let path = dir.join(name);
    let mut all = vec!["-o", path.to_str().unwrap_or_default(), "-q"];
    all.extend_from_slice(args);
    assert_success(&record(&all), "record");
    path
}

/// [`record_log`] with its arguments in one string, split at blanks (`"--resolution 160x120
/// --captures 3"`).
pub fn record_args(dir: &Path, name: &str, args: &str) -> PathBuf {
    record_log(dir, name, &args.split_whitespace().collect::<Vec<_>>())
}

/// A fresh scratch folder and a log recorded in it by `record ARGS` (split at blanks); the folder
/// lives as long as the returned guard.
pub fn recorded(name: &str, args: &str) -> (tempfile::TempDir, PathBuf) {
    let dir = temp_dir();
    let log = record_args(dir.path(), name, args);
    (dir, log)
}

/// Runs `replay LOG ARGS --out OUT -q` (ARGS split at blanks), asserts success and returns the
/// `summary.json` it wrote.
pub fn replay_summary(log: &Path, out: &Path, args: &str) -> serde_json::Value {
    let mut all = vec![log.to_str().unwrap_or_default()];
    all.extend(args.split_whitespace());
    all.extend(["--out", out.to_str().unwrap_or_default(), "-q"]);
    assert_success(&replay(&all), &format!("replay {args}"));
    let path = out.join("summary.json");
    serde_json::from_slice(&std::fs::read(&path).unwrap_or_else(|e| panic!("{}: {e}", path.display())))
        .unwrap_or_else(|e| panic!("{}: {e}", path.display()))
}

/// Runs `record` with the arguments of one string, split at blanks (paths must have none).
pub fn record_str(args: &str) -> Output {
    record(&args.split_whitespace().collect::<Vec<_>>())
}

/// Runs `replay` with the arguments of one string, split at blanks (paths must have none).
pub fn replay_str(args: &str) -> Output {
    replay(&args.split_whitespace().collect::<Vec<_>>())
}

/// Runs `replay` with arguments.
pub fn replay(args: &[&str]) -> Output {
    run(Command::new(binary("replay")).args(args))
}

/// Runs `replay eval ARGS --format json -q`, asserts success and returns its rows.
pub fn eval_json(args: &[&str]) -> Vec<serde_json::Value> {
    let mut all = vec!["eval", "--format", "json", "-q"];
    all.extend_from_slice(args);
    let output = replay(&all);
    assert_success(&output, "replay eval");
    serde_json::from_slice(&output.stdout).unwrap_or_else(|e| panic!("replay eval printed no JSON: {e}"))
}

/// Asserts success and returns stderr for messages.
pub fn assert_success(output: &Output, what: &str) {
    assert!(
        output.status.success(),
        "{what} failed with {:?}\nstdout:\n{}\nstderr:\n{}",
        output.status.code(),
        String::from_utf8_lossy(&output.stdout),
        String::from_utf8_lossy(&output.stderr)
    );
}

/// The Python interpreter with the reference MCAP clients: `$MULTISCOPIC_PYTHON`, else the
/// checkout's `.venv`, created with `tests/python/requirements.txt` on first use when missing
/// (`.ci/run` creates it up front). Panics with instructions when neither works, so that a
/// missing client fails the test instead of passing silently.
pub fn python_with_mcap() -> PathBuf {
    static PYTHON: OnceLock<Result<PathBuf, String>> = OnceLock::new();
    let found = PYTHON.get_or_init(|| {
        let has_clients = |python: &Path| {
            Command::new(python)
                .args(["-c", "import mcap, mcap_protobuf, rerun, safetensors, numpy, rosbags, mcap_ros2, PIL"])
                .output()
                .is_ok_and(|o| o.status.success())
        };
        if let Some(explicit) = std::env::var_os("MULTISCOPIC_PYTHON").map(PathBuf::from) {
            return if has_clients(&explicit) {
                Ok(explicit)
            } else {
                Err(format!(
                    "MULTISCOPIC_PYTHON={} cannot import mcap, mcap_protobuf, rerun, safetensors, numpy, rosbags, mcap_ros2 and PIL",
                    explicit.display()
                ))
            };
        }
        let root = workspace_root();
        let venv_python = root.join(".venv/bin/python");
        if !has_clients(&venv_python) {
            eprintln!(
                "setting up {} with tests/python/requirements.txt",
                root.join(".venv").display()
            );
            let created = venv_python.exists()
                || Command::new("python3")
                    .current_dir(&root)
                    .args(["-m", "venv", ".venv"])
                    .status()
                    .is_ok_and(|s| s.success());
            let installed = created
                && Command::new(&venv_python)
                    .current_dir(&root)
                    .args([
                        "-m",
                        "pip",
                        "install",
                        "--quiet",
                        "--disable-pip-version-check",
                        "-r",
                        "tests/python/requirements.txt",
                    ])
                    .status()
                    .is_ok_and(|s| s.success());
            if !installed {
                return Err(format!(
                    "could not install the Python MCAP clients into {}",
                    root.join(".venv").display()
                ));
            }
        }
        Ok(venv_python)
    });
    match found {
        Ok(python) => python.clone(),
        Err(message) => panic!(
            "the Python MCAP clients are missing: {message}. Run .ci/run (it creates .venv with \
             `pip install -r tests/python/requirements.txt`) or set MULTISCOPIC_PYTHON to an interpreter that has them."
        ),
    }
}

/// Foxglove's MCAP reader (`@mcap/core`, the library the Foxglove app reads logs with, through
/// `tests/js/read_mcap.mjs`) on a log: its report (messages per topic, chunks, attachments and
/// metadata through the summary, every chunk's CRC checked), or its error. `None`, with the
/// reason printed, where Node.js is not installed; its packages are installed into
/// `tests/js/node_modules` on first use (`npm ci`), and a failure to do so fails the test.
pub fn foxglove_read(log: &Path) -> Option<Result<serde_json::Value, String>> {
    static READY: OnceLock<Result<bool, String>> = OnceLock::new();
    let js = workspace_root().join("tests/js");
    let ready = READY.get_or_init(|| {
        if Command::new("node").arg("--version").output().is_err() {
            return Ok(false);
        }
        if !js.join("node_modules/@mcap/core").exists() {
            let installed = Command::new("npm")
                .current_dir(&js)
                .args(["ci", "--silent", "--no-audit", "--no-fund"])
                .status()
                .is_ok_and(|s| s.success());
            if !installed {
                return Err(format!("`npm ci` in {} failed", js.display()));
            }
        }
        Ok(true)
    });
    match ready {
        Ok(false) => {
            println!("skipped: Foxglove's reader needs Node.js (`node` is not installed)");
            None
        }
        Err(message) => panic!("Foxglove's MCAP reader is missing: {message}; scripts/test.sh installs it"),
        Ok(true) => {
            let output = run(Command::new("node").arg(js.join("read_mcap.mjs")).arg(log));
            Some(if output.status.success() {
                serde_json::from_slice(&output.stdout).map_err(|e| format!("read_mcap.mjs printed no JSON: {e}"))
            } else {
                Err(String::from_utf8_lossy(&output.stderr).into_owned())
            })
        }
    }
}

/// The Rerun CLI of the same environment (`rerun-sdk==0.36.3`), with analytics off.
pub fn rerun_cli() -> Command {
    let python = python_with_mcap();
    let rerun = python.with_file_name("rerun");
    let mut command = Command::new(if rerun.exists() { rerun } else { PathBuf::from("rerun") });
    command.env("RERUN_ANALYTICS", "off").env("TELEMETRY_ENABLED", "false");
    command
}

/// One message of a log.
#[derive(Debug, Clone, PartialEq)]
pub struct LoggedMessage {
    /// Topic.
    pub topic: String,
    /// Log time (ns).
    pub log_time: u64,
    /// Payload.
    pub data: Vec<u8>,
}

/// A whole log read into memory (for small test logs).
#[derive(Debug, Clone)]
pub struct Log {
    /// Messages in file order.
    pub messages: Vec<LoggedMessage>,
    /// Metadata records by name.
    pub metadata: BTreeMap<String, BTreeMap<String, String>>,
}

impl Log {
    /// Reads a log with the `mcap` crate (CRCs checked by the reader).
    pub fn read(path: &Path) -> Self {
        let bytes = std::fs::read(path).unwrap_or_else(|e| panic!("cannot read {}: {e}", path.display()));
        let mut messages = Vec::new();
        for message in mcap::MessageStream::new(&bytes).unwrap_or_else(|e| panic!("{}: {e}", path.display())) {
            let message = message.unwrap_or_else(|e| panic!("{}: {e}", path.display()));
            messages.push(LoggedMessage {
                topic: message.channel.topic.clone(),
                log_time: message.log_time,
                data: message.data.into_owned(),
            });
        }
        let mut metadata = BTreeMap::new();
        let summary = mcap::Summary::read(&bytes)
            .unwrap_or_else(|e| panic!("{}: {e}", path.display()))
            .unwrap_or_else(|| panic!("{} has no summary", path.display()));
        for index in &summary.metadata_indexes {
            let record = mcap::read::metadata(&bytes, index).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
            metadata.insert(record.name.clone(), record.metadata.clone());
        }
        Self { messages, metadata }
    }

    /// Capture events in time order.
    pub fn events(&self) -> Vec<CaptureEvent> {
        let mut events: Vec<CaptureEvent> = self
            .messages
            .iter()
            .filter(|m| m.topic == CAPTURE_EVENTS_TOPIC)
            .map(|m| serde_json::from_slice(&m.data).unwrap_or_else(|e| panic!("bad capture event: {e}")))
            .collect();
        events.sort_by_key(|e| (e.capture_time_nanos, e.set_index));
        events
    }

    /// The message on `topic` at `log_time`.
    pub fn message(&self, topic: &str, log_time: u64) -> &LoggedMessage {
        self.messages
            .iter()
            .find(|m| m.topic == topic && m.log_time == log_time)
            .unwrap_or_else(|| panic!("no message on {topic} at {log_time}"))
    }

    /// A `foxglove.RawImage` on `topic` at `log_time`.
    pub fn raw_image(&self, topic: &str, log_time: u64) -> RawImage {
        prost::Message::decode(self.message(topic, log_time).data.as_slice())
            .unwrap_or_else(|e| panic!("{topic}: not a RawImage: {e}"))
    }

    /// `world_from_<frame>` composed from the `/tf` message at `log_time`.
    pub fn world_from(&self, frame: &str, log_time: u64) -> Isometry3<f64> {
        let tf: FrameTransforms = prost::Message::decode(self.message(TF_TOPIC, log_time).data.as_slice())
            .unwrap_or_else(|e| panic!("/tf: {e}"));
        let mut pose = Isometry3::identity();
        let mut child = frame.to_owned();
        while let Some(t) = tf.transforms.iter().find(|t| t.child_frame_id == child) {
            let translation = t.translation.unwrap_or_default();
            let rotation = t.rotation.unwrap_or_default();
            let parent_from_child = Isometry3::from_parts(
                Translation3::new(translation.x, translation.y, translation.z),
                UnitQuaternion::from_quaternion(Quaternion::new(rotation.w, rotation.x, rotation.y, rotation.z)),
            );
            pose = parent_from_child * pose;
            child = t.parent_frame_id.clone();
        }
        assert_eq!(
            child,
            record::log::WORLD_FRAME,
            "the /tf chain from {frame} does not reach world"
        );
        pose
    }
}

/// Decodes little-endian f32 pixels.
pub fn f32_pixels(image: &RawImage) -> Vec<f32> {
    image
        .data
        .chunks_exact(4)
        .map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]]))
        .collect()
}

/// Copies a log without its capture events: a "foreign" log whose sets must be inferred from
/// the poses.
pub fn strip_capture_events(from: &Path, to: &Path) {
    copy_messages(from, to, |topic, _| topic != CAPTURE_EVENTS_TOPIC);
}

/// Copies the messages of a log (or one ROS 2 bag file) that `keep(topic, log_time)` accepts
/// into a new log with the same schemas, channels (and their metadata) and header profile.
pub fn copy_messages(from: &Path, to: &Path, keep: impl Fn(&str, u64) -> bool) {
    let bytes = std::fs::read(from).unwrap_or_else(|e| panic!("{}: {e}", from.display()));
    let profile = match mcap::read::LinearReader::new(&bytes)
        .unwrap_or_else(|e| panic!("{e}"))
        .next()
    {
        Some(Ok(mcap::records::Record::Header(header))) => header.profile,
        _ => String::new(),
    };
    let file = std::io::BufWriter::new(std::fs::File::create(to).unwrap_or_else(|e| panic!("{e}")));
    let mut writer = mcap::WriteOptions::new()
        .profile(profile)
        .create(file)
        .unwrap_or_else(|e| panic!("{e}"));
    let mut channels = std::collections::HashMap::new();
    for message in mcap::MessageStream::new(&bytes).unwrap_or_else(|e| panic!("{e}")) {
        let message = message.unwrap_or_else(|e| panic!("{e}"));
        if !keep(&message.channel.topic, message.log_time) {
            continue;
        }
        let id = *channels.entry(message.channel.topic.clone()).or_insert_with(|| {
            let schema = message.channel.schema.as_ref().unwrap_or_else(|| panic!("no schema"));
            let schema_id = writer
                .add_schema(&schema.name, &schema.encoding, &schema.data)
                .unwrap_or_else(|e| panic!("{e}"));
            writer
                .add_channel(
                    schema_id,
                    &message.channel.topic,
                    &message.channel.message_encoding,
                    &message.channel.metadata,
                )
                .unwrap_or_else(|e| panic!("{e}"))
        });
        let header = mcap::records::MessageHeader {
            channel_id: id,
            sequence: message.sequence,
            log_time: message.log_time,
            publish_time: message.publish_time,
        };
        writer
            .write_to_known_channel(&header, &message.data)
            .unwrap_or_else(|e| panic!("{e}"));
    }
    writer.finish().unwrap_or_else(|e| panic!("{e}"));
}

/// A fresh temporary directory.
pub fn temp_dir() -> tempfile::TempDir {
    tempfile::tempdir().unwrap_or_else(|e| panic!("cannot create a temporary directory: {e}"))
}

/// The largest single allocation made by the current thread since [`allocations::reset`]: the
/// fuzz targets check that no input makes a reader allocate more than its size allows. Counted
/// by the test binary's global allocator (the system allocator, with a per-thread maximum).
pub mod allocations {
    use std::alloc::{GlobalAlloc, Layout, System};
    use std::cell::Cell;

    thread_local! {
        static LARGEST: Cell<usize> = const { Cell::new(0) };
    }

    /// Starts counting afresh on this thread.
    pub fn reset() {
        let _ = LARGEST.try_with(|l| l.set(0));
    }

    /// The largest allocation (bytes) on this thread since the last [`reset`].
    pub fn largest() -> usize {
        LARGEST.try_with(Cell::get).unwrap_or(0)
    }

    thread_local! {
        static IN_TRAP: Cell<bool> = const { Cell::new(false) };
    }

    fn note(size: usize) {
        // `try_with`: during a thread's teardown the slot may be gone; nothing is counted then.
        let _ = LARGEST.try_with(|l| l.set(l.get().max(size)));
        // FUZZ_TRAP_BYTES=N prints where an allocation over N bytes comes from (debugging a
        // fuzz finding); the guard keeps the backtrace's own allocations out.
        if size > (1 << 30) && IN_TRAP.try_with(|t| !t.replace(true)).unwrap_or(false) {
            if std::env::var_os("FUZZ_TRAP_BYTES").is_some() {
                eprintln!(
                    "allocation of {size} bytes at\n{}",
                    std::backtrace::Backtrace::force_capture()
                );
            }
            let _ = IN_TRAP.try_with(|t| t.set(false));
        }
    }

    /// The system allocator, noting each request's size.
    pub struct Counting;

    // SAFETY: every call is forwarded unchanged to `System`, which upholds `GlobalAlloc`'s
    // contract; the bookkeeping only reads the layout and touches a const-initialised
    // thread-local `Cell` (no allocation, no destructor).
    #[allow(unsafe_code)]
    unsafe impl GlobalAlloc for Counting {
        unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
            note(layout.size());
            // SAFETY: forwarded with the caller's layout.
            unsafe { System.alloc(layout) }
        }

        unsafe fn alloc_zeroed(&self, layout: Layout) -> *mut u8 {
            note(layout.size());
            // SAFETY: forwarded with the caller's layout.
            unsafe { System.alloc_zeroed(layout) }
        }

        unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
            // SAFETY: `ptr` came from `System` with this layout.
            unsafe { System.dealloc(ptr, layout) }
        }

        unsafe fn realloc(&self, ptr: *mut u8, layout: Layout, new_size: usize) -> *mut u8 {
            note(new_size);
            // SAFETY: forwarded unchanged.
            unsafe { System.realloc(ptr, layout, new_size) }
        }
    }

    #[global_allocator]
    static GLOBAL: Counting = Counting;
}
