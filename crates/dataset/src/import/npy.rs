//! NumPy's `.npy` arrays and `.npz` archives (a zip of `.npy` files, stored or deflated),
//! read into f64 or text: the metadata of the ObSuRF releases. Format: the magic
//! `\x93NUMPY`, a version, a little-endian header length (u16 in version 1, u32 in 2 and
//! 3), a Python-literal header dict `{'descr': '<f8', 'fortran_order': False, 'shape':
//! (S, V, 3), }`, then the C-order data.

use crate::error::{DatasetError, Result};
use std::collections::BTreeMap;
use std::io::{Read, Seek};

/// One array: its shape and values, numbers as f64 (integers and booleans exactly, up to
/// 2^53) or text.
#[derive(Debug, Clone, PartialEq)]
pub struct Array {
    pub shape: Vec<usize>,
    pub values: Values,
}

#[derive(Debug, Clone, PartialEq)]
pub enum Values {
    Numbers(Vec<f64>),
    Text(Vec<String>),
}

impl Array {
    /// Elements per entry along the first axis (a scene's share).
    pub fn row_len(&self) -> usize {
        self.shape.iter().skip(1).product()
    }

    /// The numbers of row `i` (first axis), or `None` for text arrays.
    pub fn number_row(&self, i: usize) -> Option<&[f64]> {
        let n = self.row_len();
        match &self.values {
            Values::Numbers(v) => v.get(i * n..(i + 1) * n),
            Values::Text(_) => None,
        }
    }

    /// Element `j` of row `i` as text (numbers printed as integers where they are).
    pub fn text_at(&self, i: usize, j: usize) -> Option<String> {
        let k = i * self.row_len() + j;
        match &self.values {
            Values::Numbers(v) => v.get(k).map(|x| {
                if x.fract() == 0.0 && x.abs() < 1e15 {
                    format!("{}", *x as i64)
                } else {
                    format!("{x}")
                }
            }),
            Values::Text(v) => v.get(k).cloned(),
        }
    }
}

fn bad(path: &str, reason: impl Into<String>) -> DatasetError {
    DatasetError::Import {
        path: path.to_string(),
        reason: reason.into(),
    }
}

/// The value of `'key': …` in a header dict, up to the next top-level comma or brace.
fn header_field<'a>(header: &'a str, key: &str) -> Option<&'a str> {
    let at = header.find(&format!("'{key}'"))? + key.len() + 2;
    let rest = header[at..].trim_start().strip_prefix(':')?.trim_start();
    let end = if rest.starts_with('(') {
        rest.find(')')? + 1
    } else {
        rest.find([',', '}'])?
    };
    Some(rest[..end].trim())
}

/// A parsed `.npy` header: where the data starts, its dtype, shape and element count.
struct Header<'a> {
    data_start: usize,
    descr: &'a str,
    fortran: bool,
    shape: Vec<usize>,
    /// The shape's product (checked).
    n: usize,
}

impl Header<'_> {
    /// Bytes of the whole file the header announces (checked arithmetic: `None` past
    /// `usize`).
    fn file_len(&self) -> Option<usize> {
        let (_, width) = dtype(self.descr).ok()?;
        self.n.checked_mul(width)?.checked_add(self.data_start)
    }

    /// Bytes the decoded values take: an f64 per number, a `String` and its characters
    /// per text (`None` past `usize`).
    fn decoded_len(&self) -> Option<usize> {
        let (kind, width) = dtype(self.descr).ok()?;
        let each = if kind == 'U' {
            std::mem::size_of::<String>() + width
        } else {
            8
        };
        self.n.checked_mul(each)
    }
}

