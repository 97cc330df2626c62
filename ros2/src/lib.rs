//! ROS 2 messages without a ROS install.
//!
//! - [`cdr`]: the 4-byte encapsulation header (little- or big-endian plain CDR, options ignored,
//!   trailing padding tolerated) around serde encoding and decoding by `re_cdr`;
//! - [`msg`]: serde structs of the message types a multiscopic capture and its results use
//!   (images, camera info, transforms, joint states, strings, disparity images, point clouds),
//!   fields in `.msg` order, byte sequences borrowed when decoding;
//! - [`schema`]: their exact `ros2msg` schema texts and type hashes;
//! - [`bag`]: rosbag2's `metadata.yaml` (written for a bag directory, its file list read back)
//!   and the QoS profiles a channel offers.
//!
//! No mcap here: `record` writes bags with these pieces and `replay` reads them.

pub mod bag;
pub mod cdr;
pub mod msg;
pub mod schema;

pub use cdr::{CdrError, Endianness, decode, encode, encode_with};
