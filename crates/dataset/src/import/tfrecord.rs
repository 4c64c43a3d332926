//! TFRecord files: a sequence of records, each framed as
//!
//! ```text
//! u64 length (little-endian) | u32 masked CRC-32C of those 8 bytes | payload | u32 masked CRC-32C of the payload
//! ```
//!
//! with CRC-32C (Castagnoli) masked as `((crc >> 15) | (crc << 17)) + 0xa282ead8`
//! (wrapping). Both checksums are verified; a bad one is an error naming the file, the
//! record and its offset, never a silently wrong scene.

use crate::error::{DatasetError, Result};
use std::io::{Read, Seek, SeekFrom};
use std::path::Path;
use std::sync::Arc;

/// Where one record lies: 24 bytes, the file shared (an index of MSN-Hard's million
/// records takes about 24 MB).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct RecordRef {
    pub file: Arc<Path>,
    /// Byte offset of the record's header.
    pub offset: u64,
    pub len: u64,
}

/// CRC-32C (Castagnoli, reflected) of `data`.
pub fn crc32c(data: &[u8]) -> u32 {
    const CRC32C: crc::Crc<u32> = crc::Crc::<u32>::new(&crc::CRC_32_ISCSI);
    CRC32C.checksum(data)
}

/// TFRecord's masked CRC-32C.
pub fn masked_crc(data: &[u8]) -> u32 {
    let c = crc32c(data);
    c.rotate_right(15).wrapping_add(0xa282_ead8)
}

fn bad(file: &Path, reason: String) -> DatasetError {
    DatasetError::Import {
        path: file.display().to_string(),
        reason,
    }
}

fn read_exact(f: &mut impl Read, buf: &mut [u8], file: &Path, what: &str) -> Result<()> {
    f.read_exact(buf)
        .map_err(|e| bad(file, format!("{what}: {e} (a truncated TFRecord file?)")))
}

/// The largest record read (it is held in memory whole): an MSN-Hard example, ten
/// cameras' PNGs, is a few MB.
pub const MAX_RECORD_BYTES: u64 = 256 << 20;

/// Every record of a file (headers checked, payloads skipped), in order.
pub fn index_file(file: &Path) -> Result<Vec<RecordRef>> {
    let mut f =
        std::io::BufReader::new(std::fs::File::open(file).map_err(|e| bad(file, e.to_string()))?);
    let size = std::fs::metadata(file)
        .map_err(|e| bad(file, e.to_string()))?
        .len();
    let shared: Arc<Path> = Arc::from(file);
    let mut out = Vec::new();
    let mut offset = 0u64;
    while offset < size {
        let mut head = [0u8; 12];
        let what = format!("record {} at byte {offset}", out.len());
        read_exact(&mut f, &mut head, file, &what)?;
        let len = u64::from_le_bytes(head[..8].try_into().expect("8 bytes"));
        let crc = u32::from_le_bytes(head[8..].try_into().expect("4 bytes"));
        if masked_crc(&head[..8]) != crc {
            return Err(bad(
                file,
                format!("{what}: the length's CRC-32C does not match"),
            ));
        }
        // Checked: a length near 2⁶⁴ with a valid checksum must not wrap past the test.
        let room = size.saturating_sub(offset).saturating_sub(16);
        if len > room {
            return Err(bad(
                file,
                format!("{what}: {len} bytes announced past the end"),
            ));
        }
        if len > MAX_RECORD_BYTES {
            return Err(bad(
                file,
                format!("{what}: {len} bytes, more than the {MAX_RECORD_BYTES} a record may hold"),
            ));
        }
        f.seek(SeekFrom::Current(len as i64 + 4))
            .map_err(|e| bad(file, e.to_string()))?;
        out.push(RecordRef {
            file: shared.clone(),
            offset,
            len,
        });
        offset += 16 + len;
    }
    Ok(out)
}