/// The element kind (`f`, `i`, `u`, `b`, `U`) and bytes per element of a dtype such as
/// `<f8`, `|u1` or `<U4`.
fn dtype(descr: &str) -> std::result::Result<(char, usize), String> {
    if descr.starts_with('>') {
        return Err(format!("big-endian dtype {descr} is not read"));
    }
    let kind = descr.strip_prefix(['<', '|', '=']).unwrap_or(descr);
    let mut chars = kind.chars();
    let kind_char = chars
        .next()
        .ok_or_else(|| format!("unknown dtype `{descr}`"))?;
    let count: usize = chars
        .as_str()
        .parse()
        .map_err(|_| format!("unknown dtype `{descr}`"))?;
    let width = if kind_char == 'U' {
        count.checked_mul(4)
    } else {
        Some(count)
    };
    match width {
        Some(w) if w > 0 => Ok((kind_char, w)),
        _ => Err(format!("dtype `{descr}` has no size")),
    }
}

/// Parses one `.npy` file's bytes; `path` names it in errors.
pub fn parse_npy(bytes: &[u8], path: &str) -> Result<Array> {
    let h = parse_header(bytes, path)?;
    if h.fortran && h.shape.iter().filter(|&&d| d > 1).count() > 1 {
        return Err(bad(
            path,
            "Fortran-order arrays are not read; save it in C order",
        ));
    }
    let values = decode(h.descr, &bytes[h.data_start..], h.n).map_err(|e| bad(path, e))?;
    Ok(Array {
        shape: h.shape,
        values,
    })
}

/// The header of a `.npy` file from its first bytes.
fn parse_header<'a>(bytes: &'a [u8], path: &str) -> Result<Header<'a>> {
    let rest = bytes
        .strip_prefix(b"\x93NUMPY")
        .ok_or_else(|| bad(path, "not a .npy file (no \\x93NUMPY magic)"))?;
    let (major, rest) = rest
        .split_first()
        .and_then(|(m, r)| Some((*m, r.split_first()?.1)))
        .ok_or_else(|| bad(path, "truncated header"))?;
    let (len, rest) = match major {
        1 if rest.len() >= 2 => (u16::from_le_bytes([rest[0], rest[1]]) as usize, &rest[2..]),
        2 | 3 if rest.len() >= 4 => (
            u32::from_le_bytes([rest[0], rest[1], rest[2], rest[3]]) as usize,
            &rest[4..],
        ),
        _ => {
            return Err(bad(
                path,
                format!("unknown .npy version {major} or truncated header"),
            ));
        }
    };
    let header = rest
        .get(..len)
        .and_then(|h| std::str::from_utf8(h).ok())
        .ok_or_else(|| bad(path, "truncated or non-text header"))?;
    let data_start = bytes.len() - rest.len() + len;
    let descr = header_field(header, "descr")
        .map(|d| d.trim_matches(|c| c == '\'' || c == '"'))
        .ok_or_else(|| bad(path, format!("no 'descr' in header {header}")))?;
    let fortran = header_field(header, "fortran_order") == Some("True");
    let shape: Vec<usize> = header_field(header, "shape")
        .ok_or_else(|| bad(path, format!("no 'shape' in header {header}")))?
        .trim_matches(|c| c == '(' || c == ')')
        .split(',')
        .map(str::trim)
        .filter(|s| !s.is_empty())
        .map(|s| {
            s.parse()
                .map_err(|_| bad(path, format!("bad shape entry `{s}`")))
        })
        .collect::<Result<_>>()?;
    let n = shape
        .iter()
        .try_fold(1usize, |a, &d| a.checked_mul(d))
        .ok_or_else(|| {
            bad(
                path,
                format!("shape {shape:?} has more elements than fit in memory"),
            )
        })?;
    Ok(Header {
        data_start,
        descr,
        fortran,
        shape,
        n,
    })
}

