//! A walk over a log's records that keeps everything a damaged file still holds.
//!
//! The `mcap` crate's readers stop at the first bad record: a chunk cut by a crash is dropped
//! whole, and a chunk whose CRC fails ends the read. [`walk`] instead goes record by record:
//! - a chunk that runs past the end of the file (the recorder was killed while writing it) is
//!   decompressed as far as its bytes go (streaming zstd), and every complete record in it kept;
//! - a chunk whose CRC fails, or that does not decompress, is skipped with a [`BadChunk`] note
//!   (its records are still offered as untrusted, so that a reader can name the sets it lost);
//! - a top-level record cut off ends the walk with a [`Cut`] saying where.
//!
//! Nothing is allocated beyond what the file's bytes can hold: a chunk's claimed size is a limit,
//! never an allocation. Chunks are decompressed a few ahead of the walk (one per thread, in
//! parallel) into buffers reused from chunk to chunk; their records are still handed out in file
//! order.

use std::io::Read;

use mcap::records::Record;

/// MCAP magic bytes at both ends of a file.
pub const MCAP_MAGIC: &[u8] = b"\x89MCAP0\r\n";
const FOOTER_OPCODE: u8 = 0x02;
const CHUNK_OPCODE: u8 = 0x06;
/// Largest uncompressed chunk accepted (a corrupt size field must not become an allocation).
const MAX_CHUNK_UNCOMPRESSED_BYTES: u64 = 4 << 30;
/// The most a chunk is believed to expand (zstd of our logs stays far below; a corrupt stream
/// must not become a huge allocation).
const MAX_COMPRESSION_RATIO: u64 = 4096;
/// A record's framing: opcode (1 byte) and length (8 bytes).
const RECORD_HEADER_BYTES: usize = 9;

/// Where and why a log ends early.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Cut {
    /// Byte offset of the first record that could not be read whole.
    pub at_byte: u64,
    /// The file's length.
    pub file_bytes: u64,
    /// What was found there.
    pub reason: String,
    /// Complete records recovered from a chunk cut at the end (0 when the cut is elsewhere).
    pub records_from_cut_chunk: usize,
}

impl std::fmt::Display for Cut {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "cut at byte {} of {}: {}",
            self.at_byte, self.file_bytes, self.reason
        )?;
        if self.records_from_cut_chunk > 0 {
            write!(
                f,
                " ({} complete records recovered from the cut chunk)",
                self.records_from_cut_chunk
            )?;
        }
        Ok(())
    }
}

/// The file's summary section, read by the `mcap` crate only when its footer is in place, its
/// records' lengths stay within the file and its CRC (when written) matches: the crate allocates
/// what a record claims before checking it, so a flipped bit in a length must not reach it.
pub fn trusted_summary(bytes: &[u8]) -> Option<mcap::Summary> {
    // Footer: opcode, length 20, summary start, summary offset start, summary CRC; then the magic.
    let footer_at = bytes.len().checked_sub(MCAP_MAGIC.len() + RECORD_HEADER_BYTES + 20)?;
    if bytes.len() < 2 * MCAP_MAGIC.len() + RECORD_HEADER_BYTES + 20
        || &bytes[bytes.len() - MCAP_MAGIC.len()..] != MCAP_MAGIC
        || bytes[footer_at] != FOOTER_OPCODE
        || u64_at(bytes, footer_at + 1)? != 20
    {
        return None;
    }
    let summary_start = usize::try_from(u64_at(bytes, footer_at + RECORD_HEADER_BYTES)?).ok()?;
    if summary_start == 0 || summary_start < MCAP_MAGIC.len() || summary_start > footer_at {
        return None;
    }
    let crc = u32_at(bytes, footer_at + RECORD_HEADER_BYTES + 16)?;
    // The CRC covers the summary section and the footer up to its CRC field.
    if crc != 0 && crc32fast::hash(&bytes[summary_start..footer_at + RECORD_HEADER_BYTES + 16]) != crc {
        return None;
    }
    let mut at = summary_start;
    while at < footer_at {
        let length = usize::try_from(u64_at(bytes, at + 1)?).ok()?;
        at = at.checked_add(RECORD_HEADER_BYTES)?.checked_add(length)?;
    }
    if at != footer_at {
        return None;
    }
    mcap::Summary::read(bytes).ok().flatten()
}

