//! Reading a log into view sets.
//!
//! The messages are scanned in file order; every complete message is kept, so a recording that
//! was cut off (no summary, a torn last chunk) still yields the sets it completed, and
//! [`LogContents::truncation`] says what was lost. Capture events say which image is which view
//! of which set; the images, calibrations and ground truth are looked up by topic and log time.

use std::borrow::Cow;
use std::collections::{BTreeMap, HashMap};
use std::path::Path;

use foxglove::messages::{CameraCalibration, CompressedImage, RawImage};
use record::adaptive::PlanStep;
use record::camera::PinholeCamera;
use record::log::{CAPTURE_EVENTS_TOPIC, CAPTURE_PLAN_TOPIC, CaptureEvent, PoseJson};
use record::rig::REFERENCE_ROLE;

use crate::ReplayError;
use crate::viewset::{View, ViewSet};

/// What a log holds.
#[derive(Debug, Clone)]
pub struct LogContents {
    /// Complete view sets, in set order.
    pub sets: Vec<ViewSet>,
    /// Sets named by capture events but missing messages (cut off), with the reason.
    pub incomplete_sets: Vec<(u32, String)>,
    /// Messages read.
    pub messages: usize,
    /// Where and why the file ends early, when it does (cut off by a crash, or never finished).
    pub truncation: Option<String>,
    /// Chunks left out because they are corrupt (a CRC mismatch, a stream that does not
    /// decompress); their sets are in `incomplete_sets`.
    pub bad_chunks: Vec<String>,
    /// Metadata records.
    pub metadata: BTreeMap<String, BTreeMap<String, String>>,
    /// The plans of adaptive sets (`/capture/plan`), in log order.
    pub plans: Vec<PlanStep>,
    /// How the sets of a log without capture events were taken from its camera stream.
    pub stream: Option<crate::foreign::StreamReport>,
    /// ROS 2 topics of types that are not read: (topic, type, messages).
    pub ignored: Vec<(String, String, usize)>,
}

/// How a log is read.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct ReadOptions {
    /// Seconds after the log's first message before which images are left out.
    pub start_secs: Option<f64>,
    /// Seconds after the log's first message after which images are left out.
    pub end_secs: Option<f64>,
    /// How sets are taken from a camera stream (logs without capture events).
    pub stream: crate::foreign::StreamOptions,
    /// Image payloads the first pass keeps (default [`IMAGE_PAYLOAD_BUDGET_BYTES`]).
    pub image_budget_bytes: Option<usize>,
}

/// Reads a log file (memory-mapped).
pub fn read_log_file(path: &Path) -> Result<LogContents, ReplayError> {
    read_log_file_in(path, None, None)
}

/// Reads the sets of a log file whose images lie between `start_secs` and `end_secs` after the
/// log's first message (from its statistics; the Unix epoch when the log has no summary).
pub fn read_log_file_in(
    path: &Path,
    start_secs: Option<f64>,
    end_secs: Option<f64>,
) -> Result<LogContents, ReplayError> {
    read_log_file_with(
        path,
        &ReadOptions {
            start_secs,
            end_secs,
            ..ReadOptions::default()
        },
    )
}

/// Reads a log file (memory-mapped) or a ROS 2 bag directory as `options` say.
pub fn read_log_file_with(path: &Path, options: &ReadOptions) -> Result<LogContents, ReplayError> {
    let (start_secs, end_secs) = (options.start_secs, options.end_secs);
    let paths = log_files(path)?;
    let maps = paths
        .iter()
        .map(|path| {
            let io = |source| ReplayError::Io {
                path: path.clone(),
                source,
            };
            let file = std::fs::File::open(path).map_err(io)?;
            map_read_only(&file).map_err(io)
        })
        .collect::<Result<Vec<_>, _>>()?;
    let files: Vec<&[u8]> = maps.iter().map(|m| &m[..]).collect();
    let origin = files
        .first()
        .and_then(|bytes| crate::salvage::trusted_summary(bytes))
        .and_then(|s| s.stats.map(|stats| stats.message_start_time))
        .unwrap_or(0);
    let at = |secs: f64| origin.saturating_add((secs.max(0.0) * 1e9) as u64);
    let range = TimeRange {
        start_nanos: start_secs.map_or(0, at),
        end_nanos: end_secs.map_or(u64::MAX, at),
    };
    read_logs_in(&files, &range, options)
}

/// Whether a directory is a ROS 2 bag (it has a `metadata.yaml` or `.mcap` files), not an image
/// folder.
pub fn is_bag_directory(path: &Path) -> bool {
    path.join(::ros2::bag::METADATA_FILE).is_file()
        || std::fs::read_dir(path).is_ok_and(|entries| {
            entries
                .filter_map(Result::ok)
                .any(|e| e.path().extension().is_some_and(|x| x == "mcap"))
        })
}

/// Whether a log is a ROS 2 bag (its first file's header has the `ros2` profile).
pub fn is_ros2_log(path: &Path) -> bool {
    log_files(path)
        .ok()
        .and_then(|files| files.into_iter().next())
        .and_then(|file| {
            let mut head = vec![0u8; 4096];
            let read = std::io::Read::read(&mut std::fs::File::open(file).ok()?, &mut head).ok()?;
            head.truncate(read);
            match crate::salvage::record_at(&head, 8) {
                Some(mcap::records::Record::Header(header)) => Some(header.profile == ::ros2::bag::PROFILE),
                _ => None,
            }
        })
        .unwrap_or(false)
}

/// The files of a log: the file itself, or a ROS 2 bag directory's storage files in order
/// (`metadata.yaml`'s list, else its `*_N.mcap` files).
pub fn log_files(path: &Path) -> Result<Vec<std::path::PathBuf>, ReplayError> {
    if path.is_dir() {
        ros2::bag::file_list(path).map_err(|source| ReplayError::Bag { source })
    } else {
        Ok(vec![path.to_path_buf()])
    }
}

/// One file of a log, as `replay info` lists it.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct FileDescription {
    /// The file.
    pub path: std::path::PathBuf,
    /// The MCAP header's profile (`ros2` for a ROS 2 bag, empty for our own logs).
    pub profile: String,
    /// The library that wrote it.
    pub library: String,
    /// Whether it has a summary (indexes, statistics): a finished file.
    pub finished: bool,
}

/// One topic of a log.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct TopicDescription {
    /// Topic.
    pub topic: String,
    /// Schema (message type) name.
    pub schema: String,
    /// Message encoding (`cdr`, `protobuf`, `json`).
    pub encoding: String,
    /// Messages (summed over the files).
    pub messages: u64,
}

/// What `replay info` reports: the files and topics of a log, what replay took from them.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct LogDescription {
    /// The files, in order.
    pub files: Vec<FileDescription>,
    /// Every topic.
    pub topics: Vec<TopicDescription>,
    /// How a camera stream became sets (logs without capture events).
    pub stream: Option<crate::foreign::StreamReport>,
    /// The sets: index, name, rig, baseline (m), and per view its role, grid offset and time.
    pub sets: Vec<SetDescription>,
    /// What was read besides the sets ([`LogContents::notes`]).
    pub notes: Vec<String>,
    /// What was lost ([`LogContents::damage`]).
    pub lost: Vec<String>,
}

