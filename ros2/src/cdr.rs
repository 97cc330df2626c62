//! CDR framing as ROS 2 uses it (plain CDR / XCDR1): a 4-byte encapsulation header that is not
//! part of the stream (`00 01` little-endian, `00 00` big-endian, then two option bytes that
//! readers ignore: some middlewares count trailing padding there), then the serde-encoded message
//! with every primitive aligned to its size from the first byte after the header.

use serde::{Deserialize, Serialize};

/// Byte order of a CDR stream.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Endianness {
    /// `CDR_LE` (representation id `00 01`), what every common ROS 2 middleware writes.
    Little,
    /// `CDR_BE` (representation id `00 00`).
    Big,
}

/// Why a payload is not a message.
#[derive(Debug, thiserror::Error)]
pub enum CdrError {
    /// Fewer bytes than the encapsulation header.
    #[error("{len} bytes are too few for a CDR message (the encapsulation header alone is 4)")]
    TooShort {
        /// Payload length.
        len: usize,
    },
    /// A representation other than plain CDR (e.g. a parameter list or XCDR2).
    #[error(
        "representation id {id:02x?} is not plain CDR (00 01 little-endian or 00 00 big-endian); parameter lists and XCDR2 are not read"
    )]
    Representation {
        /// The first two bytes.
        id: [u8; 2],
    },
    /// The stream does not decode as the type.
    #[error("the payload ({endianness:?}-endian CDR, {len} bytes) does not decode as {type_name}: {source}")]
    Decode {
        /// The type expected.
        type_name: &'static str,
        /// The stream's byte order.
        endianness: Endianness,
        /// Payload length.
        len: usize,
        /// The decoder's reason.
        #[source]
        source: re_cdr::Error,
    },
    /// The message could not be encoded.
    #[error("cannot encode a {type_name}: {source}")]
    Encode {
        /// The type.
        type_name: &'static str,
        /// The encoder's reason.
        #[source]
        source: re_cdr::Error,
    },
}

/// The header every message written here starts with: `CDR_LE`, no options.
pub const LITTLE_ENDIAN_HEADER: [u8; 4] = [0, 1, 0, 0];
/// The big-endian header.
pub const BIG_ENDIAN_HEADER: [u8; 4] = [0, 0, 0, 0];

/// The byte order a payload declares.
pub fn endianness(bytes: &[u8]) -> Result<Endianness, CdrError> {
    match bytes {
        [0, 1, _, _, ..] => Ok(Endianness::Little),
        [0, 0, _, _, ..] => Ok(Endianness::Big),
        [a, b, _, _, ..] => Err(CdrError::Representation { id: [*a, *b] }),
        _ => Err(CdrError::TooShort { len: bytes.len() }),
    }
}

/// Decodes a message (header included). Bytes after the message (padding) are ignored.
pub fn decode<'a, T: Deserialize<'a>>(bytes: &'a [u8]) -> Result<T, CdrError> {
    let endianness = endianness(bytes)?;
    let body = &bytes[4..];
    let decoded = match endianness {
        Endianness::Little => re_cdr::from_bytes::<T, re_cdr::LittleEndian>(body),
        Endianness::Big => re_cdr::from_bytes::<T, re_cdr::BigEndian>(body),
    };
    decoded
        .map(|(message, _consumed)| message)
        .map_err(|source| CdrError::Decode {
            type_name: short_type_name::<T>(),
            endianness,
            len: bytes.len(),
            source,
        })
}

/// Encodes a message as little-endian CDR with its header.
pub fn encode<T: Serialize>(message: &T) -> Result<Vec<u8>, CdrError> {
    encode_with(message, Endianness::Little)
}

/// Encodes a message in the given byte order with its header.
pub fn encode_with<T: Serialize>(message: &T, endianness: Endianness) -> Result<Vec<u8>, CdrError> {
    let (header, body) = match endianness {
        Endianness::Little => (LITTLE_ENDIAN_HEADER, re_cdr::to_vec::<T, re_cdr::LittleEndian>(message)),
        Endianness::Big => (BIG_ENDIAN_HEADER, re_cdr::to_vec::<T, re_cdr::BigEndian>(message)),
    };
    let body = body.map_err(|source| CdrError::Encode {
        type_name: short_type_name::<T>(),
        source,
    })?;
    let mut out = Vec::with_capacity(body.len() + 4);
    out.extend_from_slice(&header);
    out.extend_from_slice(&body);
    Ok(out)
}

fn short_type_name<T>() -> &'static str {
    let full = std::any::type_name::<T>();
    let base = full.split('<').next().unwrap_or(full);
    base.rsplit("::").next().unwrap_or(base)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::msg::{Header, Image, Time};

    fn image() -> Image<'static> {
        Image {
            header: Header {
                stamp: Time { sec: 1, nanosec: 2 },
                frame_id: "camera_optical".into(),
            },
            height: 1,
            width: 2,
            encoding: "mono8".into(),
            is_bigendian: 0,
            step: 2,
            data: std::borrow::Cow::Owned(vec![7, 9]),
        }
    }

    #[test]
    fn both_byte_orders_round_trip_and_options_and_padding_are_ignored() {
        for endianness in [Endianness::Little, Endianness::Big] {
            let mut bytes = encode_with(&image(), endianness).unwrap_or_else(|e| panic!("{e}"));
            assert_eq!(decode::<Image>(&bytes).unwrap_or_else(|e| panic!("{e}")), image());
            // Cyclone's options (3 bytes of padding) and the padding itself.
            bytes[3] = 3;
            bytes.extend_from_slice(&[0, 0, 0]);
            assert_eq!(decode::<Image>(&bytes).unwrap_or_else(|e| panic!("{e}")), image());
        }
    }

    #[test]
    fn the_image_layout_matches_the_worked_example() {
        // Payload offsets after the header: 24 height, 28 width, 32 encoding length, 36 text.
        let bytes = encode(&image()).unwrap_or_else(|e| panic!("{e}"));
        let body = &bytes[4..];
        assert_eq!(&body[0..4], &1i32.to_le_bytes());
        assert_eq!(&body[8..12], &15u32.to_le_bytes(), "frame id length counts the NUL");
        assert_eq!(&body[12..27], b"camera_optical\0");
        assert_eq!(&body[28..32], &1u32.to_le_bytes());
        assert_eq!(&body[32..36], &2u32.to_le_bytes());
    }

    #[test]
    fn other_representations_and_short_or_cut_payloads_are_errors() {
        assert!(matches!(decode::<Image>(&[0, 1]), Err(CdrError::TooShort { len: 2 })));
        assert!(matches!(
            decode::<Image>(&[0, 3, 0, 0, 1]),
            Err(CdrError::Representation { id: [0, 3] })
        ));
        let bytes = encode(&image()).unwrap_or_else(|e| panic!("{e}"));
        let error = decode::<Image>(&bytes[..bytes.len() - 1])
            .map(|_| ())
            .unwrap_err()
            .to_string();
        assert!(error.contains("does not decode as Image"), "{error}");
    }
}