/// The record at `offset` (e.g. from a summary's metadata index), parsed only when its framing
/// and its length prefixes fit in the file.
pub fn record_at(bytes: &[u8], offset: u64) -> Option<Record<'_>> {
    let at = usize::try_from(offset).ok()?;
    let opcode = *bytes.get(at)?;
    let length = usize::try_from(u64_at(bytes, at.checked_add(1)?)?).ok()?;
    let body_start = at.checked_add(RECORD_HEADER_BYTES)?;
    let body = bytes.get(body_start..body_start.checked_add(length)?)?;
    if !fields_fit(opcode, body) {
        return None;
    }
    mcap::parse_record(opcode, body).ok()
}

/// A chunk whose records were not trusted.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct BadChunk {
    /// Byte offset of the chunk record.
    pub at_byte: u64,
    /// Log time of its first and last message (ns), as its header claims.
    pub message_time_nanos: (u64, u64),
    /// Why: a CRC mismatch, or a stream that does not decompress.
    pub reason: String,
}

/// What a walk found.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct WalkReport {
    /// Records handed over as trusted.
    pub records: usize,
    /// Chunks skipped.
    pub bad_chunks: Vec<BadChunk>,
    /// Where the file ends early, if it does.
    pub cut: Option<Cut>,
    /// Whether the file has a footer (it was finished; its summary may be used).
    pub finished: bool,
}

/// Errors a walk cannot go past.
#[derive(Debug, thiserror::Error)]
pub enum WalkError<E> {
    /// Not an MCAP file at all.
    #[error("not an MCAP log: the file does not start with the MCAP magic ({bytes} bytes)")]
    NotMcap {
        /// The file's length.
        bytes: usize,
    },
    /// The caller's handler failed.
    #[error(transparent)]
    Handler(E),
}

fn u64_at(bytes: &[u8], at: usize) -> Option<u64> {
    let slice = bytes.get(at..at.checked_add(8)?)?;
    let mut array = [0u8; 8];
    array.copy_from_slice(slice);
    Some(u64::from_le_bytes(array))
}

fn u32_at(bytes: &[u8], at: usize) -> Option<u32> {
    let slice = bytes.get(at..at.checked_add(4)?)?;
    let mut array = [0u8; 4];
    array.copy_from_slice(slice);
    Some(u32::from_le_bytes(array))
}

/// A chunk's header fields and where its compressed records start within the record body.
struct ChunkFrame<'a> {
    start_time: u64,
    end_time: u64,
    uncompressed_size: u64,
    uncompressed_crc: u32,
    compression: &'a [u8],
    /// The compressed records present (all of them, or those before the cut).
    records: &'a [u8],
    /// Whether every compressed byte the header announces is present.
    whole: bool,
}

/// Parses a chunk's header from `body` (possibly cut short). `None` when not even the header is
/// there.
fn chunk_frame(body: &[u8]) -> Option<ChunkFrame<'_>> {
    let start_time = u64_at(body, 0)?;
    let end_time = u64_at(body, 8)?;
    let uncompressed_size = u64_at(body, 16)?;
    let uncompressed_crc = u32_at(body, 24)?;
    let name_len = u32_at(body, 28)? as usize;
    let name_end = 32usize.checked_add(name_len)?;
    let compression = body.get(32..name_end)?;
    let compressed_size = u64_at(body, name_end)?;
    let records_start = name_end + 8;
    let available = body.len().saturating_sub(records_start);
    let whole = compressed_size <= available as u64;
    let take = if whole { compressed_size as usize } else { available };
    Some(ChunkFrame {
        start_time,
        end_time,
        uncompressed_size,
        uncompressed_crc,
        compression,
        records: body.get(records_start..records_start + take)?,
        whole,
    })
}