/// One set of a log.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct SetDescription {
    /// Index.
    pub index: u32,
    /// Name.
    pub name: String,
    /// Layout.
    pub rig: String,
    /// Baseline (m).
    pub baseline_m: f64,
    /// Image size.
    pub size: [u32; 2],
    /// (role, grid offset, image time in ns, camera position in the log's root frame in m).
    pub views: Vec<(String, [i32; 2], u64, [f64; 3])>,
}

/// Describes a log file or ROS 2 bag directory: its files and topics (from each file's summary,
/// else counted by walking it) and the sets replay reads from it.
pub fn describe(path: &Path, options: &ReadOptions) -> Result<LogDescription, ReplayError> {
    let contents = read_log_file_with(path, options)?;
    let mut files = Vec::new();
    let mut topics: Vec<TopicDescription> = Vec::new();
    for file in log_files(path)? {
        let io = |source| ReplayError::Io {
            path: file.clone(),
            source,
        };
        let bytes = map_read_only(&std::fs::File::open(&file).map_err(io)?).map_err(io)?;
        let (profile, library) = match crate::salvage::record_at(&bytes, 8) {
            Some(mcap::records::Record::Header(header)) => (header.profile, header.library),
            _ => (String::new(), String::new()),
        };
        let mut add = |topic: &str, schema: &str, encoding: &str, messages: u64| match topics
            .iter_mut()
            .find(|t| t.topic == topic)
        {
            Some(t) => t.messages += messages,
            None => topics.push(TopicDescription {
                topic: topic.to_owned(),
                schema: schema.to_owned(),
                encoding: encoding.to_owned(),
                messages,
            }),
        };
        let summary = crate::salvage::trusted_summary(&bytes);
        let finished = summary.is_some();
        match summary {
            Some(summary) => {
                let counts = summary
                    .stats
                    .as_ref()
                    .map(|s| s.channel_message_counts.clone())
                    .unwrap_or_default();
                for (id, channel) in &summary.channels {
                    let schema = channel.schema.as_ref().map_or("", |s| s.name.as_str());
                    add(
                        &channel.topic,
                        schema,
                        &channel.message_encoding,
                        counts.get(id).copied().unwrap_or(0),
                    );
                }
            }
            None => {
                let mut channels: HashMap<u16, (String, u16, String)> = HashMap::new();
                let mut schemas: HashMap<u16, String> = HashMap::new();
                let mut counts: BTreeMap<u16, u64> = BTreeMap::new();
                let _walked = crate::salvage::walk(&bytes, |record, trusted| -> Result<(), std::convert::Infallible> {
                    match record {
                        mcap::records::Record::Schema { header, .. } if trusted => {
                            schemas.insert(header.id, header.name);
                        }
                        mcap::records::Record::Channel(c) if trusted => {
                            channels.insert(c.id, (c.topic, c.schema_id, c.message_encoding));
                        }
                        mcap::records::Record::Message { header, .. } if trusted => {
                            *counts.entry(header.channel_id).or_default() += 1;
                        }
                        _ => {}
                    }
                    Ok(())
                });
                for (id, (topic, schema_id, encoding)) in &channels {
                    let schema = schemas.get(schema_id).map_or("", String::as_str);
                    add(topic, schema, encoding, counts.get(id).copied().unwrap_or(0));
                }
            }
        }
        files.push(FileDescription {
            path: file,
            profile,
            library,
            finished,
        });
    }
    topics.sort_by(|a, b| a.topic.cmp(&b.topic));
    let sets = contents
        .sets
        .iter()
        .map(|set| SetDescription {
            index: set.index,
            name: set.name.clone(),
            rig: set.rig.clone(),
            baseline_m: set.baseline_m,
            size: [set.reference.camera.width, set.reference.camera.height],
            views: std::iter::once(&set.reference)
                .chain(&set.neighbours)
                .map(|v| {
                    let p = v.world_from_camera.translation.vector;
                    (v.role.clone(), v.offset, v.capture_time_nanos, [p.x, p.y, p.z])
                })
                .collect(),
        })
        .collect();
    Ok(LogDescription {
        files,
        topics,
        notes: contents.notes(),
        lost: contents.damage(),
        stream: contents.stream,
        sets,
    })
}

impl LogDescription {
    /// The report as text.
    pub fn to_text(&self) -> String {
        use std::fmt::Write as _;
        let mut out = String::new();
        for f in &self.files {
            let kind = if f.profile == ros2::bag::PROFILE {
                "ROS 2 bag file"
            } else {
                "MCAP log"
            };
            let _ = writeln!(
                out,
                "{} — {kind}, written by {}{}",
                f.path.display(),
                if f.library.is_empty() { "?" } else { &f.library },
                if f.finished {
                    ""
                } else {
                    " (no summary: unfinished or cut)"
                }
            );
        }
        let _ = writeln!(out, "\ntopics:");
        for t in &self.topics {
            let _ = writeln!(
                out,
                "  {:<40} {:<36} {:>7} msgs  {}",
                t.topic, t.schema, t.messages, t.encoding
            );
        }
        if let Some(stream) = &self.stream {
            let _ = writeln!(
                out,
                "\ncamera stream: images on {} in frame(s) {}, poses in '{}'",
                stream
                    .image_topics
                    .iter()
                    .map(|(t, n)| format!("{t} ({n})"))
                    .collect::<Vec<_>>()
                    .join(", "),
                stream.camera_frames.join(", "),
                stream.base_frame.as_deref().unwrap_or("the tree's root")
            );
            let _ = writeln!(out, "  {} joint-state message(s) read", stream.joint_states);
            for (i, (first, last, frames, gap)) in stream.stations.iter().enumerate() {
                let _ = writeln!(
                    out,
                    "  station {i}: {frames} settled frame(s), stamps {first} … {last} ns, transforms interpolated over at most {:.1} ms",
                    *gap as f64 / 1e6
                );
            }
        }
        let _ = writeln!(out, "\nsets:");
        if self.sets.is_empty() {
            let _ = writeln!(out, "  none");
        }
        for set in &self.sets {
            let _ = writeln!(
                out,
                "  set {} '{}': {} at {:.2} mm, {}x{}",
                set.index,
                set.name,
                set.rig,
                set.baseline_m * 1000.0,
                set.size[0],
                set.size[1]
            );
            for (role, offset, time, p) in &set.views {
                let _ = writeln!(
                    out,
                    "    {role:<12} offset {:>2},{:>2}  at {time} ns  camera at ({:.4}, {:.4}, {:.4}) m",
                    offset[0], offset[1], p[0], p[1], p[2]
                );
            }
        }
        for line in &self.notes {
            let _ = writeln!(out, "note: {line}");
        }
        for line in &self.lost {
            let _ = writeln!(out, "lost: {line}");
        }
        out
    }
}

/// Maps a log file read-only.
#[allow(unsafe_code)]
fn map_read_only(file: &std::fs::File) -> std::io::Result<memmap2::Mmap> {
    // SAFETY: the mapping is read-only and lives only while the log is read; a log truncated or
    // rewritten by another process meanwhile is outside what replay supports (as with every
    // mmap-based MCAP reader), and the reader bounds-checks every record it parses.
    unsafe { memmap2::Mmap::map(file) }
}

