//! Reading a log into view sets.
//!
//! The messages are scanned in file order; every complete message is kept, so a recording that
//! was cut off (no summary, a torn last chunk) still yields the sets it completed, and
//! [`LogContents::truncation`] says what was lost. Capture events say which image is which view
//! of which set; the images, calibrations and ground truth are looked up by topic and log time.

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
    let io = |source| ReplayError::Io {
        path: path.to_path_buf(),
        source,
    };
    let file = std::fs::File::open(path).map_err(io)?;
    let bytes = map_read_only(&file).map_err(io)?;
    let origin = crate::salvage::trusted_summary(&bytes)
        .and_then(|s| s.stats.map(|stats| stats.message_start_time))
        .unwrap_or(0);
    let at = |secs: f64| origin.saturating_add((secs.max(0.0) * 1e9) as u64);
    let range = TimeRange {
        start_nanos: start_secs.map_or(0, at),
        end_nanos: end_secs.map_or(u64::MAX, at),
    };
    read_log_in(&bytes, &range)
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

/// What a scan keeps: capture events, payloads of the topics a set may need, and what
/// foreign-log inference needs.
#[derive(Default)]
struct Collected {
    events: Vec<CaptureEvent>,
    plans: Vec<PlanStep>,
    payloads: HashMap<(String, u64), Vec<u8>>,
    foreign: crate::foreign::ForeignMessages,
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
                    .push(serde_json::from_slice(data).map_err(parse(CAPTURE_EVENTS_TOPIC))?);
            }
        } else if topic == CAPTURE_PLAN_TOPIC {
            if range.contains(log_time) {
                self.plans
                    .push(serde_json::from_slice(data).map_err(parse(CAPTURE_PLAN_TOPIC))?);
            }
        } else if (range.contains(log_time) || schema == crate::foreign::TRANSFORMS_SCHEMA)
            && self.foreign.add(topic, schema, log_time, data)
        {
            self.payloads.insert((topic.to_owned(), log_time), data.to_vec());
        }
        Ok(())
    }
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
    let wanted = |topic: &str, schema: &str| {
        topic == CAPTURE_EVENTS_TOPIC
            || topic == CAPTURE_PLAN_TOPIC
            || topic.starts_with("/camera/")
            || crate::foreign::is_foreign_input(schema)
    };
    let mut collected = Collected::default();
    let indexed = if *range == TimeRange::default() {
        None
    } else {
        // Images, events and calibrations in the window; transforms whenever they were logged.
        let mut keep = |t: &str, s: &str, time: u64, data: &[u8]| collected.keep(range, t, s, time, data);
        scan_indexed(
            bytes,
            range,
            |t, s| wanted(t, s) && s != crate::foreign::TRANSFORMS_SCHEMA,
            &mut keep,
        )
        .and_then(|first| {
            scan_indexed(
                bytes,
                &TimeRange::default(),
                |_, s| s == crate::foreign::TRANSFORMS_SCHEMA,
                &mut keep,
            )
            .map(|second| first.and_then(|a| second.map(|b| a + b)))
        })
    };
    let (messages, mut damage) = match indexed {
        Some(result) => (result?, ScanDamage::default()),
        None => {
            // No usable summary (or it contradicted the file): start over with a linear scan.
            collected = Collected::default();
            scan(bytes, wanted, |t, s, time, data| {
                collected.keep(range, t, s, time, data)
            })?
        }
    };
    let Collected {
        events,
        mut plans,
        payloads,
        foreign,
    } = collected;
    plans.sort_by_key(|p| (p.set_index, p.step));
    let truncation = damage.cut;
    let damaged = truncation.is_some() || !damage.bad_chunks.is_empty();
    let bad_chunks: Vec<String> = damage.bad_chunks.iter().map(|(reason, _)| reason.clone()).collect();
    let (mut sets, mut incomplete_sets) = (Vec::new(), Vec::new());
    if events.is_empty() && foreign.has_images() {
        // A cut-off log may have lost what the inference needs: report, do not fail.
        match (foreign.infer_sets(&payloads), damaged) {
            (Ok(inferred), _) => sets = inferred,
            (Err(error), true) => incomplete_sets.push((0, error.to_string())),
            (Err(error), false) => return Err(error),
        }
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
        match assemble_set(index, &events, &payloads) {
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
        metadata: read_metadata(bytes, damage.metadata.take()),
        plans,
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
        .ok_or_else(|| ReplayError::MissingMessage {
            set,
            role: event.role.clone(),
            topic: topic.to_owned(),
            log_time: event.capture_time_nanos,
        })
}

pub(crate) fn decode_rgb(set: u32, topic: &str, data: &[u8]) -> Result<(u32, u32, Vec<u8>), ReplayError> {
    // A CompressedImage has `format` (field 3) and no `width`; try RawImage first by its fields.
    if let Ok(raw) = <RawImage as prost::Message>::decode(data)
        && raw.width > 0
        && !raw.encoding.is_empty()
    {
        return raw_to_rgb(set, topic, &raw).map(|rgb| (raw.width, raw.height, rgb));
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

fn raw_to_rgb(set: u32, topic: &str, raw: &RawImage) -> Result<Vec<u8>, ReplayError> {
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
    let mut rgb = Vec::with_capacity(w * h * 3);
    for row in 0..h {
        let line = &raw.data[row * step..row * step + w * channels];
        for p in line.chunks_exact(channels) {
            match (channels, bgr) {
                (1, _) => rgb.extend_from_slice(&[p[0]; 3]),
                (_, true) => rgb.extend_from_slice(&[p[2], p[1], p[0]]),
                (_, false) => rgb.extend_from_slice(&p[..3]),
            }
        }
    }
    Ok(rgb)
}

fn decode_depth(set: u32, topic: &str, data: &[u8], size: (u32, u32)) -> Result<Vec<f32>, ReplayError> {
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
    payloads: &HashMap<(String, u64), Vec<u8>>,
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
    for event in events {
        let (width, height, rgb) = decode_rgb(
            index,
            &event.image_topic,
            payload(payloads, index, event, &event.image_topic)?,
        )?;
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
                    payload(payloads, index, event, topic)?,
                    (width, height),
                )?);
            }
            if let Some(topic) = &event.surface_topic {
                let raw: RawImage = prost::Message::decode(payload(payloads, index, event, topic)?)
                    .map_err(decode_error(index, topic, "foxglove.RawImage"))?;
                // Surface classes are optional evaluation data: a mask of another size is
                // left out rather than misread.
                if raw.data.len() == (width as usize).saturating_mul(height as usize) {
                    surface = Some(raw.data.to_vec());
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
