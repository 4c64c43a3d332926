//! NumPy `.npz` archives written for people who analyse predictions in NumPy: a zip of
//! `NAME.npy` entries (stored, not deflated), each a version-1.0 `.npy` of little-endian
//! float32 in C order. `numpy.load(path)` reads them; so does
//! `osrt_dataset::import::npy::read_npz`.

use crate::error::{InteropError, Result};
use std::io::{Seek, Write};

/// One named array: its shape and values (C order).
#[derive(Debug, Clone, PartialEq)]
pub struct NamedArray {
    pub name: String,
    pub shape: Vec<usize>,
    pub values: Vec<f32>,
}

impl NamedArray {
    pub fn new(name: impl Into<String>, shape: Vec<usize>, values: Vec<f32>) -> Self {
        Self {
            name: name.into(),
            shape,
            values,
        }
    }
}

/// The `.npy` bytes of one float32 array.
pub fn npy_bytes(shape: &[usize], values: &[f32]) -> Vec<u8> {
    let dims = match shape.len() {
        1 => format!("({},)", shape[0]),
        _ => format!(
            "({})",
            shape
                .iter()
                .map(usize::to_string)
                .collect::<Vec<_>>()
                .join(", ")
        ),
    };
    let mut header = format!("{{'descr': '<f4', 'fortran_order': False, 'shape': {dims}, }}");
    // Magic (6) + version (2) + length (2) + header + '\n', padded to a multiple of 64.
    let unpadded = 10 + header.len() + 1;
    header.push_str(&" ".repeat(unpadded.next_multiple_of(64) - unpadded));
    header.push('\n');
    let mut out = Vec::with_capacity(10 + header.len() + 4 * values.len());
    out.extend_from_slice(b"\x93NUMPY\x01\x00");
    out.extend_from_slice(&(header.len() as u16).to_le_bytes());
    out.extend_from_slice(header.as_bytes());
    for v in values {
        out.extend_from_slice(&v.to_le_bytes());
    }
    out
}

/// Writes `arrays` as an `.npz` archive to `out`; `path` names it in errors.
pub fn write_npz<W: Write + Seek>(out: W, path: &str, arrays: &[NamedArray]) -> Result<()> {
    let err = |reason: String| InteropError::File {
        path: path.to_string(),
        reason,
    };
    let mut zip = zip::ZipWriter::new(out);
    // Stored: predictions are float noise to a compressor, and numpy maps stored entries
    // without inflating them.
    let opts = zip::write::SimpleFileOptions::default()
        .compression_method(zip::CompressionMethod::Stored)
        .large_file(true);
    for a in arrays {
        let n: usize = a.shape.iter().product();
        if n != a.values.len() {
            return Err(err(format!(
                "array `{}`: shape {:?} holds {n} values, {} given",
                a.name,
                a.shape,
                a.values.len()
            )));
        }
        zip.start_file(format!("{}.npy", a.name), opts)
            .map_err(|e| err(e.to_string()))?;
        zip.write_all(&npy_bytes(&a.shape, &a.values))
            .map_err(|e| err(e.to_string()))?;
    }
    zip.finish().map_err(|e| err(e.to_string()))?;
    Ok(())
}