/// Capture events of a log (linear scan), recovering what a cut-off log holds.
pub fn read_capture_events(mcap_bytes: &[u8]) -> Result<Vec<CaptureEvent>, ReplayError> {
    let mut events = Vec::new();
    scan(
        mcap_bytes,
        |topic, _| topic == CAPTURE_EVENTS_TOPIC,
        |topic, _, log_time, data| {
            if topic == CAPTURE_EVENTS_TOPIC {
                let event = serde_json::from_slice(data).map_err(|source| ReplayError::BadEvent {
                    topic: CAPTURE_EVENTS_TOPIC,
                    log_time,
                    source,
                })?;
                events.push(event);
            }
            Ok(())
        },
    )?;
    Ok(events)
}

/// Largest record accepted by the indexed reader: a corrupt length must fail, not allocate.
fn record_length_limit(file_len: usize) -> usize {
    (file_len.saturating_mul(64)).clamp(256 << 20, 2 << 30)
}

/// What a linear scan found beyond the messages.
#[derive(Default)]
struct ScanDamage {
    /// Where and why the file ends early.
    cut: Option<String>,
    /// Chunks left out, each with the sets its capture events named (read from the untrusted
    /// chunk when it still decompresses).
    bad_chunks: Vec<(String, Vec<(u32, String)>)>,
    /// The metadata records met on the way (`None` when the scan did not run).
    metadata: Option<BTreeMap<String, BTreeMap<String, String>>>,
}

/// Scans messages in file order ([`crate::salvage::walk`]: a cut chunk is read as far as it
/// goes, a chunk whose CRC fails is left out), handing those whose topic `wanted` accepts to
/// `on_message`. Returns the message count and the damage found.
fn scan(
    bytes: &[u8],
    wanted: impl Fn(&str, &str) -> bool,
    mut on_message: impl FnMut(&str, &str, u64, &[u8]) -> Result<(), ReplayError>,
) -> Result<(usize, ScanDamage), ReplayError> {
    use mcap::records::Record;
    let mut topics: HashMap<u16, (String, u16)> = HashMap::new();
    let mut schemas: HashMap<u16, String> = HashMap::new();
    let mut count = 0;
    // Capture events of untrusted chunks: set index, name and log time.
    let mut untrusted_events: Vec<(u32, String, u64)> = Vec::new();
    let mut metadata = BTreeMap::new();
    let report = crate::salvage::walk(bytes, |record, trusted| {
        match record {
            Record::Schema { header, .. } if trusted => {
                schemas.insert(header.id, header.name.clone());
            }
            Record::Channel(channel) if trusted => {
                topics.insert(channel.id, (channel.topic.clone(), channel.schema_id));
            }
            Record::Metadata(record) if trusted => {
                metadata.insert(record.name, record.metadata);
            }
            Record::Message { header, data } => {
                let Some((topic, schema_id)) = topics.get(&header.channel_id) else {
                    return Ok(());
                };
                if !trusted {
                    if topic == CAPTURE_EVENTS_TOPIC
                        && let Ok(event) = serde_json::from_slice::<CaptureEvent>(&data)
                    {
                        untrusted_events.push((event.set_index, event.set_name, header.log_time));
                    }
                    return Ok(());
                }
                count += 1;
                let schema = schemas.get(schema_id).map_or("", String::as_str);
                if wanted(topic, schema) {
                    on_message(topic, schema, header.log_time, &data)?;
                }
            }
            _ => {}
        }
        Ok(())
    })
    .map_err(|error| match error {
        crate::salvage::WalkError::NotMcap { .. } => ReplayError::Mcap {
            source: mcap::McapError::BadMagic,
        },
        crate::salvage::WalkError::Handler(error) => error,
    })?;
    // Each bad chunk's sets: those of the untrusted capture events within its time span.
    let bad_chunks = report
        .bad_chunks
        .iter()
        .map(|chunk| {
            let (start, end) = chunk.message_time_nanos;
            let mut sets: Vec<(u32, String)> = Vec::new();
            for (index, name, time) in &untrusted_events {
                if (start..=end).contains(time) && !sets.iter().any(|(i, _)| i == index) {
                    sets.push((*index, name.clone()));
                }
            }
            let reason = format!(
                "the chunk at byte {} (messages {start} … {end} ns) is corrupt ({}) and was left out",
                chunk.at_byte, chunk.reason
            );
            (reason, sets)
        })
        .collect();
    let damage = ScanDamage {
        cut: report.cut.map(|cut| cut.to_string()),
        bad_chunks,
        metadata: Some(metadata),
    };
    Ok((count, damage))
}

/// Reads the messages of `wanted` channels with log times in `range` through the summary's chunk
/// and message indexes: only the chunks that hold such messages are decompressed. `None` when the
/// log has no usable summary (then the caller scans linearly).
fn scan_indexed(
    bytes: &[u8],
    range: &TimeRange,
    wanted: impl Fn(&str, &str) -> bool,
    mut on_message: impl FnMut(&str, &str, u64, &[u8]) -> Result<(), ReplayError>,
) -> Option<Result<usize, ReplayError>> {
    use mcap::sans_io::{IndexedReadEvent, IndexedReader, IndexedReaderOptions};
    let summary = crate::salvage::trusted_summary(bytes)?;
    // The indexed reader allocates each chunk's claimed size: an implausible one (or a chunk
    // outside the file) sends the read to the linear scan, which bounds what it decompresses.
    let plausible = |c: &mcap::records::ChunkIndex| {
        c.uncompressed_size <= c.compressed_size.saturating_mul(4096).saturating_add(64 << 10)
            && c.chunk_start_offset.saturating_add(c.chunk_length) <= bytes.len() as u64
    };
    if summary.chunk_indexes.is_empty() || !summary.chunk_indexes.iter().all(plausible) {
        return None;
    }
    let channels: HashMap<u16, (String, String)> = summary
        .channels
        .iter()
        .map(|(id, c)| {
            (
                *id,
                (
                    c.topic.clone(),
                    c.schema.as_ref().map_or_else(String::new, |s| s.name.clone()),
                ),
            )
        })
        .filter(|(_, (topic, schema))| wanted(topic, schema))
        .collect();
    let topics: Vec<String> = channels.values().map(|(topic, _)| topic.clone()).collect();
    let options = IndexedReaderOptions::new()
        .include_topics(topics)
        .starting_at(range.start_nanos)
        .ending_before(range.end_nanos.saturating_add(1))
        .with_record_length_limit(record_length_limit(bytes.len()));
    let mut reader = IndexedReader::new_with_options(&summary, options).ok()?;
    let mut count = 0;
    // The indexed reader trusts the summary; a chunk that contradicts it makes it panic, so a
    // corrupt file falls back to the linear scan, which reports what it finds.
    let result = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| -> Result<usize, ReplayError> {
        while let Some(event) = reader.next_event() {
            match event.map_err(|source| ReplayError::Mcap { source })? {
                IndexedReadEvent::ReadChunkRequest { offset, length } => {
                    let start = usize::try_from(offset).unwrap_or(usize::MAX);
                    let chunk = bytes
                        .get(start..start.saturating_add(length))
                        .ok_or(ReplayError::Mcap {
                            source: mcap::McapError::UnexpectedEof,
                        })?;
                    reader
                        .insert_chunk_record_data(offset, chunk)
                        .map_err(|source| ReplayError::Mcap { source })?;
                }
                IndexedReadEvent::Message { header, data } => {
                    count += 1;
                    if let Some((topic, schema)) = channels.get(&header.channel_id) {
                        on_message(topic, schema, header.log_time, data)?;
                    }
                }
            }
        }
        Ok(count)
    }));
    result.ok()
}

