//! rosbag2's bag directory: `metadata.yaml` (version 9, what Jazzy's `ros2 bag` writes; a
//! reader of version 8 reads it too) and the QoS profiles a channel offers
//! (`offered_qos_profiles`, the same YAML in `metadata.yaml` and in each MCAP channel's
//! metadata). `ros2 bag play` republishes `/tf_static` with `transient_local` only when its
//! profile says so, so that late subscribers (rviz) still get the static transforms.
//!
//! Reading needs only the file list: [`file_list`] takes `relative_file_paths` from the YAML
//! (a small line parser: the workspace has no YAML library), or the directory's `*_N.mcap` files
//! in order when there is no `metadata.yaml`.

use std::fmt::Write as _;
use std::path::{Path, PathBuf};

/// The name of the metadata file in a bag directory.
pub const METADATA_FILE: &str = "metadata.yaml";
/// The name of the MCAP metadata record that repeats `metadata.yaml` inside the file.
pub const METADATA_RECORD: &str = "rosbag2";
/// The MCAP header profile of a ROS 2 bag.
pub const PROFILE: &str = "ros2";

/// The durability a topic's publisher offered.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Durability {
    /// Late subscribers get nothing from before they joined (the default).
    Volatile,
    /// Late subscribers get the last message(s): `/tf_static`, latched topics.
    TransientLocal,
}

/// One offered QoS profile: reliable, keep-last, the given depth and durability, no deadlines.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Qos {
    /// History depth.
    pub depth: u32,
    /// Durability.
    pub durability: Durability,
}

impl Qos {
    /// A sensor or `/tf` stream: reliable, volatile, depth 10.
    pub const STREAM: Self = Self {
        depth: 10,
        durability: Durability::Volatile,
    };
    /// `/tf_static`: reliable, transient local, depth 1.
    pub const LATCHED: Self = Self {
        depth: 1,
        durability: Durability::TransientLocal,
    };

    /// The YAML list (one profile) at `indent` spaces, as rosbag2 version 9 writes it.
    pub fn yaml(&self, indent: usize) -> String {
        let pad = " ".repeat(indent);
        let durability = match self.durability {
            Durability::Volatile => "volatile",
            Durability::TransientLocal => "transient_local",
        };
        let forever = |name: &str| format!("{pad}  {name}:\n{pad}    nsec: 4294967295\n{pad}    sec: 2147483647\n");
        let mut out = format!("{pad}- avoid_ros_namespace_conventions: false\n");
        out.push_str(&forever("deadline"));
        let _ = writeln!(out, "{pad}  depth: {}", self.depth);
        let _ = writeln!(out, "{pad}  durability: {durability}");
        let _ = writeln!(out, "{pad}  history: keep_last");
        out.push_str(&forever("lifespan"));
        let _ = writeln!(out, "{pad}  liveliness: automatic");
        out.push_str(&forever("liveliness_lease_duration"));
        let _ = write!(out, "{pad}  reliability: reliable");
        out
    }
}

/// A topic of a bag with its message count.
#[derive(Debug, Clone, PartialEq)]
pub struct TopicInfo {
    /// Topic name.
    pub name: String,
    /// Message type (`pkg/msg/Type`).
    pub type_name: String,
    /// The type's `RIHS01_…` hash (empty when unknown).
    pub type_hash: String,
    /// The profile its publisher offered.
    pub qos: Qos,
    /// Messages written.
    pub message_count: u64,
}

/// One storage file of a bag.
#[derive(Debug, Clone, PartialEq)]
pub struct FileInfo {
    /// Path relative to the bag directory (`NAME_0.mcap`).
    pub path: String,
    /// Earliest log time (ns).
    pub starting_time_nanos: u64,
    /// Latest minus earliest log time (ns).
    pub duration_nanos: u64,
    /// Messages in the file.
    pub message_count: u64,
}

