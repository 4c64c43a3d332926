//! Files written by `torch.save` (PyTorch ≥ 1.6): a zip archive holding `NAME/data.pkl`,
//! the pickled object, and `NAME/data/K`, one raw little-endian storage per tensor.
//!
//! The pickle is interpreted by candle's reader (`candle_core::pickle`), which only builds
//! values from the opcodes: it never imports or calls anything the pickle names, so a
//! file cannot run code here. Its object tree becomes a [`Value`]; tensors stay
//! references into the archive ([`TensorRef`]) until [`TorchFile::tensor`] reads one.

use crate::error::{InteropError, Result};
use candle_core::pickle::{Object, Stack};
use candle_core::{DType, Device, Tensor};
use std::fs::File;
use std::io::{BufReader, Read};
use std::path::{Path, PathBuf};

/// A dict key: the names of a state dict, the indices of an optimiser's state.
#[derive(Debug, Clone, PartialEq, Eq, PartialOrd, Ord)]
pub enum Key {
    Str(String),
    Int(i64),
}

impl std::fmt::Display for Key {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Key::Str(s) => write!(f, "'{s}'"),
            Key::Int(i) => write!(f, "{i}"),
        }
    }
}

/// A pickled value as far as checkpoints need it.
#[derive(Debug, Clone, PartialEq)]
pub enum Value {
    /// A dict (also `OrderedDict`). The order of the entries is not the file's: candle's
    /// reader reverses each batch of items, so nothing here may depend on it.
    Dict(Vec<(Key, Value)>),
    /// A list or a tuple.
    List(Vec<Value>),
    Int(i64),
    Float(f64),
    Str(String),
    Bool(bool),
    None,
    Tensor(TensorRef),
    /// Anything else (an object of some class), described for error messages.
    Other(String),
}

impl Value {
    /// What the value is, for error messages.
    pub fn kind(&self) -> String {
        match self {
            Value::Dict(d) => format!("a dict of {} entries", d.len()),
            Value::List(l) => format!("a list of {} items", l.len()),
            Value::Int(i) => format!("the integer {i}"),
            Value::Float(x) => format!("the number {x}"),
            Value::Str(s) => format!("the string '{s}'"),
            Value::Bool(b) => format!("the boolean {b}"),
            Value::None => "None".into(),
            Value::Tensor(t) => format!("a {:?} tensor {:?}", t.dtype, t.shape),
            Value::Other(what) => what.clone(),
        }
    }

    /// The entry `key` of a dict.
    pub fn get(&self, key: &str) -> Option<&Value> {
        match self {
            Value::Dict(d) => d
                .iter()
                .find(|(k, _)| matches!(k, Key::Str(s) if s == key))
                .map(|(_, v)| v),
            _ => None,
        }
    }

    pub fn as_f64(&self) -> Option<f64> {
        match self {
            Value::Int(i) => Some(*i as f64),
            Value::Float(x) => Some(*x),
            _ => None,
        }
    }
}

/// Where a tensor's values are: its storage's entry in the archive, element offset,
/// shape and strides (in elements).
#[derive(Debug, Clone, PartialEq)]
pub struct TensorRef {
    pub dtype: DType,
    pub shape: Vec<usize>,
    pub stride: Vec<usize>,
    pub offset: usize,
    /// Archive entry of the storage (`NAME/data/K`).
    pub storage: String,
    /// Elements in the storage.
    pub storage_len: usize,
}

/// An open `torch.save` file.
pub struct TorchFile {
    path: PathBuf,
    zip: zip::ZipArchive<BufReader<File>>,
    root: Value,
}

impl std::fmt::Debug for TorchFile {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("TorchFile")
            .field("path", &self.path)
            .finish()
    }
}

/// The most bytes of one storage read into memory (a 2 GB tensor is far beyond any
/// checkpoint of this model; a header announcing more is a broken file).
const MAX_STORAGE_BYTES: u64 = 2 << 30;

impl TorchFile {
    /// Opens `path` and reads its pickle (not the tensors).
    pub fn open(path: &Path) -> Result<Self> {
        let shown = path.display().to_string();
        let bad = |reason: String| InteropError::File {
            path: shown.clone(),
            reason,
        };
        let file = File::open(path).map_err(|e| bad(format!("cannot open: {e}")))?;
        let mut zip = zip::ZipArchive::new(BufReader::new(file)).map_err(|e| {
            bad(format!(
                "not a PyTorch checkpoint: not a zip archive ({e}); the file is truncated, \
                 or was written by torch.save before PyTorch 1.6 or by something else"
            ))
        })?;
        let pkl = (0..zip.len())
            .filter_map(|i| zip.name_for_index(i)?.ok().map(|n| n.into_owned()))
            .find(|n| n.ends_with("/data.pkl") || n == "data.pkl")
            .ok_or_else(|| bad("not a PyTorch checkpoint: the archive holds no data.pkl".into()))?;
        // Storages are `NAME/data/K`: the pickle's name without `.pkl`, then the key.
        let dir = pkl
            .strip_suffix(".pkl")
            .expect("found by this suffix")
            .to_string();
        let mut stack = Stack::empty();
        {
            let entry = zip.by_name(&pkl).map_err(|e| bad(format!("{pkl}: {e}")))?;
            let mut reader = BufReader::new(entry);
            stack.read_loop(&mut reader).map_err(|e| {
                bad(format!(
                    "{pkl}: not a pickle this reader understands (it reads plain data and \
                     tensors, never code): {e}"
                ))
            })?;
        }
        let object = stack
            .finalize()
            .map_err(|e| bad(format!("{pkl}: empty pickle: {e}")))?;
        let root = to_value(object, &dir);
        Ok(Self {
            path: path.to_path_buf(),
            zip,
            root,
        })
    }