/// Image payloads kept by the first pass over a log: past this many bytes (a camera that
/// streamed through a long capture) the reader drops them, remembers only what each image is, and
/// reads the images the sets need in a second pass, so that memory holds the sets, not the stream.
pub const IMAGE_PAYLOAD_BUDGET_BYTES: usize = 256 << 20;

/// What a scan keeps: capture events, payloads of the topics a set may need, and what
/// foreign-log inference needs. ROS 2 messages are translated first (`crate::ros2`).
#[derive(Default)]
struct Collected {
    events: Vec<CaptureEvent>,
    plans: Vec<PlanStep>,
    payloads: HashMap<(String, u64), Vec<u8>>,
    foreign: crate::foreign::ForeignMessages,
    ros2: crate::ros2::Ros2Translator,
    /// Bytes of image payloads kept, their keys, and the budget.
    image_bytes: usize,
    image_keys: Vec<(String, u64)>,
    image_budget_bytes: usize,
    /// Image payloads were dropped: the needed ones are read again.
    deferred: bool,
}

/// Reads the payloads of `needed` (topic, log time) from the files (a second pass, after the
/// first one dropped the image payloads of a long stream), translating ROS 2 messages with the
/// first pass's translator (so a 16-bit topic keeps its shift).
fn fetch(
    files: &[&[u8]],
    needed: &[(String, u64)],
    ros2: &mut crate::ros2::Ros2Translator,
    payloads: &mut HashMap<(String, u64), Vec<u8>>,
) -> Result<(), ReplayError> {
    let missing: std::collections::HashSet<&(String, u64)> =
        needed.iter().filter(|key| !payloads.contains_key(*key)).collect();
    if missing.is_empty() {
        return Ok(());
    }
    let topics: std::collections::HashSet<&str> = missing.iter().map(|(topic, _)| topic.as_str()).collect();
    for bytes in files {
        scan(
            bytes,
            |topic, _| topics.contains(topic),
            |topic, schema, time, data| {
                let key = (topic.to_owned(), time);
                if !missing.contains(&key) || payloads.contains_key(&key) {
                    return Ok(());
                }
                let data = if crate::ros2::is_ros2_schema(schema) {
                    match ros2.translate(topic, schema, data)? {
                        crate::ros2::Translated::Foxglove { data, .. } => data,
                        _ => return Ok(()),
                    }
                } else {
                    data.to_vec()
                };
                payloads.insert(key, data);
                Ok(())
            },
        )?;
    }
    Ok(())
}

impl Collected {
    fn keep(
        &mut self,
        range: &TimeRange,
        topic: &str,
        schema: &str,
        log_time: u64,
        data: &[u8],
    ) -> Result<(), ReplayError> {
        if crate::ros2::is_ros2_schema(schema) {
            // Past the image budget only what an image is matters: its pixels are not kept.
            let translated = if self.deferred && crate::ros2::is_image_type(schema) {
                self.ros2.translate_header(topic, schema, data)
            } else {
                self.ros2.translate(topic, schema, data)
            };
            // A topic whose messages do not translate (an encoding not read, a corrupt payload)
            // is left out and listed; the views that need it say so when they are assembled.
            let translated = match translated {
                Ok(translated) => translated,
                Err(error) => {
                    self.ros2.unreadable(topic, schema, &error);
                    return Ok(());
                }
            };
            return match translated {
                crate::ros2::Translated::Foxglove { schema, data } => {
                    self.keep_data(range, topic, schema, log_time, Cow::Owned(data))
                }
                crate::ros2::Translated::Text(text) => self.keep_data(range, topic, "json", log_time, Cow::Owned(text)),
                crate::ros2::Translated::Ignored => Ok(()),
            };
        }
        self.keep_data(range, topic, schema, log_time, Cow::Borrowed(data))
    }

    fn keep_data(
        &mut self,
        range: &TimeRange,
        topic: &str,
        schema: &str,
        log_time: u64,
        data: Cow<'_, [u8]>,
    ) -> Result<(), ReplayError> {
        let parse = |topic: &'static str| {
            move |source| ReplayError::BadEvent {
                topic,
                log_time,
                source,
            }
        };
        if topic == CAPTURE_EVENTS_TOPIC {
            if range.contains(log_time) {
                self.events
                    .push(serde_json::from_slice(&data).map_err(parse(CAPTURE_EVENTS_TOPIC))?);
            }
        } else if topic == CAPTURE_PLAN_TOPIC {
            if range.contains(log_time) {
                self.plans
                    .push(serde_json::from_slice(&data).map_err(parse(CAPTURE_PLAN_TOPIC))?);
            }
        } else if (range.contains(log_time) || crate::foreign::is_pose_source(schema))
            && self.foreign.add(topic, schema, log_time, &data)
        {
            let key = (topic.to_owned(), log_time);
            if crate::foreign::is_image_schema(schema) {
                if self.deferred {
                    return Ok(());
                }
                self.image_bytes += data.len();
                if self.image_bytes > self.image_budget_bytes {
                    // A long stream: from here on, images are read again when needed.
                    for key in self.image_keys.drain(..) {
                        self.payloads.remove(&key);
                    }
                    self.deferred = true;
                    return Ok(());
                }
                self.image_keys.push(key.clone());
            }
            self.payloads.insert(key, data.into_owned());
        }
        Ok(())
    }
}

/// Whether `topic` is a neighbour's ground truth (`/camera/ROLE/ground_truth/…` of a role other
/// than the reference): a set is evaluated on its reference's ground truth only, so the
/// neighbours' (half of a simulated set's bytes) are not copied out of the log.
fn is_neighbour_ground_truth(topic: &str) -> bool {
    topic
        .strip_prefix("/camera/")
        .and_then(|rest| rest.split_once("/ground_truth/"))
        .is_some_and(|(role, _)| role != REFERENCE_ROLE)
}

/// Reads a log held in memory.
pub fn read_log(bytes: &[u8]) -> Result<LogContents, ReplayError> {
    read_log_in(bytes, &TimeRange::default())
}

/// A log-time window (ns since the Unix epoch); messages outside it are not kept.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct TimeRange {
    /// First log time kept.
    pub start_nanos: u64,
    /// Last log time kept.
    pub end_nanos: u64,
}

impl Default for TimeRange {
    fn default() -> Self {
        Self {
            start_nanos: 0,
            end_nanos: u64::MAX,
        }
    }
}

impl TimeRange {
    fn contains(&self, time: u64) -> bool {
        (self.start_nanos..=self.end_nanos).contains(&time)
    }
}

/// Reads the view sets of a log whose images fall within `range`. Logs without capture events
/// (foreign logs with images, calibrations and `/tf`) get their sets inferred from the poses.
pub fn read_log_in(bytes: &[u8], range: &TimeRange) -> Result<LogContents, ReplayError> {
    read_logs_in(&[bytes], range, &ReadOptions::default())
}

