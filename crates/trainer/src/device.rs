//! Where a worker computes: `cpu`, `cuda` (the first GPU) or `cuda:N`.
//!
//! On the CPU the model runs the fused kernels and AdamW runs on the host. On a GPU
//! (candle's CUDA backend, the `cuda` cargo feature) the weights, the optimiser moments,
//! the batch and the whole step live on the device and the model runs candle's own ops;
//! only the flat gradient crosses to the host, for the all-reduce, and back.

use crate::error::{Result, TrainError};
use candle_core::Device;
use serde::{Deserialize, Serialize};

/// A device by name, as the job config and `--device` spell it.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(try_from = "String", into = "String")]
pub enum DeviceSpec {
    #[default]
    Cpu,
    /// A CUDA GPU by ordinal; `cuda` alone is ordinal 0.
    Cuda(usize),
}

impl DeviceSpec {
    pub fn is_cuda(&self) -> bool {
        matches!(self, Self::Cuda(_))
    }

    /// Opens the device, once per process (every later call returns the same context,
    /// so a worker's generations share one GPU context and its memory pool). Without the
    /// `cuda` feature a GPU is refused with how to get one.
    pub fn open(&self) -> Result<Device> {
        static OPEN: std::sync::Mutex<Vec<(DeviceSpec, Device)>> =
            std::sync::Mutex::new(Vec::new());
        let ordinal = match *self {
            Self::Cpu => return Ok(Device::Cpu),
            Self::Cuda(ordinal) => ordinal,
        };
        let mut open = OPEN.lock().unwrap_or_else(|e| e.into_inner());
        if let Some((_, d)) = open.iter().find(|(s, _)| s == self) {
            return Ok(d.clone());
        }
        let d = open_cuda(ordinal)?;
        open.push((*self, d.clone()));
        Ok(d)
    }

    /// The spec of an open device.
    pub fn from_device(device: &Device) -> Self {
        match device.location() {
            candle_core::DeviceLocation::Cuda { gpu_id } => Self::Cuda(gpu_id),
            _ => Self::Cpu,
        }
    }

    /// The device worker `index` of a local cluster uses: on a machine with `gpus` GPUs,
    /// worker k takes GPU `k mod gpus` (a GPU per worker when there are enough).
    pub fn for_local_worker(&self, index: usize, gpus: usize) -> Self {
        match *self {
            Self::Cpu => Self::Cpu,
            Self::Cuda(first) => Self::Cuda((first + index) % gpus.max(1)),
        }
    }
}

impl DeviceSpec {
    /// Whether this process could open the device, without opening it (a launcher checks
    /// before it starts workers, so that a missing GPU is one clear error).
    pub fn check_available(&self) -> Result<()> {
        match *self {
            Self::Cpu => Ok(()),
            Self::Cuda(ordinal) => cuda_available(ordinal),
        }
    }
}

#[cfg(feature = "cuda")]
fn cuda_available(ordinal: usize) -> Result<()> {
    let n = cuda_device_count();
    if ordinal >= n {
        return Err(TrainError::Config {
            path: "device".into(),
            reason: format!("cuda:{ordinal} asked for, this machine has {n} CUDA device(s)"),
        });
    }
    Ok(())
}

#[cfg(not(feature = "cuda"))]
fn cuda_available(ordinal: usize) -> Result<()> {
    open_cuda(ordinal).map(|_| ())
}

#[cfg(feature = "cuda")]
fn open_cuda(ordinal: usize) -> Result<Device> {
    cuda_available(ordinal)?;
    Device::new_cuda(ordinal).map_err(|e| TrainError::Config {
        path: "device".into(),
        reason: format!("opening cuda:{ordinal}: {e}"),
    })
}

#[cfg(not(feature = "cuda"))]
fn open_cuda(ordinal: usize) -> Result<Device> {
    Err(TrainError::Config {
        path: "device".into(),
        reason: format!(
            "cuda:{ordinal} asked for, but this osrt was built without the `cuda` feature \
             (build it with scripts/build-cuda.sh)"
        ),
    })
}