/// Decompresses as much of `records` as decodes, up to `limit` bytes, into `out` (cleared
/// first; its capacity is kept from chunk to chunk, so that a log's chunks reuse one buffer's
/// pages instead of faulting fresh ones). The error, if any, says why it stopped early.
fn decompress(compression: &[u8], records: &[u8], limit: u64, out: &mut Vec<u8>) -> Option<String> {
    out.clear();
    match compression {
        b"" => {
            let take = records.len().min(usize::try_from(limit).unwrap_or(usize::MAX));
            out.extend_from_slice(&records[..take]);
            None
        }
        b"zstd" => {
            // The limit is the claimed size when that is plausible: one allocation, no doubling.
            // A spare buffer too small is replaced, not grown: growing copies its old bytes
            // (the allocator's `realloc` knows no length) into freshly faulted pages.
            let wanted = usize::try_from(limit).unwrap_or(0);
            if out.capacity() < wanted {
                *out = Vec::with_capacity(wanted);
            }
            // A whole frame within the limit decodes in one call straight into the buffer's
            // spare capacity (no zeroing first); anything else (a cut or corrupt stream, a
            // frame larger than claimed) is decoded again as a stream, as far as it goes.
            if let Ok(mut decompressor) = zstd::bulk::Decompressor::new()
                && decompressor.decompress_to_buffer(records, out).is_ok()
            {
                return None;
            }
            out.clear();
            let decoder = match zstd::stream::read::Decoder::with_buffer(records) {
                Ok(decoder) => decoder,
                Err(error) => return Some(error.to_string()),
            };
            decoder
                .take(limit)
                .read_to_end(out)
                .err()
                .map(|error| error.to_string())
        }
        other => Some(format!(
            "compression '{}' is not supported",
            String::from_utf8_lossy(other)
        )),
    }
}

/// Reads `count`-byte length prefixes through a record body, checking that each field fits.
struct Fields<'a> {
    body: &'a [u8],
    at: usize,
}

impl Fields<'_> {
    fn skip(&mut self, bytes: usize) -> Option<()> {
        self.at = self.at.checked_add(bytes).filter(|end| *end <= self.body.len())?;
        Some(())
    }

    /// A field with a 4-byte length prefix (a string, a schema's data).
    fn prefixed32(&mut self) -> Option<()> {
        let length = u32_at(self.body, self.at)? as usize;
        self.skip(4)?;
        self.skip(length)
    }

    /// A string → string map: its 4-byte byte length, then prefixed keys and values within it.
    fn map(&mut self) -> Option<()> {
        let length = u32_at(self.body, self.at)? as usize;
        self.skip(4)?;
        let end = self.at.checked_add(length).filter(|end| *end <= self.body.len())?;
        while self.at < end {
            self.prefixed32()?;
            self.prefixed32()?;
        }
        (self.at == end).then_some(())
    }
}

/// Whether a record is one the walk hands over (schema, channel, message, attachment, metadata)
/// and the length prefixes inside it stay within its body: the `mcap` crate allocates what a
/// prefix claims before checking it, so a flipped bit must be caught here.
fn fields_fit(opcode: u8, body: &[u8]) -> bool {
    let mut f = Fields { body, at: 0 };
    let fits = match opcode {
        // Schema: id, name, encoding, data.
        0x03 => f
            .skip(2)
            .and_then(|()| f.prefixed32())
            .and_then(|()| f.prefixed32())
            .and_then(|()| f.prefixed32()),
        // Channel: id, schema id, topic, message encoding, metadata.
        0x04 => f
            .skip(4)
            .and_then(|()| f.prefixed32())
            .and_then(|()| f.prefixed32())
            .and_then(|()| f.map()),
        // Attachment: log time, create time, name, media type, data (8-byte length), CRC.
        0x09 => f
            .skip(16)
            .and_then(|()| f.prefixed32())
            .and_then(|()| f.prefixed32())
            .and_then(|()| {
                let length = usize::try_from(u64_at(f.body, f.at)?).ok()?;
                f.skip(8)?;
                f.skip(length)
            })
            .and_then(|()| f.skip(4)),
        // Metadata: name, map.
        0x0C => f.prefixed32().and_then(|()| f.map()),
        // Header: profile, library.
        0x01 => f.prefixed32().and_then(|()| f.prefixed32()),
        // Message: channel id, sequence, log time, publish time, then the payload.
        0x05 => f.skip(22),
        // Everything else (indexes, statistics, summary offsets, …) is not handed over.
        _ => None,
    };
    fits.is_some()
}