/// Reads the view sets of the files of one log (a ROS 2 bag split into `NAME_0.mcap`,
/// `NAME_1.mcap`, …: their messages are taken in file order as one stream) whose images fall
/// within `range` (`options.stream` says how a stream becomes sets).
pub fn read_logs_in(files: &[&[u8]], range: &TimeRange, options: &ReadOptions) -> Result<LogContents, ReplayError> {
    let wanted = |topic: &str, schema: &str| {
        (topic == CAPTURE_EVENTS_TOPIC
            || topic == CAPTURE_PLAN_TOPIC
            || topic.starts_with("/camera/")
            || crate::foreign::is_foreign_input(schema)
            || crate::ros2::is_ros2_schema(schema))
            && !is_neighbour_ground_truth(topic)
    };
    let mut collected = Collected {
        image_budget_bytes: options.image_budget_bytes.unwrap_or(IMAGE_PAYLOAD_BUDGET_BYTES),
        ..Collected::default()
    };
    let mut messages = 0;
    let mut damage = ScanDamage::default();
    let mut metadata = BTreeMap::new();
    for bytes in files {
        let (count, file_damage) = read_one(bytes, range, files.len() == 1, &wanted, &mut collected)?;
        messages += count;
        metadata.extend(read_metadata(bytes, file_damage.metadata.clone()));
        // The first cut ends the stream's trustworthy part; corrupt chunks of every file count.
        damage.cut = damage.cut.or(file_damage.cut);
        damage.bad_chunks.extend(file_damage.bad_chunks);
    }
    let Collected {
        events,
        mut plans,
        mut payloads,
        foreign,
        mut ros2,
        deferred,
        ..
    } = collected;
    let ignored = ros2
        .ignored()
        .iter()
        .map(|((topic, schema), count)| (topic.clone(), schema.clone(), *count))
        .collect();
    plans.sort_by_key(|p| (p.set_index, p.step));
    let truncation = damage.cut;
    let damaged = truncation.is_some() || !damage.bad_chunks.is_empty();
    let bad_chunks: Vec<String> = damage.bad_chunks.iter().map(|(reason, _)| reason.clone()).collect();
    let (mut sets, mut incomplete_sets) = (Vec::new(), Vec::new());
    let mut stream = None;
    if events.is_empty() && foreign.has_images() {
        // A cut-off log may have lost what the inference needs: report, do not fail.
        let inferred = foreign.plan(&options.stream).and_then(|plan| {
            if deferred {
                fetch(files, &plan.needed(), &mut ros2, &mut payloads)?;
            }
            plan.build(&payloads)
        });
        match (inferred, damaged) {
            (Ok((inferred, report)), _) => {
                sets = inferred;
                stream = Some(report);
            }
            (Err(error), true) => incomplete_sets.push((0, error.to_string())),
            (Err(error), false) => return Err(error),
        }
    } else if deferred {
        let needed: Vec<(String, u64)> = events
            .iter()
            .flat_map(|e| {
                let reference = e.role == REFERENCE_ROLE;
                [
                    Some(&e.image_topic),
                    Some(&e.calibration_topic),
                    e.depth_topic.as_ref().filter(|_| reference),
                    e.surface_topic.as_ref().filter(|_| reference),
                ]
                .into_iter()
                .flatten()
                .map(|topic| (topic.clone(), e.capture_time_nanos))
            })
            .collect();
        fetch(files, &needed, &mut ros2, &mut payloads)?;
    }
    let mut by_set: BTreeMap<u32, Vec<CaptureEvent>> = BTreeMap::new();
    for event in events {
        by_set.entry(event.set_index).or_default().push(event);
    }
    for (index, events) in by_set {
        let expected = events.first().map_or(0, |e| e.views_in_set as usize);
        if events.len() < expected {
            incomplete_sets.push((index, format!("{} of {expected} views logged", events.len())));
            continue;
        }
        match assemble_set(index, &events, &mut payloads) {
            Ok(set) => sets.push(set),
            Err(error) if damaged => incomplete_sets.push((index, error.to_string())),
            Err(error) => return Err(error),
        }
    }
    // Sets whose messages were all in a corrupt chunk: named from its capture events.
    for (reason, lost) in &damage.bad_chunks {
        for (index, name) in lost {
            if !sets.iter().any(|s| s.index == *index) && !incomplete_sets.iter().any(|(i, _)| i == index) {
                incomplete_sets.push((*index, format!("'{name}' lost: {reason}")));
            }
        }
    }
    incomplete_sets.sort_by_key(|(index, _)| *index);
    Ok(LogContents {
        sets,
        incomplete_sets,
        messages,
        truncation,
        bad_chunks,
        metadata,
        plans,
        stream,
        ignored,
    })
}

/// Scans one file into `collected`: through its summary's indexes when it is the log's only
/// file and only a time window is wanted, else linearly (a file without a usable summary starts
/// over with a linear scan).
fn read_one(
    bytes: &[u8],
    range: &TimeRange,
    only_file: bool,
    wanted: &impl Fn(&str, &str) -> bool,
    collected: &mut Collected,
) -> Result<(usize, ScanDamage), ReplayError> {
    if only_file && *range != TimeRange::default() {
        // Images, events and calibrations in the window; transforms and joints whenever logged.
        let mut keep = |t: &str, s: &str, time: u64, data: &[u8]| collected.keep(range, t, s, time, data);
        let pose_source = crate::foreign::is_pose_source;
        let indexed = scan_indexed(bytes, range, |t, s| wanted(t, s) && !pose_source(s), &mut keep).and_then(|first| {
            scan_indexed(bytes, &TimeRange::default(), |_, s| pose_source(s), &mut keep)
                .map(|second| first.and_then(|a| second.map(|b| a + b)))
        });
        if let Some(result) = indexed {
            return Ok((result?, ScanDamage::default()));
        }
        // No usable summary (or it contradicted the file): start over with a linear scan.
        *collected = Collected {
            image_budget_bytes: collected.image_budget_bytes,
            ..Collected::default()
        };
    }
    scan(bytes, wanted, |t, s, time, data| {
        collected.keep(range, t, s, time, data)
    })
}

/// The metadata records: through the summary's index when the log has one, else those the linear
/// scan met (`scanned`), else by walking the file (a log cut before its summary keeps the records
/// written before the cut).
fn read_metadata(
    bytes: &[u8],
    scanned: Option<BTreeMap<String, BTreeMap<String, String>>>,
) -> BTreeMap<String, BTreeMap<String, String>> {
    let mut out = BTreeMap::new();
    if let Some(summary) = crate::salvage::trusted_summary(bytes)
        && summary
            .metadata_indexes
            .iter()
            .all(|index| match crate::salvage::record_at(bytes, index.offset) {
                Some(mcap::records::Record::Metadata(record)) => {
                    out.insert(record.name, record.metadata);
                    true
                }
                _ => false,
            })
    {
        return out;
    }
    if let Some(scanned) = scanned {
        return scanned;
    }
    out.clear();
    // A file that is not MCAP at all has no metadata; the message scan reports it.
    let _not_mcap = crate::salvage::walk(bytes, |record, trusted| -> Result<(), std::convert::Infallible> {
        if let (mcap::records::Record::Metadata(metadata), true) = (record, trusted) {
            out.insert(metadata.name, metadata.metadata);
        }
        Ok(())
    });
    out
}

impl LogContents {
    /// Whether anything of the log was lost (a cut, a corrupt chunk, an incomplete set).
    pub fn lost_anything(&self) -> bool {
        self.truncation.is_some() || !self.bad_chunks.is_empty() || !self.incomplete_sets.is_empty()
    }

