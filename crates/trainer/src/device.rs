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
        return Err(TrainError::Device(format!(
            "cuda:{ordinal} asked for, this machine has {n} CUDA device(s)"
        )));
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
    let opening =
        |e: &dyn std::fmt::Display| TrainError::Device(format!("opening cuda:{ordinal}: {e}"));
    // One stream of its own for the whole process: candle's default is CUDA's per-thread
    // stream, a different stream on each host thread, so work queued from two tokio
    // threads (a step's backward pass and the optimiser, the staging's copies) would not
    // be ordered. With one stream, the stream order alone orders every use of a buffer.
    let device = Device::new_cuda_with_stream(ordinal).map_err(|e| opening(&e))?;
    pool::configure(&device).map_err(|e| opening(&e))?;
    Ok(device)
}

/// The device's stream-ordered memory pool, which candle's allocations come from
/// (cudarc allocates with `cuMemAllocAsync` from the device's default pool).
// Memory-pool attributes are read and set through cudarc's raw driver calls.
#[cfg(feature = "cuda")]
#[allow(unsafe_code)]
mod pool {
    use candle_core::Device;
    use candle_core::cuda_backend::cudarc::driver::{DriverError, result, sys};

    /// GPU `ordinal`'s total memory in bytes, as the driver reports it.
    pub fn total_bytes(ordinal: usize) -> Option<usize> {
        result::init().ok()?;
        let dev = result::device::get(i32::try_from(ordinal).ok()?).ok()?;
        // SAFETY: `dev` is a handle the driver just returned; the call writes a size.
        unsafe { result::device::total_mem(dev) }.ok()
    }

    fn default_pool(device: &Device) -> Option<sys::CUmemoryPool> {
        let Device::Cuda(d) = device else { return None };
        let ctx = d.cuda_stream().context().clone();
        // Binding first reports an error an earlier asynchronous call left behind: say
        // what it was, or it is lost with the pool's figures.
        if let Err(e) = ctx.bind_to_thread() {
            tracing::error!(error = %e, "the CUDA context reports an earlier error");
            return None;
        }
        // SAFETY: the device handle comes from a live context.
        unsafe { result::device::get_default_mem_pool(ctx.cu_device()) }.ok()
    }

    /// Keeps freed memory in the pool instead of handing it back to the driver: the
    /// default release threshold (0) returns every free block at each synchronisation,
    /// so every step allocates its activations from the driver again. And turns off
    /// cudarc's per-allocation event pair: osrt runs one stream per device (`open_cuda`), where the
    /// stream order alone keeps uses and frees in order (the events serve several streams).
    pub fn configure(device: &Device) -> Result<(), DriverError> {
        let Device::Cuda(d) = device else {
            return Ok(());
        };
        // SAFETY: osrt queues everything on the device's one stream (`open_cuda`), so no
        // buffer crosses streams.
        unsafe { d.disable_event_tracking() };
        let Some(pool) = default_pool(device) else {
            return Ok(());
        };
        let mut keep_all = u64::MAX;
        // SAFETY: RELEASE_THRESHOLD takes a u64 (cuuint64_t).
        unsafe {
            result::mem_pool::set_attribute(
                pool,
                sys::CUmemPool_attribute::CU_MEMPOOL_ATTR_RELEASE_THRESHOLD,
                (&mut keep_all as *mut u64).cast(),
            )
        }
    }

    /// Hands every free block of the pool back to the driver.
    pub fn trim(device: &Device) -> bool {
        let Some(pool) = default_pool(device) else {
            return false;
        };
        // SAFETY: a valid pool; keeping 0 bytes only releases memory no allocation holds.
        unsafe { result::mem_pool::trim_to(pool, 0) }.is_ok()
    }

    /// The most bytes the pool had handed out at once since the last [`reset_peak`]
    /// (`USED_MEM_HIGH`: the counterpart of `torch.cuda.max_memory_allocated`).
    pub fn peak_bytes(device: &Device) -> Option<u64> {
        read(
            device,
            sys::CUmemPool_attribute::CU_MEMPOOL_ATTR_USED_MEM_HIGH,
        )
    }

    /// The bytes the pool has handed out now (`USED_MEM_CURRENT`: the counterpart of
    /// `torch.cuda.memory_allocated`).
    pub fn used_bytes(device: &Device) -> Option<u64> {
        read(
            device,
            sys::CUmemPool_attribute::CU_MEMPOOL_ATTR_USED_MEM_CURRENT,
        )
    }