/// Hands every complete record of `records` (a chunk's decompressed contents) to `on_record`;
/// returns how many there were and whether the last one was cut.
fn walk_inner<E>(
    records: &[u8],
    trusted: bool,
    on_record: &mut impl FnMut(Record<'_>, bool) -> Result<(), E>,
) -> Result<(usize, bool), E> {
    let mut at = 0usize;
    let mut count = 0;
    while at < records.len() {
        let Some(length) = u64_at(records, at + 1) else {
            return Ok((count, true));
        };
        let body = at + RECORD_HEADER_BYTES;
        let Some(end) = usize::try_from(length).ok().and_then(|l| body.checked_add(l)) else {
            return Ok((count, true));
        };
        let Some(data) = records.get(body..end) else {
            return Ok((count, true));
        };
        // A record the `mcap` crate cannot parse inside a chunk is skipped, like an unknown
        // opcode.
        if fields_fit(records[at], data)
            && let Ok(record) = mcap::parse_record(records[at], data)
        {
            on_record(record, trusted)?;
            count += 1;
        }
        at = end;
    }
    Ok((count, false))
}

/// A chunk's records decompressed ahead of the walk.
struct Decompressed {
    /// Offset of the chunk's record in the file.
    at: usize,
    records: Vec<u8>,
    /// Why the records stop early, if they do.
    error: Option<String>,
    /// The records' CRC-32 (computed beside the decompression; 0 when the chunk has none).
    crc: u32,
}

/// The most a chunk's records are taken to expand to: what its header claims, within what the
/// compressed bytes can hold.
fn chunk_limit(frame: &ChunkFrame<'_>) -> u64 {
    frame
        .uncompressed_size
        .min(MAX_CHUNK_UNCOMPRESSED_BYTES)
        .min((frame.records.len() as u64).saturating_mul(MAX_COMPRESSION_RATIO) + (64 << 10))
}

/// Uncompressed bytes decompressed ahead at most: a bound on the memory the look-ahead holds.
const AHEAD_BYTES: u64 = 256 << 20;

/// Decompresses the chunk whose record starts at `at` and the whole chunks right after it (one
/// per thread, within [`AHEAD_BYTES`]) in parallel, into buffers taken from `spare`. Empty when
/// the record at `at` has no chunk header.
fn decompress_ahead(bytes: &[u8], at: usize, spare: &mut Vec<Vec<u8>>) -> Vec<Decompressed> {
    use rayon::prelude::*;
    let mut batch = Vec::new();
    let mut next = at;
    let mut total = 0u64;
    while batch.len() < rayon::current_num_threads().max(1) {
        let (Some(&opcode), Some(length)) = (bytes.get(next), u64_at(bytes, next + 1)) else {
            break;
        };
        let body = next + RECORD_HEADER_BYTES;
        let available = bytes.len().saturating_sub(body);
        let whole = length <= available as u64;
        let data =
            &bytes[body.min(bytes.len())..body.min(bytes.len()) + if whole { length as usize } else { available }];
        if opcode == CHUNK_OPCODE {
            // The first chunk always (cut or not); those after it only when whole.
            let Some(frame) = chunk_frame(data).filter(|f| next == at || (whole && f.whole)) else {
                break;
            };
            let limit = chunk_limit(&frame);
            if next != at && total + limit > AHEAD_BYTES {
                break;
            }
            total += limit;
            batch.push((next, frame, limit, spare.pop().unwrap_or_default()));
        } else if next == at || !whole {
            break;
        }
        if !whole {
            break;
        }
        next = body + length as usize;
    }
    batch
        .into_par_iter()
        .map(|(at, frame, limit, mut records)| {
            let error = decompress(frame.compression, frame.records, limit, &mut records);
            let crc = if frame.uncompressed_crc == 0 {
                0
            } else {
                crc32fast::hash(&records)
            };
            Decompressed {
                at,
                records,
                error,
                crc,
            }
        })
        .collect()
}

/// Walks `bytes` (a whole or damaged MCAP file), handing every record it can read to
/// `on_record(record, trusted)`: schemas, channels, messages (chunked or not), attachments and
/// metadata, including the summary's schemas and channels when the file was finished. Records of a bad chunk come
/// with `trusted = false`.
pub fn walk<E>(
    bytes: &[u8],
    mut on_record: impl FnMut(Record<'_>, bool) -> Result<(), E>,
) -> Result<WalkReport, WalkError<E>> {
    if bytes.len() < MCAP_MAGIC.len() || &bytes[..MCAP_MAGIC.len()] != MCAP_MAGIC {
        return Err(WalkError::NotMcap { bytes: bytes.len() });
    }
    let mut report = WalkReport::default();
    // Chunks decompressed ahead, in parallel, each with the offset of its record; their buffers
    // go back to `spare` once walked, so that a log's chunks reuse a few buffers' pages.
    let mut ahead: std::collections::VecDeque<Decompressed> = std::collections::VecDeque::new();
    let mut spare: Vec<Vec<u8>> = Vec::new();
    let file_bytes = bytes.len() as u64;
    let mut at = MCAP_MAGIC.len();
    while at < bytes.len() {
        let cut = |reason: String, records: usize| Cut {
            at_byte: at as u64,
            file_bytes,
            reason,
            records_from_cut_chunk: records,
        };
        let opcode = bytes[at];
        let Some(length) = u64_at(bytes, at + 1) else {
            if bytes[at..] != MCAP_MAGIC[..bytes.len() - at] {
                report.cut = Some(cut("a record's header is cut off".into(), 0));
            } else {
                report.cut = Some(cut("the closing magic is cut off".into(), 0));
            }
            break;
        };
        let body = at + RECORD_HEADER_BYTES;
        let available = bytes.len() - body;
        let whole = length <= available as u64;
        let data = &bytes[body..body + if whole { length as usize } else { available }];
        if opcode == CHUNK_OPCODE {
            let Some(frame) = chunk_frame(data) else {
                report.cut = Some(cut("a chunk's header is cut off".into(), 0));
                break;
            };
            if ahead.front().is_none_or(|chunk| chunk.at != at) {
                spare.extend(ahead.drain(..).map(|chunk| chunk.records));
                ahead = decompress_ahead(bytes, at, &mut spare).into();
            }
            let Some(Decompressed {
                records: buffer,
                error,
                crc,
                ..
            }) = ahead.pop_front()
            else {
                report.cut = Some(cut("a chunk's header is cut off".into(), 0));
                break;
            };
            let records = &buffer[..];
            if frame.whole && whole {
                let crc_ok = frame.uncompressed_crc == 0 || crc == frame.uncompressed_crc;
                let complete = records.len() as u64 == frame.uncompressed_size;
                let trusted = error.is_none() && crc_ok && complete;
                let (count, _) = walk_inner(records, trusted, &mut on_record).map_err(WalkError::Handler)?;
                if trusted {
                    report.records += count;
                } else {
                    report.bad_chunks.push(BadChunk {
                        at_byte: at as u64,
                        message_time_nanos: (frame.start_time, frame.end_time),
                        reason: match error {
                            Some(e) => format!("does not decompress: {e}"),
                            None if !complete => format!(
                                "holds {} bytes uncompressed, its header says {}",
                                records.len(),
                                frame.uncompressed_size
                            ),
                            None => "CRC mismatch".to_owned(),
                        },
                    });
                }
                spare.push(buffer);
            } else {
                // Cut inside the chunk: keep the complete records that decompress.
                let (count, _) = walk_inner(records, true, &mut on_record).map_err(WalkError::Handler)?;
                report.records += count;
                // A chunk still being written has placeholders for its times and length.
                let times = if (frame.start_time, frame.end_time) == (0, 0) {
                    String::new()
                } else {
                    format!(" (messages {} … {} ns)", frame.start_time, frame.end_time)
                };
                let declared = u64_at(data, 32 + frame.compression.len())
                    .filter(|n| *n != u64::MAX && *n != 0)
                    .map_or_else(
                        || " (a chunk still being written: its length was not yet known)".to_owned(),
                        |n| format!(" of its {n}"),
                    );
                report.cut = Some(cut(
                    format!(
                        "a chunk{times} is cut after {} compressed bytes{declared}",
                        frame.records.len()
                    ),
                    count,
                ));
                break;
            }
        } else if !whole {
            report.cut = Some(cut(
                format!("a record (opcode 0x{opcode:02x}, {length} bytes) runs past the end of the file"),
                0,
            ));
            break;
        } else if opcode == FOOTER_OPCODE {
            report.finished = true;
            break;
        } else if fields_fit(opcode, data)
            && let Ok(record) = mcap::parse_record(opcode, data)
        {
            on_record(record, true).map_err(WalkError::Handler)?;
            report.records += 1;
        }
        at = body + length as usize;
    }
    if !report.finished && report.cut.is_none() {
        report.cut = Some(Cut {
            at_byte: file_bytes,
            file_bytes,
            reason: "the file ends after a whole record but has no footer (the recording did not finish)".into(),
            records_from_cut_chunk: 0,
        });
    }
    Ok(report)
}