    /// What was read besides the sets, one line each: a camera stream's stations and the images
    /// it left out, the ROS 2 topics of types not read.
    pub fn notes(&self) -> Vec<String> {
        let mut lines = Vec::new();
        if let Some(stream) = &self.stream {
            lines.push(format!(
                "sets taken from the camera stream: {} image(s) with a pose, {} while the arm moved (left out), {} settled station(s), the {} frame of each",
                stream.images_with_pose,
                stream.moving_images,
                stream.stations.len(),
                match stream.station_frame {
                    crate::foreign::StationFrame::First => "first",
                    crate::foreign::StationFrame::Middle => "middle",
                    crate::foreign::StationFrame::Last => "last",
                    crate::foreign::StationFrame::Mean => "mean",
                }
            ));
            if let Some(first) = &stream.first_missing_pose {
                lines.push(format!(
                    "{} image(s) left out without a camera pose; the first: {first}",
                    stream.images_without_pose
                ));
            }
        }
        for (topic, schema, count) in &self.ignored {
            lines.push(format!("{topic} ({schema}, {count} messages) is not read"));
        }
        lines
    }

    /// One line per thing lost: where the file was cut, each corrupt chunk, each incomplete set.
    pub fn damage(&self) -> Vec<String> {
        let mut lines = Vec::new();
        if let Some(cut) = &self.truncation {
            lines.push(format!(
                "the log is {cut}; every complete message before it was kept ({} messages, {} complete set(s))",
                self.messages,
                self.sets.len()
            ));
        }
        lines.extend(self.bad_chunks.iter().cloned());
        for (set, reason) in &self.incomplete_sets {
            lines.push(format!("set {set} is incomplete and skipped: {reason}"));
        }
        lines
    }
}

fn decode_error<'a>(set: u32, topic: &'a str, schema: &'static str) -> impl Fn(prost::DecodeError) -> ReplayError + 'a {
    move |e| ReplayError::Decode {
        set,
        topic: topic.to_owned(),
        schema,
        reason: e.to_string(),
    }
}

fn payload<'a>(
    payloads: &'a HashMap<(String, u64), Vec<u8>>,
    set: u32,
    event: &CaptureEvent,
    topic: &str,
) -> Result<&'a [u8], ReplayError> {
    payloads
        .get(&(topic.to_owned(), event.capture_time_nanos))
        .map(Vec::as_slice)
        .ok_or_else(|| missing_message(set, event, topic))
}

/// Takes the payload of `topic` at the event's capture time out of `payloads` (it is read once),
/// as [`bytes::Bytes`] over the same buffer.
fn take_payload(
    payloads: &mut HashMap<(String, u64), Vec<u8>>,
    set: u32,
    event: &CaptureEvent,
    topic: &str,
) -> Result<bytes::Bytes, ReplayError> {
    payloads
        .remove(&(topic.to_owned(), event.capture_time_nanos))
        .map(bytes::Bytes::from)
        .ok_or_else(|| missing_message(set, event, topic))
}

/// The error of a payload the event names that the log does not hold.
fn missing_message(set: u32, event: &CaptureEvent, topic: &str) -> ReplayError {
    ReplayError::MissingMessage {
        set,
        role: event.role.clone(),
        topic: topic.to_owned(),
        log_time: event.capture_time_nanos,
    }
}

/// Decodes an image message (`foxglove.RawImage` or a PNG `foxglove.CompressedImage`) into
/// packed RGB. From [`bytes::Bytes`] a tight `rgb8` image costs no copy of its pixels: prost
/// slices the payload's buffer, and the buffer, once the message is dropped, becomes the result
/// (its pixels moved to the front in place); from a `&[u8]` they are copied once.
pub(crate) fn decode_rgb(
    set: u32,
    topic: &str,
    data: impl bytes::Buf + Clone,
) -> Result<(u32, u32, Vec<u8>), ReplayError> {
    // A CompressedImage has `format` (field 3) and no `width`; try RawImage first by its fields.
    if let Ok(raw) = <RawImage as prost::Message>::decode(data.clone())
        && raw.width > 0
        && !raw.encoding.is_empty()
    {
        // The payload let go first, so that the pixels' buffer has one owner.
        drop(data);
        let (width, height) = (raw.width, raw.height);
        return raw_to_rgb(set, topic, raw).map(|rgb| (width, height, rgb));
    }
    let compressed: CompressedImage = prost::Message::decode(data).map_err(decode_error(
        set,
        topic,
        "foxglove.RawImage or foxglove.CompressedImage",
    ))?;
    if !compressed.format.eq_ignore_ascii_case("png") {
        return Err(ReplayError::UnknownEncoding {
            set,
            topic: topic.to_owned(),
            encoding: compressed.format,
        });
    }
    decode_png(&compressed.data).map_err(|reason| ReplayError::Decode {
        set,
        topic: topic.to_owned(),
        schema: "PNG",
        reason,
    })
}

fn decode_png(data: &[u8]) -> Result<(u32, u32, Vec<u8>), String> {
    let mut decoder = png::Decoder::new(std::io::Cursor::new(data));
    decoder.set_transformations(png::Transformations::EXPAND | png::Transformations::STRIP_16);
    let mut reader = decoder.read_info().map_err(|e| e.to_string())?;
    let size = reader.output_buffer_size().ok_or("image too large")?;
    // Deflate expands at most about 1032 : 1; a header claiming more than the bytes can hold is
    // corrupt, and must not become an allocation.
    if size > data.len().saturating_mul(1032).saturating_add(1 << 20) {
        let info = reader.info();
        return Err(format!(
            "the PNG header claims {}x{} ({size} bytes), more than its {} bytes can hold",
            info.width,
            info.height,
            data.len()
        ));
    }
    let mut buffer = vec![0; size];
    let info = reader.next_frame(&mut buffer).map_err(|e| e.to_string())?;
    buffer.truncate(info.buffer_size());
    let rgb = match info.color_type {
        png::ColorType::Rgb => buffer,
        png::ColorType::Rgba => buffer.chunks_exact(4).flat_map(|p| [p[0], p[1], p[2]]).collect(),
        png::ColorType::Grayscale => buffer.iter().flat_map(|v| [*v; 3]).collect(),
        png::ColorType::GrayscaleAlpha => buffer.chunks_exact(2).flat_map(|p| [p[0]; 3]).collect(),
        png::ColorType::Indexed => return Err("indexed PNG after expansion".into()),
    };
    Ok((info.width, info.height, rgb))
}

/// The pixels of `raw` as tightly packed RGB: a tight `rgb8` image's own buffer, else converted
/// row by row.
fn raw_to_rgb(set: u32, topic: &str, raw: RawImage) -> Result<Vec<u8>, ReplayError> {
    let (w, h, step) = (raw.width as usize, raw.height as usize, raw.step as usize);
    let channels = match raw.encoding.as_str() {
        "rgb8" | "bgr8" | "8UC3" => 3,
        "rgba8" | "bgra8" => 4,
        "mono8" | "8UC1" => 1,
        other => {
            return Err(ReplayError::UnknownEncoding {
                set,
                topic: topic.to_owned(),
                encoding: other.to_owned(),
            });
        }
    };
    let row_bytes = w.saturating_mul(channels);
    if step < row_bytes || raw.data.len() < step.saturating_mul(h.saturating_sub(1)).saturating_add(row_bytes) {
        return Err(ReplayError::BadField {
            set,
            topic: topic.to_owned(),
            field: "data",
            value: format!("{} bytes for {w}x{h} {} with step {step}", raw.data.len(), raw.encoding),
        });
    }
    let bgr = raw.encoding.starts_with("bgr") || raw.encoding == "8UC3";
    if channels == 3 && !bgr && step == row_bytes {
        // (The decoded pixels are uniquely owned: `Vec::from` takes their buffer, moving them to
        // its front when the message's header came first.)
        let mut rgb = Vec::from(raw.data);
        rgb.truncate(row_bytes * h);
        return Ok(rgb);
    }
    let mut rgb = Vec::with_capacity(w * h * 3);
    for row in 0..h {
        let line = &raw.data[row * step..row * step + row_bytes];
        match (channels, bgr) {
            (3, false) => rgb.extend_from_slice(line),
            (1, _) => rgb.extend(line.iter().flat_map(|v| [*v; 3])),
            (_, true) => rgb.extend(line.chunks_exact(channels).flat_map(|p| [p[2], p[1], p[0]])),
            (_, false) => rgb.extend(line.chunks_exact(channels).flat_map(|p| [p[0], p[1], p[2]])),
        }
    }
    Ok(rgb)
}

