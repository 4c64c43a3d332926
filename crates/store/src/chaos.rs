//! A store that misbehaves on request, around any other (compiled with the
//! `fault-injection` feature only): reads of chosen objects that fail as a timeout, a 5xx
//! or a refused permission would, slow puts, and create-only puts that succeed but answer
//! `AlreadyExists` (a retried request whose first try went through). Tests of what osrt
//! does when its store misbehaves wrap a real store with it.

use async_trait::async_trait;
use futures::stream::BoxStream;
use object_store::path::Path;
use object_store::{
    CopyOptions, GetOptions, GetResult, ListResult, MultipartUpload, ObjectMeta, ObjectStore,
    PutMode, PutMultipartOptions, PutOptions, PutPayload, PutResult,
};
use std::sync::{Arc, Mutex};
use std::time::Duration;

/// How a faulty read fails.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum ReadFault {
    /// As a timeout or a 5xx answer does: `Error::Generic`.
    Transient,
    /// As a refused permission does: `Error::PermissionDenied`.
    Denied,
}

/// What goes wrong, changed at any time through [`ChaosStore::faults`].
#[derive(Debug, Default, Clone)]
pub struct Faults {
    /// Reads (gets and heads) of objects whose path contains the pattern fail, the next
    /// `count` times (`usize::MAX`: until changed).
    pub reads: Vec<(String, ReadFault, usize)>,
    /// The next this many puts fail as a dropped connection does (`Error::Generic`).
    pub fail_puts: usize,
    /// Every put waits this long first (with `slow_puts` set: only puts of objects whose
    /// path contains it).
    pub put_delay: Duration,
    pub slow_puts: Option<String>,
    /// The next this many create-only puts are written and then answered with
    /// `AlreadyExists`.
    pub exists_after_create: usize,
    /// Faults drawn at random, on top of the counted ones.
    pub random: Option<Random>,
}

/// Faults drawn from a seeded generator: whole jobs run on a store configured by
/// [`ENV`] (`seed=7,reads=optimizer.,read_p=0.2,creates=checkpoints/,create_p=0.3,put_delay_ms=80`).
#[derive(Debug, Default, Clone)]
pub struct Random {
    pub state: u64,
    /// Reads of objects whose path contains `reads` fail transiently with `read_p`.
    pub reads: String,
    pub read_p: f64,
    /// Create-only puts of objects whose path contains `creates` are written and then
    /// answered `AlreadyExists` with `create_p`.
    pub creates: String,
    pub create_p: f64,
    /// Every put waits a time drawn up to this.
    pub put_delay_max: Duration,
}

impl Random {
    /// The next draw in [0, 1) (xorshift64*: no dependency, the same sequence for a
    /// seed).
    fn draw(&mut self) -> f64 {
        let mut x = self.state.max(1);
        x ^= x >> 12;
        x ^= x << 25;
        x ^= x >> 27;
        self.state = x;
        (x.wrapping_mul(0x2545_f491_4f6c_dd1d) >> 11) as f64 / (1u64 << 53) as f64
    }

    /// Parses [`ENV`]'s value.
    pub fn parse(spec: &str) -> Result<Self, String> {
        let mut r = Random::default();
        for part in spec.split(',').filter(|p| !p.is_empty()) {
            let (k, v) = part
                .split_once('=')
                .ok_or_else(|| format!("{ENV}: `{part}` is not KEY=VALUE"))?;
            let num = |v: &str| {
                v.parse::<f64>()
                    .ok()
                    .filter(|x| x.is_finite() && *x >= 0.0)
                    .ok_or_else(|| format!("{ENV}: {k} = `{v}` is not a non-negative number"))
            };
            match k {
                "seed" => r.state = num(v)? as u64 ^ 0x9e37_79b9_7f4a_7c15,
                "reads" => r.reads = v.to_string(),
                "read_p" => r.read_p = num(v)?,
                "creates" => r.creates = v.to_string(),
                "create_p" => r.create_p = num(v)?,
                "put_delay_ms" => {
                    r.put_delay_max = Duration::from_secs_f64(num(v)?.min(60e3) / 1e3)
                }
                _ => return Err(format!("{ENV}: unknown key `{k}`")),
            }
        }
        Ok(r)
    }
}

/// The variable that wraps every store a process opens in a [`ChaosStore`] with
/// [`Random`] faults (builds with the `fault-injection` feature only).
pub const ENV: &str = "OSRT_FAULT_STORE";

/// `inner` with [`Faults`].
#[derive(Debug)]
pub struct ChaosStore {
    inner: Arc<dyn ObjectStore>,
    faults: Mutex<Faults>,
    /// Faults served so far.
    served: std::sync::atomic::AtomicUsize,
}

