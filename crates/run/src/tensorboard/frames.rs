//! Event-file encoding: TFRecord frames (length, payload, masked CRC-32C checksums)
//! around `tensorflow.Event` messages, and reading them back.

use super::proto::Event;
use crate::{Result, RunError};
use prost::Message;

/// TFRecord's checksum: CRC-32C (Castagnoli), rotated right by 15 bits plus a constant.
pub(super) fn masked_crc(data: &[u8]) -> u32 {
    const CRC32C: crc::Crc<u32> = crc::Crc::<u32>::new(&crc::CRC_32_ISCSI);
    CRC32C
        .checksum(data)
        .rotate_right(15)
        .wrapping_add(0xa282_ead8)
}

/// One TFRecord frame around `payload`.
pub(super) fn frame(payload: &[u8], out: &mut Vec<u8>) {
    let len = (payload.len() as u64).to_le_bytes();
    out.extend_from_slice(&len);
    out.extend_from_slice(&masked_crc(&len).to_le_bytes());
    out.extend_from_slice(payload);
    out.extend_from_slice(&masked_crc(payload).to_le_bytes());
}

/// Where and why an event file stops being readable.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct BadRecord {
    /// The offset of the frame that cannot be read.
    pub offset: usize,
    pub reason: String,
}

/// The events of an event file's bytes, each with the end offset of its frame, and the
/// frame reading stopped at (`None`: the bytes end with a whole frame). A torn frame (a
/// write cut short), a failed checksum or a payload that is no `Event` ends the read:
/// what follows cannot be framed. A frame's declared length is compared with the bytes
/// there before anything is sliced, so no length, however crafted, sizes an allocation
/// or reaches past the end.
pub fn scan_events(bytes: &[u8]) -> (Vec<(Event, usize)>, Option<BadRecord>) {
    let mut out = Vec::new();
    let mut at = 0usize;
    while at < bytes.len() {
        let rest = bytes.len() - at;
        let bad = |reason: String| Some(BadRecord { offset: at, reason });
        if rest < 12 {
            let reason = format!("a torn frame: {rest} bytes of its 12-byte header");
            return (out, bad(reason));
        }
        let head = &bytes[at..at + 12];
        let len = u64::from_le_bytes(head[..8].try_into().expect("8 bytes"));
        let crc = u32::from_le_bytes(head[8..].try_into().expect("4 bytes"));
        if masked_crc(&head[..8]) != crc {
            return (out, bad("the length's checksum does not match".into()));
        }
        // The header, the record, its 4-byte checksum.
        let fits = |l: &usize| rest.checked_sub(16).is_some_and(|room| *l <= room);
        let Some(len) = usize::try_from(len).ok().filter(fits) else {
            let reason = format!(
                "its header declares a record of {len} bytes and its 4-byte checksum, {} \
                 bytes follow",
                rest - 12
            );
            return (out, bad(reason));
        };
        let body = &bytes[at + 12..at + 12 + len];
        let tail = &bytes[at + 12 + len..at + 16 + len];
        if masked_crc(body).to_le_bytes() != tail {
            return (out, bad("the record's checksum does not match".into()));
        }
        match Event::decode(body) {
            Ok(e) => {
                at += 16 + len;
                out.push((e, at));
            }
            Err(e) => return (out, bad(format!("the record is no tensorflow.Event: {e}"))),
        }
    }
    (out, None)
}

/// The events of the event file `path` (as shown in errors) whose bytes are `bytes`,
/// each with the end offset of its frame; a file that is not whole frames throughout is
/// an error naming it.
pub fn read_events(path: &str, bytes: &[u8]) -> Result<Vec<(Event, usize)>> {
    match scan_events(bytes) {
        (events, None) => Ok(events),
        (_, Some(bad)) => Err(malformed(path, &bad)),
    }
}

pub(super) fn malformed(path: &str, bad: &BadRecord) -> RunError {
    RunError::Run {
        path: path.to_string(),
        reason: format!(
            "event file unreadable from byte {}: {}",
            bad.offset, bad.reason
        ),
    }
}