fn decode_depth(set: u32, topic: &str, data: impl bytes::Buf, size: (u32, u32)) -> Result<Vec<f32>, ReplayError> {
    let raw: RawImage = prost::Message::decode(data).map_err(decode_error(set, topic, "foxglove.RawImage"))?;
    if raw.encoding != record::log::DEPTH_ENCODING {
        return Err(ReplayError::UnknownEncoding {
            set,
            topic: topic.to_owned(),
            encoding: raw.encoding,
        });
    }
    let pixels = (raw.width as usize).saturating_mul(raw.height as usize);
    let row_bytes = (raw.width as usize).saturating_mul(4);
    let step = (raw.step as usize).max(row_bytes);
    let needed = step
        .saturating_mul((raw.height as usize).saturating_sub(1))
        .saturating_add(row_bytes);
    if (raw.width, raw.height) != size || raw.data.len() < needed {
        return Err(ReplayError::BadField {
            set,
            topic: topic.to_owned(),
            field: "width/height/data",
            value: format!(
                "{}x{} with step {} and {} bytes, image is {}x{}",
                raw.width,
                raw.height,
                raw.step,
                raw.data.len(),
                size.0,
                size.1
            ),
        });
    }
    let mut depth = Vec::with_capacity(pixels);
    for row in 0..raw.height as usize {
        for b in raw.data[row * step..row * step + row_bytes].chunks_exact(4) {
            let z = f32::from_le_bytes([b[0], b[1], b[2], b[3]]);
            if !z.is_finite() || z < 0.0 {
                return Err(ReplayError::BadField {
                    set,
                    topic: topic.to_owned(),
                    field: "depth",
                    value: format!(
                        "{z} at pixel {} (ground truth must be finite metres ≥ 0; 0 = unknown)",
                        depth.len()
                    ),
                });
            }
            depth.push(z);
        }
    }
    Ok(depth)
}