/// What `metadata.yaml` says of a bag.
#[derive(Debug, Clone, PartialEq)]
pub struct BagInfo {
    /// The storage files in order.
    pub files: Vec<FileInfo>,
    /// Every topic.
    pub topics: Vec<TopicInfo>,
    /// The ROS distribution named in `ros_distro` (the chunks' zstd compression is the
    /// storage's, so `compression_format` stays empty).
    pub ros_distro: String,
}

impl BagInfo {
    /// The `metadata.yaml` text (version 9).
    pub fn to_yaml(&self) -> String {
        let start = self.files.iter().map(|f| f.starting_time_nanos).min().unwrap_or(0);
        let end = self
            .files
            .iter()
            .map(|f| f.starting_time_nanos + f.duration_nanos)
            .max()
            .unwrap_or(0);
        let count: u64 = self.files.iter().map(|f| f.message_count).sum();
        let mut out = String::from("rosbag2_bagfile_information:\n");
        let _ = writeln!(out, "  compression_format: ''");
        let _ = writeln!(out, "  compression_mode: ''");
        let _ = writeln!(out, "  custom_data: {{}}");
        let _ = writeln!(out, "  duration:\n    nanoseconds: {}", end - start);
        let _ = writeln!(out, "  files:");
        for f in &self.files {
            let _ = writeln!(out, "  - duration:\n      nanoseconds: {}", f.duration_nanos);
            let _ = writeln!(out, "    message_count: {}", f.message_count);
            let _ = writeln!(out, "    path: {}", yaml_string(&f.path));
            let _ = writeln!(
                out,
                "    starting_time:\n      nanoseconds_since_epoch: {}",
                f.starting_time_nanos
            );
        }
        let _ = writeln!(out, "  message_count: {count}");
        let _ = writeln!(out, "  relative_file_paths:");
        for f in &self.files {
            let _ = writeln!(out, "  - {}", yaml_string(&f.path));
        }
        let _ = writeln!(out, "  ros_distro: {}", self.ros_distro);
        let _ = writeln!(out, "  starting_time:\n    nanoseconds_since_epoch: {start}");
        let _ = writeln!(out, "  storage_identifier: mcap");
        let _ = writeln!(out, "  topics_with_message_count:");
        for t in &self.topics {
            let _ = writeln!(out, "  - message_count: {}", t.message_count);
            let _ = writeln!(out, "    topic_metadata:");
            let _ = writeln!(out, "      name: {}", t.name);
            let _ = writeln!(out, "      offered_qos_profiles:\n{}", t.qos.yaml(6));
            let _ = writeln!(out, "      serialization_format: cdr");
            let _ = writeln!(out, "      type: {}", t.type_name);
            let _ = writeln!(out, "      type_description_hash: {}", t.type_hash);
        }
        let _ = writeln!(out, "  version: 9");
        out
    }
}

/// A YAML scalar: as it is when plain, else single-quoted (a name with `: `, ` #`, or a leading
/// indicator such as `[`, `*`, `&`, `!`).
fn yaml_string(text: &str) -> String {
    let plain = !text.is_empty()
        && !text.contains(": ")
        && !text.contains(" #")
        && !text.ends_with(':')
        && !text.starts_with(|c: char| "[]{}*&!|>'\"%@`#,?:- ".contains(c));
    if plain {
        text.to_owned()
    } else {
        format!("'{}'", text.replace('\'', "''"))
    }
}

/// Why a bag directory's files cannot be listed.
#[derive(Debug, thiserror::Error)]
pub enum BagError {
    /// The directory or its metadata cannot be read.
    #[error("cannot read '{}'", path.display())]
    Io {
        /// The path.
        path: PathBuf,
        /// Cause.
        #[source]
        source: std::io::Error,
    },
    /// A listed file is missing.
    #[error("'{}' lists '{listed}', which is not in the bag directory", metadata.display())]
    MissingFile {
        /// The metadata file.
        metadata: PathBuf,
        /// The file it lists.
        listed: String,
    },
    /// The directory holds no storage file.
    #[error(
        "'{}' is a directory without a rosbag2 metadata.yaml or any .mcap file (a ROS 2 bag is a directory written by `ros2 bag record -s mcap`, or one .mcap file){}",
        dir.display(),
        partial_hint(partial)
    )]
    Empty {
        /// The directory.
        dir: PathBuf,
        /// Temporary files of a recording that did not finish (`.NAME.partial-PID`).
        partial: Vec<PathBuf>,
    },
    /// The metadata names a storage other than MCAP.
    #[error("'{}' is a {storage} bag; only MCAP storage is read (convert it with `ros2 bag convert`)", metadata.display())]
    Storage {
        /// The metadata file.
        metadata: PathBuf,
        /// Its `storage_identifier`.
        storage: String,
    },
}

