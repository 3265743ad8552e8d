//! A ROS 2 message on the wire: a 4-byte encapsulation header (representation id, options),
//! then the message in plain CDR with alignment counted from after the header. The byte order
//! is the sender's; murk writes little-endian.

use byteorder::{BigEndian, LittleEndian};
use serde::{de::DeserializeOwned, Serialize};

/// `CDR_BE` and `CDR_LE` representation ids (OMG DDS-XTypes, Table 60).
const CDR_BE: [u8; 2] = [0x00, 0x00];
const CDR_LE: [u8; 2] = [0x00, 0x01];

/// Decodes a CDR-encapsulated message; the error says what is wrong with the bytes.
pub fn decode<T: DeserializeOwned>(bytes: &[u8]) -> Result<T, String> {
    if bytes.len() < 4 {
        return Err(format!(
            "{} bytes, shorter than the CDR header",
            bytes.len()
        ));
    }
    let body = &bytes[4..];
    let decoded = match [bytes[0], bytes[1]] {
        CDR_LE => cdr_encoding::from_bytes::<T, LittleEndian>(body),
        CDR_BE => cdr_encoding::from_bytes::<T, BigEndian>(body),
        other => {
            return Err(format!(
                "representation {other:02x?} is not plain CDR (XCDR2 and parameter lists are \
                 not read)"
            ))
        }
    };
    decoded
        .map(|(v, _)| v)
        .map_err(|e| format!("not a valid message: {e}"))
}

/// Encodes a message as little-endian CDR with its encapsulation header.
pub fn encode<T: Serialize>(value: &T) -> Vec<u8> {
    let body = cdr_encoding::to_vec::<T, LittleEndian>(value)
        // Serialising the plain structs of `msgs` to a Vec cannot fail: every field type is one
        // CDR has, and writing to memory does not fail.
        .expect("CDR encoding of a ROS message");
    let mut out = Vec::with_capacity(body.len() + 4);
    out.extend_from_slice(&CDR_LE);
    out.extend_from_slice(&[0, 0]);
    out.extend_from_slice(&body);
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::bag::msgs::{CameraInfo, Header, Image, Time};

    #[test]
    fn a_camera_info_round_trips_with_its_doubles_aligned_to_eight() {
        let info = CameraInfo {
            header: Header {
                stamp: Time { sec: 7, nanosec: 9 },
                frame_id: "left".into(),
            },
            height: 4,
            width: 6,
            distortion_model: "plumb_bob".into(),
            d: vec![0.1, -0.2],
            k: [1.0, 0.0, 2.0, 0.0, 1.0, 3.0, 0.0, 0.0, 1.0],
            p: [5.0; 12],
            ..CameraInfo::default()
        };
        let bytes = encode(&info);
        assert_eq!(&bytes[..4], &[0, 1, 0, 0]);
        // header: sec, nanosec (8), frame_id "left\0" (4 + 5 = 9) → 17, pad to 20; height,
        // width (8) → 28; "plumb_bob\0" (4 + 10) → 42, pad to 44; d's length (4) → 48, which
        // is where d's first double starts (aligned to 8 from the body's start).
        let body = &bytes[4..];
        assert_eq!(f64::from_le_bytes(body[48..56].try_into().unwrap()), 0.1);
        assert_eq!(decode::<CameraInfo>(&bytes).unwrap(), info);
    }

    #[test]
    fn big_endian_messages_are_read() {
        let img = Image {
            height: 1,
            width: 2,
            encoding: "mono8".into(),
            step: 2,
            data: vec![3, 4],
            ..Image::default()
        };
        let mut bytes = vec![0, 0, 0, 0];
        bytes.extend(cdr_encoding::to_vec::<_, BigEndian>(&img).unwrap());
        assert_eq!(decode::<Image>(&bytes).unwrap(), img);
    }

    #[test]
    fn truncated_and_foreign_encodings_are_refused() {
        let bytes = encode(&Image {
            data: vec![1; 100],
            ..Image::default()
        });
        assert!(decode::<Image>(&bytes[..bytes.len() - 10]).is_err());
        assert!(decode::<Image>(&bytes[..3]).is_err());
        let mut xcdr2 = bytes.clone();
        xcdr2[1] = 0x07;
        assert!(decode::<Image>(&xcdr2)
            .unwrap_err()
            .contains("not plain CDR"));
    }
}