fn assemble_set(
    index: u32,
    events: &[CaptureEvent],
    payloads: &mut HashMap<(String, u64), Vec<u8>>,
) -> Result<ViewSet, ReplayError> {
    let mut views = Vec::with_capacity(events.len());
    let mut ground_truth = None;
    let mut surface = None;
    let reference_event = events
        .iter()
        .find(|e| e.role == REFERENCE_ROLE)
        .ok_or_else(|| ReplayError::MissingView {
            set: index,
            role: REFERENCE_ROLE.into(),
        })?;
    if !(reference_event.baseline_m.is_finite() && reference_event.baseline_m > 0.0) {
        return Err(ReplayError::BadField {
            set: index,
            topic: CAPTURE_EVENTS_TOPIC.into(),
            field: "baseline_m",
            value: reference_event.baseline_m.to_string(),
        });
    }
    // Each view's image payload is taken out of the map (a set's messages belong to it alone),
    // so that its buffer becomes the view's pixels without another copy.
    let images = events
        .iter()
        .map(|event| take_payload(payloads, index, event, &event.image_topic))
        .collect::<Result<Vec<_>, _>>()?;
    // The views' images decoded at once (the largest part of assembling a 1080p set).
    let decoded = {
        use rayon::prelude::*;
        events
            .par_iter()
            .zip(images)
            .map(|(event, image)| {
                let frame_id = crate::foreign::image_frame_id(&image);
                decode_rgb(index, &event.image_topic, image).map(|decoded| (decoded, frame_id))
            })
            .collect::<Vec<_>>()
    };
    for (event, decoded) in events.iter().zip(decoded) {
        let ((width, height, rgb), frame_id) = decoded?;
        let calibration: CameraCalibration =
            prost::Message::decode(payload(payloads, index, event, &event.calibration_topic)?).map_err(
                decode_error(index, &event.calibration_topic, "foxglove.CameraCalibration"),
            )?;
        if calibration.k.len() != 9 || calibration.k[0] <= 0.0 || !calibration.k[0].is_finite() {
            return Err(ReplayError::BadField {
                set: index,
                topic: event.calibration_topic.clone(),
                field: "k",
                value: format!("{:?}", calibration.k),
            });
        }
        let camera = PinholeCamera {
            width,
            height,
            fx: calibration.k[0],
            fy: calibration.k[4],
            cx: calibration.k[2],
            cy: calibration.k[5],
        };
        if event.role == REFERENCE_ROLE {
            if let Some(topic) = &event.depth_topic {
                ground_truth = Some(decode_depth(
                    index,
                    topic,
                    take_payload(payloads, index, event, topic)?,
                    (width, height),
                )?);
            }
            if let Some(topic) = &event.surface_topic {
                let raw: RawImage = prost::Message::decode(take_payload(payloads, index, event, topic)?)
                    .map_err(decode_error(index, topic, "foxglove.RawImage"))?;
                // Surface classes are optional evaluation data: a mask of another size is
                // left out rather than misread.
                if raw.data.len() == (width as usize).saturating_mul(height as usize) {
                    surface = Some(Vec::from(raw.data));
                }
            }
        }
        views.push(View {
            role: event.role.clone(),
            offset: event.grid_offset,
            camera,
            rgb,
            world_from_camera: event.world_from_camera.to_isometry(),
            true_world_from_camera: event.true_world_from_camera.as_ref().map(PoseJson::to_isometry),
            capture_time_nanos: event.capture_time_nanos,
            joints: event.joint_positions_rad,
            frame_id: frame_id.unwrap_or_else(|| record::log::view_frame(&event.role)),
        });
    }
    let reference_position = views.iter().position(|v| v.role == REFERENCE_ROLE).unwrap_or(0);
    let reference = views.remove(reference_position);
    for view in &views {
        if (view.camera.width, view.camera.height) != (reference.camera.width, reference.camera.height) {
            return Err(ReplayError::SizeMismatch {
                set: index,
                role: view.role.clone(),
                topic: record::log::image_topic(&view.role),
                width: view.camera.width,
                height: view.camera.height,
                reference_width: reference.camera.width,
                reference_height: reference.camera.height,
            });
        }
    }
    Ok(ViewSet {
        index,
        name: reference_event.set_name.clone(),
        rig: reference_event.rig.clone(),
        baseline_m: reference_event.baseline_m,
        reference,
        neighbours: views,
        ground_truth_depth_m: ground_truth,
        surface_class: surface,
        disparity_range: reference_event.disparity_range,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use record::rig::RigKind;
    use record::{CapturedSet, CapturedView};

    #[test]
    fn raw_images_of_every_encoding_become_packed_rgb() {
        // Two rows of two pixels, each row padded by one byte (step = row + 1), and tight.
        let pixels: [[u8; 4]; 4] = [[10, 20, 30, 40], [11, 21, 31, 41], [12, 22, 32, 42], [13, 23, 33, 43]];
        for (encoding, channels) in [
            ("rgb8", 3),
            ("bgr8", 3),
            ("8UC3", 3),
            ("rgba8", 4),
            ("bgra8", 4),
            ("mono8", 1),
        ] {
            let bgr = encoding.starts_with("bgr") || encoding == "8UC3";
            let expected: Vec<u8> = pixels
                .iter()
                .flat_map(|p| match (channels, bgr) {
                    (1, _) => [p[0]; 3],
                    (_, true) => [p[2], p[1], p[0]],
                    (_, false) => [p[0], p[1], p[2]],
                })
                .collect();
            for pad in [0, 1] {
                let step = 2 * channels + pad;
                let mut data = Vec::new();
                for row in pixels.chunks(2) {
                    for p in row {
                        data.extend_from_slice(&p[..channels]);
                    }
                    data.extend(std::iter::repeat_n(99, pad));
                }
                let raw = RawImage {
                    width: 2,
                    height: 2,
                    encoding: encoding.into(),
                    step: step as u32,
                    data: data.into(),
                    ..Default::default()
                };
                let rgb = raw_to_rgb(0, "/camera/center/image", raw).unwrap_or_else(|e| panic!("{e}"));
                assert_eq!(rgb, expected, "{encoding}, step {step}");
            }
        }
    }

    #[test]
    fn a_tight_rgb8_payload_becomes_the_pixels_without_a_copy() {
        let pixels: Vec<u8> = (0..64 * 48 * 3).map(|i| (i % 251) as u8).collect();
        let raw = RawImage {
            width: 64,
            height: 48,
            encoding: "rgb8".into(),
            step: 64 * 3,
            frame_id: "center_camera".into(),
            data: pixels.clone().into(),
            ..Default::default()
        };
        let payload = prost::Message::encode_to_vec(&raw);
        let buffer = payload.as_ptr();
        let (width, height, rgb) =
            decode_rgb(0, "/camera/center/image", bytes::Bytes::from(payload)).unwrap_or_else(|e| panic!("{e}"));
        assert_eq!((width, height), (64, 48));
        assert_eq!(rgb, pixels);
        assert_eq!(rgb.as_ptr(), buffer, "the payload's buffer holds the pixels");
        // From a borrowed slice the same pixels come out, in a buffer of their own.
        let borrowed = prost::Message::encode_to_vec(&raw);
        let (_, _, copied) =
            decode_rgb(0, "/camera/center/image", borrowed.as_slice()).unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(copied, pixels);
    }

    fn set(index: u32) -> CapturedSet {
        let camera = PinholeCamera::from_horizontal_fov(4, 3, 60.0);
        let view = |role: &str, dx: i32, time: u64| CapturedView {
            depth_m: Some(vec![0.5; 12]),
            ..CapturedView::new(
                (role, [dx, 0]),
                camera,
                nalgebra::Isometry3::translation(f64::from(dx) * 0.02, 0.0, 0.0),
                time,
                (0..36).map(|i| (i * 7 + dx as i64 * 3) as u8).collect(),
            )
        };
        let t = u64::from(index) * 1_000;
        CapturedSet {
            index,
            name: format!("s{index}"),
            rig: RigKind::ThreeView.name().to_owned(),
            baseline_m: 0.02,
            motion: Vec::new(),
            views: vec![
                view("center", 0, t + 1),
                view("left", -1, t + 2),
                view("right", 1, t + 3),
            ],
            disparity_range: None,
        }
    }

    fn log_bytes(sets: &[CapturedSet]) -> Vec<u8> {
        let mut writer = record::log::LogOptions::new()
            .create(std::io::Cursor::new(Vec::new()))
            .unwrap_or_else(|e| panic!("{e}"));
        for s in sets {
            writer.write_set(s, None).unwrap_or_else(|e| panic!("{e}"));
        }
        writer.finish().unwrap_or_else(|e| panic!("{e}")).into_inner()
    }

    #[test]
    fn only_the_reference_ground_truth_is_read() {
        use record::log::{depth_topic, image_topic, surface_topic};
        assert!(!is_neighbour_ground_truth(&depth_topic(REFERENCE_ROLE)));
        assert!(!is_neighbour_ground_truth(&surface_topic(REFERENCE_ROLE)));
        assert!(is_neighbour_ground_truth(&depth_topic("left")));
        assert!(is_neighbour_ground_truth(&surface_topic("top2")));
        assert!(!is_neighbour_ground_truth(&image_topic("left")));
        assert!(!is_neighbour_ground_truth("/camera/left/calibration"));
    }

    #[test]
    fn view_sets_round_trip_through_an_in_memory_log() {
        let written = [set(0), set(1)];
        let contents = read_log(&log_bytes(&written)).unwrap_or_else(|e| panic!("{e}"));
        assert!(contents.truncation.is_none());
        assert_eq!(contents.sets.len(), 2);
        for (read, original) in contents.sets.iter().zip(&written) {
            assert_eq!(read.reference.role, "center");
            assert_eq!(read.reference.rgb, original.views[0].rgb);
            let roles: Vec<&str> = read.neighbours.iter().map(|n| n.role.as_str()).collect();
            assert_eq!(roles, ["left", "right"]);
            assert_eq!(read.neighbours[0].offset, [-1, 0]);
            assert_eq!(read.ground_truth_depth_m.as_deref(), Some(&[0.5f32; 12][..]));
            assert!((read.baseline_m - 0.02).abs() < 1e-12);
        }
        assert_eq!(
            read_capture_events(&log_bytes(&written)).map(|e| e.len()).unwrap_or(0),
            6
        );
    }

    #[test]
    fn a_cut_off_log_keeps_its_complete_sets() {
        // One chunk per set: force small chunks so that a cut lands after the first set.
        let mut writer = record::log::LogOptions::new()
            .chunk_size(64)
            .create(std::io::Cursor::new(Vec::new()))
            .unwrap_or_else(|e| panic!("{e}"));
        for s in [set(0), set(1)] {
            writer.write_set(&s, None).unwrap_or_else(|e| panic!("{e}"));
        }
        let bytes = writer.finish().unwrap_or_else(|e| panic!("{e}")).into_inner();
        let full = read_log(&bytes).unwrap_or_else(|e| panic!("{e}"));
        let mut recovered_some = false;
        for cut in (16..bytes.len()).step_by(37) {
            match read_log(&bytes[..cut]) {
                Ok(contents) => {
                    assert!(contents.sets.len() <= full.sets.len());
                    for s in &contents.sets {
                        assert_eq!(s.reference.rgb, full.sets[s.index as usize].reference.rgb);
                    }
                    recovered_some |= !contents.sets.is_empty() && contents.truncation.is_some();
                }
                Err(ReplayError::Mcap { .. }) => {}
                Err(other) => panic!("cut at {cut}: unexpected error {other}"),
            }
        }
        assert!(recovered_some, "no cut recovered a complete set");
    }

    #[test]
    fn garbage_is_an_error_not_a_panic() {
        assert!(matches!(read_log(b"not an mcap file"), Err(ReplayError::Mcap { .. })));
    }
}