/// `n` elements of dtype `descr` from `data`.
fn decode(descr: &str, data: &[u8], n: usize) -> std::result::Result<Values, String> {
    let (kind_char, width) = dtype(descr)?;
    let need = n
        .checked_mul(width)
        .ok_or_else(|| format!("{n} × {descr} is more bytes than fit in memory"))?;
    let data = data
        .get(..need)
        .ok_or_else(|| format!("{} data bytes, {need} needed for {n} × {descr}", data.len()))?;
    if kind_char == 'U' {
        let text = data
            .chunks(width)
            .map(|c| {
                c.chunks(4)
                    .map(|b| u32::from_le_bytes([b[0], b[1], b[2], b[3]]))
                    .take_while(|&u| u != 0)
                    .map(|u| char::from_u32(u).unwrap_or('\u{fffd}'))
                    .collect()
            })
            .collect();
        return Ok(Values::Text(text));
    }
    let num = |c: &[u8]| -> f64 {
        match (kind_char, width) {
            ('f', 4) => f32::from_le_bytes(c.try_into().unwrap()) as f64,
            ('f', 8) => f64::from_le_bytes(c.try_into().unwrap()),
            ('i', 1) => c[0] as i8 as f64,
            ('i', 2) => i16::from_le_bytes(c.try_into().unwrap()) as f64,
            ('i', 4) => i32::from_le_bytes(c.try_into().unwrap()) as f64,
            ('i', 8) => i64::from_le_bytes(c.try_into().unwrap()) as f64,
            ('u' | 'b', 1) => c[0] as f64,
            ('u', 2) => u16::from_le_bytes(c.try_into().unwrap()) as f64,
            ('u', 4) => u32::from_le_bytes(c.try_into().unwrap()) as f64,
            ('u', 8) => u64::from_le_bytes(c.try_into().unwrap()) as f64,
            _ => f64::NAN,
        }
    };
    if !matches!(
        (kind_char, width),
        ('f', 4 | 8) | ('i', 1 | 2 | 4 | 8) | ('u', 1 | 2 | 4 | 8) | ('b', 1)
    ) {
        return Err(format!("dtype {descr} is not read"));
    }
    Ok(Values::Numbers(data.chunks(width).map(num).collect()))
}

/// The most memory the wanted arrays of an `.npz` archive may take, all together: what
/// their entries decompress to plus what they decode to (8 bytes a number, a `String` a
/// text). Far above any metadata file of the releases (tens of MB), and well below what
/// would exhaust a small machine.
pub const MAX_NPZ_BYTES: u64 = 768 << 20;

/// Bytes of an entry read before its header is known (`.npy` headers are padded to a
/// multiple of 64 bytes and are short; 64 KiB covers any real one).
const HEADER_PREFIX: u64 = 64 << 10;

/// The arrays named in `wanted` (without `.npy`) of an `.npz` archive; the other entries
/// are never decompressed. Each wanted entry is decompressed only as far as its own
/// header announces (more is an error), and all of them together may take at most
/// [`MAX_NPZ_BYTES`] of memory: a zip bomb ends in an error, not in memory exhaustion.
pub fn read_npz<R: Read + Seek>(
    archive: R,
    path: &str,
    wanted: &[&str],
) -> Result<BTreeMap<String, Array>> {
    read_npz_within(archive, path, wanted, MAX_NPZ_BYTES)
}