impl ChaosStore {
    pub fn new(inner: Arc<dyn ObjectStore>) -> Self {
        Self {
            inner,
            faults: Mutex::default(),
            served: Default::default(),
        }
    }

    /// Changes the faults.
    pub fn faults(&self, f: impl FnOnce(&mut Faults)) {
        f(&mut self.faults.lock().expect("faults"));
    }

    /// Faults served so far.
    pub fn served(&self) -> usize {
        self.served.load(std::sync::atomic::Ordering::SeqCst)
    }

    fn read_fault(&self, location: &Path) -> object_store::Result<()> {
        let mut f = self.faults.lock().expect("faults");
        if let Some(r) = f.random.as_mut()
            && !r.reads.is_empty()
            && location.as_ref().contains(r.reads.as_str())
            && r.draw() < r.read_p
        {
            self.served
                .fetch_add(1, std::sync::atomic::Ordering::SeqCst);
            return Err(object_store::Error::Generic {
                store: "chaos",
                source: format!("{location}: request timed out (injected)").into(),
            });
        }
        let hit = f
            .reads
            .iter_mut()
            .find(|(pattern, _, n)| *n > 0 && location.as_ref().contains(pattern.as_str()));
        let Some((_, kind, n)) = hit else {
            return Ok(());
        };
        if *n != usize::MAX {
            *n -= 1;
        }
        self.served
            .fetch_add(1, std::sync::atomic::Ordering::SeqCst);
        let path = location.to_string();
        Err(match kind {
            ReadFault::Transient => object_store::Error::Generic {
                store: "chaos",
                source: format!("{path}: request timed out (injected)").into(),
            },
            ReadFault::Denied => object_store::Error::PermissionDenied {
                path,
                source: "access denied (injected)".into(),
            },
        })
    }
}

impl std::fmt::Display for ChaosStore {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "Chaos({})", self.inner)
    }
}

#[async_trait]
impl ObjectStore for ChaosStore {
    async fn put_opts(
        &self,
        location: &Path,
        payload: PutPayload,
        opts: PutOptions,
    ) -> object_store::Result<PutResult> {
        let (delay, lie) = {
            let mut f = self.faults.lock().expect("faults");
            if f.fail_puts > 0 {
                f.fail_puts -= 1;
                self.served
                    .fetch_add(1, std::sync::atomic::Ordering::SeqCst);
                return Err(object_store::Error::Generic {
                    store: "chaos",
                    source: format!("{location}: connection reset by peer (injected)").into(),
                });
            }
            let create = matches!(opts.mode, PutMode::Create);
            let mut lie = create && f.exists_after_create > 0;
            if lie {
                f.exists_after_create -= 1;
            }
            let slow = f
                .slow_puts
                .as_ref()
                .is_none_or(|p| location.as_ref().contains(p.as_str()));
            let mut delay = if slow { f.put_delay } else { Duration::ZERO };
            if let Some(r) = f.random.as_mut() {
                delay += r.put_delay_max.mul_f64(r.draw());
                lie |= create
                    && !r.creates.is_empty()
                    && location.as_ref().contains(r.creates.as_str())
                    && r.draw() < r.create_p;
            }
            (delay, lie)
        };
        if !delay.is_zero() {
            tokio::time::sleep(delay).await;
        }
        let put = self.inner.put_opts(location, payload, opts).await?;
        if lie {
            self.served
                .fetch_add(1, std::sync::atomic::Ordering::SeqCst);
            return Err(object_store::Error::AlreadyExists {
                path: location.to_string(),
                source: "written, but the retried request found it (injected)".into(),
            });
        }
        Ok(put)
    }

    async fn put_multipart_opts(
        &self,
        location: &Path,
        opts: PutMultipartOptions,
    ) -> object_store::Result<Box<dyn MultipartUpload>> {
        self.inner.put_multipart_opts(location, opts).await
    }

    async fn get_opts(
        &self,
        location: &Path,
        options: GetOptions,
    ) -> object_store::Result<GetResult> {
        self.read_fault(location)?;
        self.inner.get_opts(location, options).await
    }

    fn delete_stream(
        &self,
        locations: BoxStream<'static, object_store::Result<Path>>,
    ) -> BoxStream<'static, object_store::Result<Path>> {
        self.inner.delete_stream(locations)
    }

    fn list(&self, prefix: Option<&Path>) -> BoxStream<'static, object_store::Result<ObjectMeta>> {
        self.inner.list(prefix)
    }

    async fn list_with_delimiter(&self, prefix: Option<&Path>) -> object_store::Result<ListResult> {
        self.inner.list_with_delimiter(prefix).await
    }

    async fn copy_opts(
        &self,
        from: &Path,
        to: &Path,
        options: CopyOptions,
    ) -> object_store::Result<()> {
        self.inner.copy_opts(from, to, options).await
    }
}