/// The storage files of a bag directory, in order: those `metadata.yaml` lists, else the
/// directory's `.mcap` files ordered by their `_N` suffix (then by name).
pub fn file_list(dir: &Path) -> Result<Vec<PathBuf>, BagError> {
    let metadata = dir.join(METADATA_FILE);
    match std::fs::read_to_string(&metadata) {
        Ok(text) => {
            if let Some(storage) = yaml_scalar(&text, "storage_identifier")
                && storage != "mcap"
            {
                return Err(BagError::Storage { metadata, storage });
            }
            let listed = relative_file_paths(&text);
            if !listed.is_empty() {
                return listed
                    .into_iter()
                    .map(|name| {
                        let path = dir.join(&name);
                        if path.is_file() {
                            Ok(path)
                        } else {
                            Err(BagError::MissingFile {
                                metadata: metadata.clone(),
                                listed: name,
                            })
                        }
                    })
                    .collect();
            }
        }
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => {}
        Err(source) => return Err(BagError::Io { path: metadata, source }),
    }
    let entries = std::fs::read_dir(dir).map_err(|source| BagError::Io {
        path: dir.to_path_buf(),
        source,
    })?;
    let mut files: Vec<(u64, PathBuf)> = entries
        .filter_map(Result::ok)
        .map(|e| e.path())
        .filter(|p| p.is_file() && p.extension().is_some_and(|e| e == "mcap"))
        .map(|p| (split_index(&p).unwrap_or(0), p))
        .collect();
    files.sort();
    if files.is_empty() {
        let partial = std::fs::read_dir(dir)
            .map(|entries| {
                entries
                    .filter_map(Result::ok)
                    .map(|e| e.path())
                    .filter(|p| p.file_name().is_some_and(|n| n.to_string_lossy().contains(".partial-")))
                    .collect()
            })
            .unwrap_or_default();
        return Err(BagError::Empty {
            dir: dir.to_path_buf(),
            partial,
        });
    }
    Ok(files.into_iter().map(|(_, p)| p).collect())
}

/// What to do with the temporary files of a recording that stopped before it finished.
fn partial_hint(partial: &[PathBuf]) -> String {
    match partial.first() {
        None => String::new(),
        Some(first) => format!(
            "; it holds {} unfinished recording file(s): `replay recover {} -o FIXED.mcap` finishes one",
            partial.len(),
            first.display()
        ),
    }
}

/// The `N` of `NAME_N.mcap`.
fn split_index(path: &Path) -> Option<u64> {
    let stem = path.file_stem()?.to_str()?;
    stem.rsplit_once('_')?.1.parse().ok()
}

/// The value of the first `key: value` line (any indentation), unquoted.
fn yaml_scalar(text: &str, key: &str) -> Option<String> {
    text.lines().find_map(|line| {
        let rest = line.trim_start().strip_prefix(key)?.strip_prefix(':')?;
        Some(unquote(rest.trim()))
    })
}

fn unquote(value: &str) -> String {
    match value.strip_prefix('\'').and_then(|v| v.strip_suffix('\'')) {
        Some(quoted) => quoted.replace("''", "'"),
        None => value
            .strip_prefix('"')
            .and_then(|v| v.strip_suffix('"'))
            .unwrap_or(value)
            .to_owned(),
    }
}