fn read_npz_within<R: Read + Seek>(
    archive: R,
    path: &str,
    wanted: &[&str],
    budget: u64,
) -> Result<BTreeMap<String, Array>> {
    let mut left = budget;
    let mut zip = zip::ZipArchive::new(archive)
        .map_err(|e| bad(path, format!("not a readable .npz (zip) archive: {e}")))?;
    let mut out = BTreeMap::new();
    for i in 0..zip.len() {
        let mut f = zip
            .by_index(i)
            .map_err(|e| bad(path, format!("archive entry {i}: {e}")))?;
        let name = f
            .name()
            .map_err(|e| bad(path, format!("archive entry {i}: {e}")))?
            .to_string();
        let Some(key) = name.strip_suffix(".npy").filter(|k| wanted.contains(k)) else {
            continue;
        };
        let entry = format!("{path}:{name}");
        let too_big = || {
            bad(
                &entry,
                format!("takes more than {budget} bytes of memory (the wanted entries together)"),
            )
        };
        // The header first, then exactly the bytes it announces and one more, to tell a
        // longer entry.
        let mut data = Vec::new();
        (&mut f)
            .take(HEADER_PREFIX.min(left))
            .read_to_end(&mut data)
            .map_err(|e| bad(&entry, e.to_string()))?;
        let header = parse_header(&data, &entry)?;
        dtype(header.descr).map_err(|e| bad(&entry, e))?;
        let (want, cost) = match (header.file_len(), header.decoded_len()) {
            (Some(w), Some(d)) => (w as u64, (w as u64).saturating_add(d as u64)),
            _ => return Err(too_big()),
        };
        if cost > left {
            return Err(too_big());
        }
        if (data.len() as u64) < want {
            data.try_reserve_exact((want - data.len() as u64) as usize)
                .map_err(|_| too_big())?;
            (&mut f)
                .take(want - data.len() as u64 + 1)
                .read_to_end(&mut data)
                .map_err(|e| bad(&entry, e.to_string()))?;
        }
        if data.len() as u64 > want {
            return Err(bad(
                &entry,
                format!("holds more than the {want} bytes its header announces"),
            ));
        }
        // The entry's bytes are dropped once decoded, but they were held beside it.
        left -= cost;
        out.insert(key.to_string(), parse_npy(&data, &entry)?);
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::io::Cursor;

    fn npy(descr: &str, shape: &str, data: &[u8], version: u8) -> Vec<u8> {
        let header =
            format!("{{'descr': '{descr}', 'fortran_order': False, 'shape': {shape}, }}\n");
        let mut out = b"\x93NUMPY".to_vec();
        out.extend([version, 0]);
        match version {
            1 => out.extend((header.len() as u16).to_le_bytes()),
            _ => out.extend((header.len() as u32).to_le_bytes()),
        }
        out.extend(header.as_bytes());
        out.extend(data);
        out
    }

    #[test]
    fn numbers_text_and_shapes_are_read() {
        let f: Vec<u8> = [1.5f64, -2.0, 3.25]
            .iter()
            .flat_map(|x| x.to_le_bytes())
            .collect();
        let a = parse_npy(&npy("<f8", "(3,)", &f, 1), "a.npy").unwrap();
        assert_eq!(a.shape, vec![3]);
        assert_eq!(a.values, Values::Numbers(vec![1.5, -2.0, 3.25]));
        let i: Vec<u8> = [7i64, -1, 0, 4]
            .iter()
            .flat_map(|x| x.to_le_bytes())
            .collect();
        let b = parse_npy(&npy("<i8", "(2, 2)", &i, 2), "b.npy").unwrap();
        assert_eq!(b.shape, vec![2, 2]);
        assert_eq!(b.number_row(1), Some(&[0.0, 4.0][..]));
        assert_eq!(b.text_at(0, 1).as_deref(), Some("-1"));
        let mut u = Vec::new();
        for s in ["red", "blue"] {
            let mut cps: Vec<u32> = s.chars().map(u32::from).collect();
            cps.resize(4, 0);
            u.extend(cps.iter().flat_map(|c| c.to_le_bytes()));
        }
        let t = parse_npy(&npy("<U4", "(2,)", &u, 1), "t.npy").unwrap();
        assert_eq!(t.text_at(1, 0).as_deref(), Some("blue"));
        let s = parse_npy(&npy("|u1", "()", &[9], 1), "s.npy").unwrap();
        assert_eq!((s.shape.len(), s.values), (0, Values::Numbers(vec![9.0])));
    }

    #[test]
    fn bad_files_name_the_problem() {
        let cases: [(&[u8], &str); 5] = [
            (b"PK\x03\x04", "magic"),
            (&npy("<f8", "(3,)", &[0; 8], 1), "data bytes"),
            (&npy(">f8", "(1,)", &[0; 8], 1), "big-endian"),
            (&npy("<c16", "(1,)", &[0; 16], 1), "not read"),
            (&npy("<f8", "(x,)", &[0; 8], 1), "bad shape"),
        ];
        for (bytes, want) in cases {
            let e = parse_npy(bytes, "m.npy").unwrap_err().to_string();
            assert!(e.contains("m.npy") && e.contains(want), "{want}: {e}");
        }
        assert!(
            read_npz(Cursor::new(b"not a zip"), "meta.npz", &["a"])
                .unwrap_err()
                .to_string()
                .contains("meta.npz")
        );
    }

    /// Headers a hostile or broken writer can produce end in errors naming the file,
    /// never in a panic or an overflowed size.
    #[test]
    fn hostile_headers_are_errors() {
        let cases: [(Vec<u8>, &str); 8] = [
            (npy("<", "(1,)", &[0; 8], 1), "dtype"),
            (npy("", "(1,)", &[0; 8], 1), "dtype"),
            (npy("é8", "(1,)", &[0; 8], 1), "dtype"),
            (npy("<U0", "(2,)", &[], 1), "no size"),
            (npy("<f0", "(2,)", &[], 1), "no size"),
            (
                npy("<f8", "(4294967296, 4294967296, 16)", &[0; 8], 1),
                "fit in memory",
            ),
            (
                npy("<f8", "(2305843009213693952,)", &[0; 8], 1),
                "fit in memory",
            ),
            (npy("<f8", "(2, 3)", &[0; 40], 1), "data bytes"),
        ];
        for (bytes, want) in cases {
            let e = parse_npy(&bytes, "h.npy").unwrap_err().to_string();
            assert!(e.contains("h.npy") && e.contains(want), "{want}: {e}");
        }
    }

    fn npz(entries: &[(&str, Vec<u8>)]) -> Vec<u8> {
        let mut zip = zip::ZipWriter::new(std::io::Cursor::new(Vec::new()));
        let opts = zip::write::SimpleFileOptions::default()
            .compression_method(zip::CompressionMethod::Deflated);
        for (name, data) in entries {
            zip.start_file(*name, opts).unwrap();
            std::io::Write::write_all(&mut zip, data).unwrap();
        }
        zip.finish().unwrap().into_inner()
    }

    /// A zip bomb (an entry that inflates past the budget) and an entry longer than its
    /// header are refused without inflating them whole; entries nobody asked for are not
    /// read at all.
    #[test]
    fn archives_decompress_only_what_their_headers_announce() {
        let zeros = vec![0u8; 8 << 20];
        let small = npy("<f8", "(2,)", &[0; 16], 1);
        let big = npy("<f8", "(1048576,)", &zeros, 1);
        let ok = npz(&[("a.npy", small), ("b.npy", big)]);
        let both = read_npz(Cursor::new(&ok), "m.npz", &["a", "b"]).unwrap();
        assert_eq!(both.len(), 2);
        // 8 MiB of zeros compress to a few KiB: over a 1 MiB budget it is refused...
        let e = read_npz_within(Cursor::new(&ok), "m.npz", &["a", "b"], 1 << 20)
            .unwrap_err()
            .to_string();
        assert!(e.contains("m.npz:b.npy") && e.contains("more than"), "{e}");
        // ...unless nobody asks for it.
        let a = read_npz_within(Cursor::new(&ok), "m.npz", &["a"], 1 << 20).unwrap();
        assert_eq!(a.keys().collect::<Vec<_>>(), ["a"]);
        // Decoding counts: 1 Mi one-byte values take 8 MiB as numbers.
        let bytes = npz(&[("u.npy", npy("|u1", "(1048576,)", &zeros[..1 << 20], 1))]);
        let e = read_npz_within(Cursor::new(&bytes), "m.npz", &["u"], 4 << 20)
            .unwrap_err()
            .to_string();
        assert!(e.contains("more than"), "{e}");
        // A header announcing two values before 8 MiB of data.
        let mut long = npy("<f8", "(2,)", &[0; 16], 1);
        long.extend(&zeros);
        let e = read_npz(Cursor::new(npz(&[("c.npy", long)])), "m.npz", &["c"])
            .unwrap_err()
            .to_string();
        assert!(e.contains("m.npz:c.npy") && e.contains("announces"), "{e}");
    }
}