    pub fn path(&self) -> &Path {
        &self.path
    }

    /// The pickled object.
    pub fn root(&self) -> &Value {
        &self.root
    }

    /// A tensor's values in C order, as f32 (f64, f16, bf16 and integer storages are
    /// converted). `name` is for error messages.
    pub fn tensor(&mut self, t: &TensorRef, name: &str) -> Result<Vec<f32>> {
        let bad = |reason: String| InteropError::Tensor {
            path: self.path.display().to_string(),
            name: name.to_string(),
            reason,
        };
        let elem = t.dtype.size_in_bytes();
        let want = (t.storage_len * elem) as u64;
        if want > MAX_STORAGE_BYTES {
            return Err(bad(format!("its storage claims {want} bytes")));
        }
        // Every element the view reaches must lie inside the storage.
        let last = t.offset
            + t.shape
                .iter()
                .zip(&t.stride)
                .map(|(&n, &s)| n.saturating_sub(1) * s)
                .sum::<usize>();
        if t.shape.iter().product::<usize>() > 0 && last >= t.storage_len {
            return Err(bad(format!(
                "shape {:?} with strides {:?} at offset {} reaches past its storage of {} elements",
                t.shape, t.stride, t.offset, t.storage_len
            )));
        }
        let mut entry = self
            .zip
            .by_name(&t.storage)
            .map_err(|e| bad(format!("storage {}: {e}", t.storage)))?;
        let mut bytes = Vec::with_capacity(want as usize);
        (&mut entry)
            .take(want)
            .read_to_end(&mut bytes)
            .map_err(|e| bad(format!("storage {}: {e} (truncated file?)", t.storage)))?;
        if (bytes.len() as u64) < want {
            return Err(bad(format!(
                "storage {} holds {} bytes, {want} expected (truncated file?)",
                t.storage,
                bytes.len()
            )));
        }
        let storage = Tensor::from_raw_buffer(&bytes, t.dtype, &[t.storage_len], &Device::Cpu)
            .and_then(|s| s.to_dtype(DType::F32))
            .and_then(|s| s.to_vec1::<f32>())
            .map_err(|e| bad(e.to_string()))?;
        Ok(gather(&storage, t))
    }
}

/// The view's elements in C order.
fn gather(storage: &[f32], t: &TensorRef) -> Vec<f32> {
    let n: usize = t.shape.iter().product();
    let mut out = Vec::with_capacity(n);
    let mut index = vec![0usize; t.shape.len()];
    for _ in 0..n {
        let at = t.offset
            + index
                .iter()
                .zip(&t.stride)
                .map(|(i, s)| i * s)
                .sum::<usize>();
        out.push(storage[at]);
        for d in (0..index.len()).rev() {
            index[d] += 1;
            if index[d] < t.shape[d] {
                break;
            }
            index[d] = 0;
        }
    }
    out
}

fn to_key(o: Object) -> Key {
    match o {
        Object::Unicode(s) => Key::Str(s),
        Object::Int(i) => Key::Int(i as i64),
        Object::Long(i) => Key::Int(i),
        other => Key::Str(format!("{other:?}")),
    }
}

fn to_value(o: Object, dir: &str) -> Value {
    match o {
        Object::Dict(d) => Value::Dict(
            d.into_iter()
                .map(|(k, v)| (to_key(k), to_value(v, dir)))
                .collect(),
        ),
        Object::List(l) | Object::Tuple(l) => {
            Value::List(l.into_iter().map(|v| to_value(v, dir)).collect())
        }
        Object::Int(i) => Value::Int(i as i64),
        Object::Long(i) => Value::Int(i),
        Object::Float(x) => Value::Float(x),
        Object::Unicode(s) => Value::Str(s),
        Object::Bool(b) => Value::Bool(b),
        Object::None => Value::None,
        o @ Object::Reduce { .. } => tensor_or_other(o, dir),
        Object::Build { callable, .. } => {
            Value::Other(format!("an object built from {}", describe(&callable)))
        }
        other => Value::Other(describe(&other)),
    }
}

fn describe(o: &Object) -> String {
    match o {
        Object::Class {
            module_name,
            class_name,
        } => format!("{module_name}.{class_name}"),
        Object::Reduce { callable, .. } => format!("an object of {}", describe(callable)),
        other => format!("{other:?}").chars().take(80).collect(),
    }
}

fn tensor_or_other(o: Object, dir: &str) -> Value {
    let what = describe(&o);
    // candle's tensor recogniser; the name argument is only echoed back.
    match o.into_tensor_info(Object::Unicode(String::new()), Path::new(dir)) {
        Ok(Some(info)) => {
            let elem = info.dtype.size_in_bytes();
            Value::Tensor(TensorRef {
                dtype: info.dtype,
                shape: info.layout.dims().to_vec(),
                stride: info.layout.stride().to_vec(),
                offset: info.layout.start_offset() / elem,
                storage: info.path,
                storage_len: info.storage_size,
            })
        }
        _ => Value::Other(what),
    }
}