    fn read(device: &Device, attribute: sys::CUmemPool_attribute) -> Option<u64> {
        let pool = default_pool(device)?;
        let mut v = 0u64;
        // SAFETY: both attributes read here (USED_MEM_HIGH, USED_MEM_CURRENT) are u64s
        // (cuuint64_t).
        unsafe { result::mem_pool::get_attribute(pool, attribute, (&mut v as *mut u64).cast()) }
            .ok()?;
        Some(v)
    }

    /// Starts a new peak from the bytes in use now (the driver only accepts 0, which
    /// resets the high-water mark to the current use).
    pub fn reset_peak(device: &Device) -> bool {
        let Some(pool) = default_pool(device) else {
            return false;
        };
        let mut zero = 0u64;
        // SAFETY: USED_MEM_HIGH is set with a u64 (cuuint64_t).
        unsafe {
            result::mem_pool::set_attribute(
                pool,
                sys::CUmemPool_attribute::CU_MEMPOOL_ATTR_USED_MEM_HIGH,
                (&mut zero as *mut u64).cast(),
            )
        }
        .is_ok()
    }
}

/// The most device memory the step's tensors held at once since the last
/// [`reset_device_peak`], in bytes; `None` on the CPU or where the driver does not say.
pub fn device_peak_bytes(device: &Device) -> Option<u64> {
    #[cfg(feature = "cuda")]
    {
        device.synchronize().ok()?;
        pool::peak_bytes(device)
    }
    #[cfg(not(feature = "cuda"))]
    {
        let _ = device;
        None
    }
}

/// The memory a device's tensors hold, for the per-op profile: the counted heap on the
/// CPU (where the binary installs [`crate::memory::CountingAlloc`]), the memory pool on
/// a GPU.
pub struct Meter(pub Device);

impl osrt_kernels::profile::MemoryMeter for Meter {
    fn live(&self) -> Option<u64> {
        if self.0.is_cpu() {
            return crate::memory::live_heap_bytes().map(|b| b as u64);
        }
        #[cfg(feature = "cuda")]
        {
            self.0.synchronize().ok()?;
            pool::used_bytes(&self.0)
        }
        #[cfg(not(feature = "cuda"))]
        None
    }

    fn reset_peak(&self) {
        if self.0.is_cpu() {
            crate::memory::reset_peak_heap();
        } else {
            reset_device_peak(&self.0);
        }
    }

    fn peak(&self) -> Option<u64> {
        if self.0.is_cpu() {
            crate::memory::peak_heap_bytes().map(|b| b as u64)
        } else {
            device_peak_bytes(&self.0)
        }
    }
}

/// Whether `e` is the device running out of memory: the driver's allocation failing, or
/// cuBLAS failing to allocate its workspace (outside the memory pool).
pub fn is_out_of_memory(e: &candle_core::Error) -> bool {
    let text = e.to_string();
    text.contains("CUDA_ERROR_OUT_OF_MEMORY") || text.contains("CUBLAS_STATUS_ALLOC_FAILED")
}

/// Hands the memory pool's free blocks back to the driver (after an allocation failed:
/// the pool keeps what it frees, and its free blocks may be too fragmented for one big
/// request that fresh memory from the driver would satisfy); false on the CPU.
pub fn release_cached(device: &Device) -> bool {
    #[cfg(feature = "cuda")]
    {
        device.synchronize().is_ok() && pool::trim(device)
    }
    #[cfg(not(feature = "cuda"))]
    {
        let _ = device;
        false
    }
}

/// Starts a new device-memory peak from what is in use now; false on the CPU.
pub fn reset_device_peak(device: &Device) -> bool {
    #[cfg(feature = "cuda")]
    {
        device.synchronize().is_ok() && pool::reset_peak(device)
    }
    #[cfg(not(feature = "cuda"))]
    {
        let _ = device;
        false
    }
}

#[cfg(not(feature = "cuda"))]
fn open_cuda(ordinal: usize) -> Result<Device> {
    Err(TrainError::Device(format!(
        "cuda:{ordinal} asked for, but this osrt was built without the `cuda` feature \
         (build it with scripts/build-cuda.sh)"
    )))
}

/// GPU `ordinal`'s total memory in bytes; `None` without the `cuda` feature, a driver or
/// that device.
pub fn gpu_memory(ordinal: usize) -> Option<f64> {
    #[cfg(feature = "cuda")]
    {
        pool::total_bytes(ordinal).map(|b| b as f64)
    }
    #[cfg(not(feature = "cuda"))]
    {
        let _ = ordinal;
        None
    }
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

    #[cfg(not(feature = "cuda"))]
    #[test]
    fn opening_a_gpu_without_the_feature_is_a_device_error() {
        let e = DeviceSpec::Cuda(0).open().unwrap_err();
        assert!(matches!(e, crate::TrainError::Device(_)), "{e}");
    }

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