/// CUDA devices the driver reports (0 without the `cuda` feature or a driver).
pub fn cuda_device_count() -> usize {
    #[cfg(feature = "cuda")]
    {
        use candle_core::cuda_backend::cudarc::driver::result;
        if result::init().is_err() {
            return 0;
        }
        result::device::get_count().map_or(0, |n| n.max(0) as usize)
    }
    #[cfg(not(feature = "cuda"))]
    0
}

impl std::fmt::Display for DeviceSpec {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Self::Cpu => f.write_str("cpu"),
            Self::Cuda(n) => write!(f, "cuda:{n}"),
        }
    }
}

impl std::str::FromStr for DeviceSpec {
    type Err = String;
    fn from_str(s: &str) -> std::result::Result<Self, String> {
        match s {
            "cpu" => Ok(Self::Cpu),
            "cuda" | "gpu" => Ok(Self::Cuda(0)),
            _ => match s.strip_prefix("cuda:").map(str::parse::<usize>) {
                Some(Ok(n)) => Ok(Self::Cuda(n)),
                _ => Err(format!(
                    "unknown device `{s}`: expected cpu, cuda or cuda:N (N a GPU ordinal)"
                )),
            },
        }
    }
}

impl TryFrom<String> for DeviceSpec {
    type Error = String;
    fn try_from(s: String) -> std::result::Result<Self, String> {
        s.parse()
    }
}

impl From<DeviceSpec> for String {
    fn from(d: DeviceSpec) -> String {
        d.to_string()
    }
}

/// Whether `device` is the CPU (where the fused kernels and the host optimiser run).
pub fn is_cpu(device: &Device) -> bool {
    matches!(device, Device::Cpu)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn names_round_trip_and_bad_names_say_what_is_expected() {
        for (s, d) in [
            ("cpu", DeviceSpec::Cpu),
            ("cuda", DeviceSpec::Cuda(0)),
            ("cuda:3", DeviceSpec::Cuda(3)),
        ] {
            assert_eq!(s.parse::<DeviceSpec>().unwrap(), d);
            assert_eq!(d.to_string().parse::<DeviceSpec>().unwrap(), d);
        }
        for bad in ["", "cuda:", "cuda:-1", "metal", "cuda:x"] {
            let e = bad.parse::<DeviceSpec>().unwrap_err();
            assert!(e.contains("expected cpu, cuda or cuda:N"), "{e}");
        }
    }

    #[test]
    fn local_workers_take_one_gpu_each_and_share_when_there_are_fewer() {
        let d = DeviceSpec::Cuda(0);
        let on = |gpus| {
            (0..4)
                .map(|k| d.for_local_worker(k, gpus))
                .collect::<Vec<_>>()
        };
        use DeviceSpec::Cuda;
        assert_eq!(on(4), [Cuda(0), Cuda(1), Cuda(2), Cuda(3)]);
        assert_eq!(on(2), [Cuda(0), Cuda(1), Cuda(0), Cuda(1)]);
        assert_eq!(on(0), [Cuda(0); 4]);
        assert_eq!(DeviceSpec::Cpu.for_local_worker(3, 8), DeviceSpec::Cpu);
    }

    #[test]
    fn config_text_spells_the_device_by_name() {
        #[derive(Serialize, Deserialize)]
        struct T {
            device: DeviceSpec,
        }
        let t: T = toml::from_str("device = \"cuda:1\"").unwrap();
        assert_eq!(t.device, DeviceSpec::Cuda(1));
        assert_eq!(toml::to_string(&t).unwrap().trim(), "device = \"cuda:1\"");
        assert!(toml::from_str::<T>("device = \"tpu\"").is_err());
    }

    #[cfg(not(feature = "cuda"))]
    #[test]
    fn a_gpu_without_the_feature_is_refused_with_the_build_recipe() {
        let e = DeviceSpec::Cuda(0).open().unwrap_err().to_string();
        assert!(e.contains("scripts/build-cuda.sh"), "{e}");
        let e = DeviceSpec::Cuda(1)
            .check_available()
            .unwrap_err()
            .to_string();
        assert!(e.contains("cuda:1") && e.contains("`cuda` feature"), "{e}");
        assert_eq!(cuda_device_count(), 0);
    }
}