/// The payload of one record, its CRC-32C checked; `index` names it in errors.
pub fn read_record(r: &RecordRef, index: usize) -> Result<Vec<u8>> {
    let mut f = std::fs::File::open(&r.file).map_err(|e| bad(&r.file, e.to_string()))?;
    f.seek(SeekFrom::Start(r.offset + 12))
        .map_err(|e| bad(&r.file, e.to_string()))?;
    let what = format!("record {index} at byte {}", r.offset);
    let mut data = vec![0u8; r.len as usize];
    read_exact(&mut f, &mut data, &r.file, &what)?;
    let mut crc = [0u8; 4];
    read_exact(&mut f, &mut crc, &r.file, &what)?;
    if masked_crc(&data) != u32::from_le_bytes(crc) {
        return Err(bad(
            &r.file,
            format!("{what}: the payload's CRC-32C does not match"),
        ));
    }
    Ok(data)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn crc32c_matches_the_standard_check_value() {
        assert_eq!(crc32c(b"123456789"), 0xE306_9283);
        assert_eq!(crc32c(b""), 0);
    }

    fn record(payload: &[u8]) -> Vec<u8> {
        let len = (payload.len() as u64).to_le_bytes();
        let mut out = len.to_vec();
        out.extend(masked_crc(&len).to_le_bytes());
        out.extend(payload);
        out.extend(masked_crc(payload).to_le_bytes());
        out
    }

    /// Records come back in order; a flipped payload byte, a flipped length byte and a
    /// truncated file are errors naming the file and the record.
    #[test]
    fn records_are_framed_and_checked() {
        let dir = tempfile::tempdir().unwrap();
        let file = dir.path().join("x.tfrecord");
        let mut bytes = record(b"first");
        bytes.extend(record(b""));
        bytes.extend(record(b"third one"));
        std::fs::write(&file, &bytes).unwrap();
        let idx = index_file(&file).unwrap();
        let got: Vec<Vec<u8>> = idx
            .iter()
            .enumerate()
            .map(|(i, r)| read_record(r, i).unwrap())
            .collect();
        assert_eq!(got, [b"first".to_vec(), vec![], b"third one".to_vec()]);
        let mut flipped = bytes.clone();
        flipped[13] ^= 1;
        std::fs::write(&file, &flipped).unwrap();
        let e = read_record(&index_file(&file).unwrap()[0], 0)
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("x.tfrecord") && e.contains("record 0") && e.contains("payload"),
            "{e}"
        );
        let mut len = bytes.clone();
        len[21] ^= 1;
        std::fs::write(&file, &len).unwrap();
        let e = index_file(&file).unwrap_err().to_string();
        assert!(e.contains("record 1") && e.contains("length"), "{e}");
        std::fs::write(&file, &bytes[..bytes.len() - 3]).unwrap();
        assert!(
            index_file(&file)
                .unwrap_err()
                .to_string()
                .contains("record 2")
        );
    }

    /// A length near 2⁶⁴ with a valid checksum is refused, not wrapped into a backward
    /// seek (which looped forever).
    #[test]
    fn a_huge_length_with_a_valid_checksum_is_an_error() {
        let dir = tempfile::tempdir().unwrap();
        let file = dir.path().join("huge.tfrecord");
        for len in [u64::MAX, u64::MAX - 15, u64::MAX - 40, 1 << 63] {
            let mut bytes = record(b"first");
            let l = len.to_le_bytes();
            bytes.extend(l);
            bytes.extend(masked_crc(&l).to_le_bytes());
            bytes.extend(b"payload and crc");
            std::fs::write(&file, &bytes).unwrap();
            let e = index_file(&file).unwrap_err().to_string();
            assert!(
                e.contains("record 1") && e.contains("past the end"),
                "{len}: {e}"
            );
        }
        // A record larger than any real one, with the bytes present (a sparse file), is
        // refused before it is read into memory.
        let len = MAX_RECORD_BYTES + 1;
        let mut bytes = len.to_le_bytes().to_vec();
        bytes.extend(masked_crc(&len.to_le_bytes()).to_le_bytes());
        std::fs::write(&file, &bytes).unwrap();
        std::fs::OpenOptions::new()
            .write(true)
            .open(&file)
            .unwrap()
            .set_len(len + 16)
            .unwrap();
        let e = index_file(&file).unwrap_err().to_string();
        assert!(e.contains("record 0") && e.contains("may hold"), "{e}");
    }
}