/// The items of the `relative_file_paths:` block list.
fn relative_file_paths(text: &str) -> Vec<String> {
    let mut lines = text.lines().skip_while(|l| l.trim() != "relative_file_paths:");
    let Some(key) = lines.next() else {
        return Vec::new();
    };
    let indent = key.len() - key.trim_start().len();
    lines
        .take_while(|l| {
            let i = l.len() - l.trim_start().len();
            let t = l.trim_start();
            t.starts_with("- ") && i >= indent
        })
        .map(|l| unquote(l.trim_start().trim_start_matches("- ").trim()))
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn info() -> BagInfo {
        BagInfo {
            files: vec![FileInfo {
                path: "capture_0.mcap".into(),
                starting_time_nanos: 5,
                duration_nanos: 10,
                message_count: 3,
            }],
            topics: vec![TopicInfo {
                name: "/tf_static".into(),
                type_name: "tf2_msgs/msg/TFMessage".into(),
                type_hash: crate::schema::TF_MESSAGE.type_hash.into(),
                qos: Qos::LATCHED,
                message_count: 1,
            }],
            ros_distro: "jazzy".into(),
        }
    }

    #[test]
    fn file_names_yaml_would_misread_are_quoted_and_read_back() {
        let mut odd = info();
        odd.files[0].path = "it's: [a]_0.mcap".into();
        let yaml = odd.to_yaml();
        assert!(yaml.contains("  - 'it''s: [a]_0.mcap'\n"), "{yaml}");
        assert_eq!(relative_file_paths(&yaml), vec!["it's: [a]_0.mcap".to_owned()]);
    }

    #[test]
    fn the_written_metadata_lists_its_files_and_latches_tf_static() {
        let yaml = info().to_yaml();
        assert_eq!(relative_file_paths(&yaml), vec!["capture_0.mcap".to_owned()]);
        assert_eq!(yaml_scalar(&yaml, "storage_identifier").as_deref(), Some("mcap"));
        assert!(yaml.contains("      offered_qos_profiles:\n      - avoid_ros_namespace_conventions: false"));
        assert!(yaml.contains("        durability: transient_local\n"));
        assert!(yaml.contains("  duration:\n    nanoseconds: 10\n"));
    }

    #[test]
    fn a_directory_with_only_an_unfinished_recording_says_how_to_recover_it() {
        let dir = std::env::temp_dir().join(format!("ros2-bag-partial-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        std::fs::create_dir_all(&dir).unwrap_or_else(|e| panic!("{e}"));
        std::fs::write(dir.join(".cap_0.mcap.partial-42"), b"").unwrap_or_else(|e| panic!("{e}"));
        let error = file_list(&dir).map(|_| ()).unwrap_err().to_string();
        assert!(
            error.contains("1 unfinished recording file(s)")
                && error.contains("replay recover")
                && error.contains(".cap_0.mcap.partial-42"),
            "{error}"
        );
        std::fs::remove_dir_all(&dir).unwrap_or_else(|e| panic!("{e}"));
    }

    #[test]
    fn a_directory_without_metadata_is_read_in_split_order() {
        let dir = std::env::temp_dir().join(format!("ros2-bag-test-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        std::fs::create_dir_all(&dir).unwrap_or_else(|e| panic!("{e}"));
        for name in ["b_10.mcap", "b_2.mcap", "notes.txt"] {
            std::fs::write(dir.join(name), b"").unwrap_or_else(|e| panic!("{e}"));
        }
        let files = file_list(&dir).unwrap_or_else(|e| panic!("{e}"));
        let names: Vec<_> = files.iter().filter_map(|p| p.file_name()?.to_str()).collect();
        assert_eq!(names, ["b_2.mcap", "b_10.mcap"]);
        std::fs::write(dir.join(METADATA_FILE), info().to_yaml()).unwrap_or_else(|e| panic!("{e}"));
        let error = file_list(&dir).map(|_| ()).unwrap_err().to_string();
        assert!(error.contains("lists 'capture_0.mcap'"), "{error}");
        std::fs::remove_dir_all(&dir).unwrap_or_else(|e| panic!("{e}"));
        let error = file_list(&dir).map(|_| ()).unwrap_err().to_string();
        assert!(error.contains("cannot read"), "{error}");
    }
}
