//! `replay recover`: rewrites what a damaged log still holds as a finished one.
//!
//! The records that [`crate::salvage::walk`] can read (schemas, channels with their ids, every
//! complete message, attachments and metadata) are written, in file order, into a new log with
//! zstd chunks, message and chunk indexes, statistics and CRCs, under a temporary name renamed
//! into place when done. Records of a bad chunk are left out. What the new log holds is then
//! read back as view sets, so the report says which sets survived whole.

use std::collections::HashSet;
use std::path::{Path, PathBuf};

use mcap::records::Record;

use crate::salvage::{BadChunk, WalkError, walk};

/// Errors of a recovery.
#[derive(Debug, thiserror::Error)]
pub enum RecoverError {
    /// The input cannot be read.
    #[error("cannot read '{path}'")]
    Read {
        /// Input file.
        path: PathBuf,
        /// Cause.
        #[source]
        source: std::io::Error,
    },
    /// A bag directory of several storage files.
    #[error(
        "'{}' is a bag of {} storage files; recover each one (`replay recover FILE -o FIXED.mcap`): {}",
        path.display(),
        files.len(),
        files.iter().map(|f| f.display().to_string()).collect::<Vec<_>>().join(", ")
    )]
    SeveralFiles {
        /// The bag directory.
        path: PathBuf,
        /// Its files.
        files: Vec<PathBuf>,
    },
    /// The input is not an MCAP file.
    #[error("'{path}' is not an MCAP log (it does not start with the MCAP magic; {bytes} bytes)")]
    NotMcap {
        /// Input file.
        path: PathBuf,
        /// Its length.
        bytes: usize,
    },
    /// Writing the output failed.
    #[error("cannot write the recovered log '{path}' ({what})")]
    Write {
        /// Output file.
        path: PathBuf,
        /// The record being written.
        what: String,
        /// Cause.
        #[source]
        source: mcap::McapError,
    },
    /// Creating or committing the output file failed.
    #[error(transparent)]
    Output(#[from] record::log::LogError),
    /// The recovered log does not read back.
    #[error("the recovered log '{path}' does not read back")]
    ReadBack {
        /// Output file.
        path: PathBuf,
        /// Cause.
        #[source]
        source: Box<crate::ReplayError>,
    },
}

/// What a recovery kept and lost.
#[derive(Debug, Clone, Default, serde::Serialize)]
pub struct RecoverReport {
    /// The recovered log.
    pub output: PathBuf,
    /// Messages written.
    pub messages: usize,
    /// Channels written.
    pub channels: usize,
    /// Attachments written.
    pub attachments: usize,
    /// Metadata records written.
    pub metadata: usize,
    /// Whether the input had its footer (a finished log rewritten).
    pub input_finished: bool,
    /// Where the input was cut, when it was.
    pub cut: Option<String>,
    /// Chunks left out (bad CRC, not decompressing).
    pub bad_chunks: Vec<String>,
    /// Complete view sets in the recovered log (index, name).
    pub sets: Vec<(u32, String)>,
    /// Sets named by capture events but missing views, with what is missing.
    pub incomplete_sets: Vec<(u32, String)>,
}

impl RecoverReport {
    /// Whether anything was lost (a cut, a bad chunk, an incomplete set).
    pub fn lost_anything(&self) -> bool {
        self.cut.is_some() || !self.bad_chunks.is_empty() || !self.incomplete_sets.is_empty()
    }
}

fn describe_bad_chunk(chunk: &BadChunk) -> String {
    format!(
        "chunk at byte {} (messages {} … {} ns): {}",
        chunk.at_byte, chunk.message_time_nanos.0, chunk.message_time_nanos.1, chunk.reason
    )
}

/// Recovers `input` into `output` (written atomically).
pub fn recover_file(input: &Path, output: &Path) -> Result<RecoverReport, RecoverError> {
    // A ROS 2 bag directory of one storage file: that file.
    let input = &match crate::log::log_files(input) {
        Ok(files) if files.len() == 1 => files[0].clone(),
        Ok(files) if input.is_dir() => {
            return Err(RecoverError::SeveralFiles {
                path: input.to_path_buf(),
                files,
            });
        }
        _ => input.to_path_buf(),
    };
    let bytes = std::fs::read(input).map_err(|source| RecoverError::Read {
        path: input.to_path_buf(),
        source,
    })?;
    // Keep the header's profile (`ros2` for a ROS 2 bag), so that ROS tools take the result.
    let profile = match crate::salvage::record_at(&bytes, 8) {
        Some(Record::Header(header)) => header.profile,
        _ => String::new(),
    };
    let (file, writer) = record::log::OutputFile::create(output)?;
    let write_error = |what: String| {
        let path = output.to_path_buf();
        move |source| RecoverError::Write { path, what, source }
    };
    let options = record::log::LogOptions::new()
        .mcap_options(format!("multiscopic-replay-recover {}", env!("CARGO_PKG_VERSION")))
        .profile(profile);
    let mut mcap = options.create(writer).map_err(write_error("header".into()))?;
    let mut report = RecoverReport {
        output: output.to_path_buf(),
        ..RecoverReport::default()
    };
    let mut schemas = HashSet::new();
    let mut channels = HashSet::new();
    let walked = walk(&bytes, |record, trusted| -> Result<(), RecoverError> {
        if !trusted {
            return Ok(());
        }
        match record {
            // Schemas and channels once each (a finished log repeats them in its summary).
            Record::Schema { header, data } if header.id != 0 && schemas.insert(header.id) => {
                mcap.add_schema_with_id(header.id, &header.name, &header.encoding, &data)
                    .map_err(write_error(format!("schema '{}'", header.name)))?;
            }
            Record::Channel(channel)
                if (channel.schema_id == 0 || schemas.contains(&channel.schema_id)) && channels.insert(channel.id) =>
            {
                mcap.add_channel_with_id(
                    channel.id,
                    channel.schema_id,
                    &channel.topic,
                    &channel.message_encoding,
                    &channel.metadata,
                )
                .map_err(write_error(format!("channel '{}'", channel.topic)))?;
                report.channels += 1;
            }
            Record::Message { header, data } if channels.contains(&header.channel_id) => {
                mcap.write_to_known_channel(&header, &data)
                    .map_err(write_error(format!("message on channel {}", header.channel_id)))?;
                report.messages += 1;
            }
            Record::Attachment { header, data, .. } => {
                mcap.attach(&mcap::Attachment {
                    log_time: header.log_time,
                    create_time: header.create_time,
                    name: header.name.clone(),
                    media_type: header.media_type.clone(),
                    data,
                })
                .map_err(write_error(format!("attachment '{}'", header.name)))?;
                report.attachments += 1;
            }
            Record::Metadata(metadata) => {
                mcap.write_metadata(&metadata)
                    .map_err(write_error(format!("metadata '{}'", metadata.name)))?;
                report.metadata += 1;
            }
            _ => {}
        }
        Ok(())
    });
    let walked = match walked {
        Ok(walked) => walked,
        Err(WalkError::NotMcap { bytes }) => {
            return Err(RecoverError::NotMcap {
                path: input.to_path_buf(),
                bytes,
            });
        }
        Err(WalkError::Handler(error)) => return Err(error),
    };
    report.input_finished = walked.finished;
    report.cut = walked.cut.as_ref().map(ToString::to_string);
    report.bad_chunks = walked.bad_chunks.iter().map(describe_bad_chunk).collect();
    mcap.finish().map_err(write_error("summary".into()))?;
    let writer = mcap.into_inner();
    let path = file.commit(writer)?;
    let contents = crate::log::read_log_file(&path).map_err(|source| RecoverError::ReadBack {
        path: path.clone(),
        source: Box::new(source),
    })?;
    report.sets = contents.sets.iter().map(|s| (s.index, s.name.clone())).collect();
    report.incomplete_sets = contents.incomplete_sets;
    Ok(report)
}
