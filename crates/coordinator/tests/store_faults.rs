//! The coordinator against a store whose writes fail for a while: it keeps serving,
//! writes `job.json` once the store answers again, and never exits on one failed put.

use async_trait::async_trait;
use futures::stream::BoxStream;
use object_store::memory::InMemory;
use object_store::path::Path;
use object_store::{
    CopyOptions, GetOptions, GetResult, ListResult, MultipartUpload, ObjectMeta, ObjectStore,
    ObjectStoreExt, PutMultipartOptions, PutOptions, PutPayload, PutResult,
};
use osrt_coordinator::{ClusterOverrides, Coordinator, JobSpec};
use osrt_dataset::Location;
use osrt_proto::auth::Token;
use osrt_trainer::JobConfig;
use std::sync::Arc;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::time::{Duration, Instant};

/// An in-memory store whose next `fail_puts` puts fail as a network error would.
#[derive(Debug, Default)]
struct Flaky {
    inner: InMemory,
    fail_puts: AtomicUsize,
    failed: AtomicUsize,
}

impl std::fmt::Display for Flaky {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "Flaky({})", self.inner)
    }
}

#[async_trait]
impl ObjectStore for Flaky {
    async fn put_opts(
        &self,
        location: &Path,
        payload: PutPayload,
        opts: PutOptions,
    ) -> object_store::Result<PutResult> {
        let take = |n: usize| n.checked_sub(1);
        if self
            .fail_puts
            .fetch_update(Ordering::SeqCst, Ordering::SeqCst, take)
            .is_ok()
        {
            self.failed.fetch_add(1, Ordering::SeqCst);
            return Err(object_store::Error::Generic {
                store: "flaky",
                source: "connection reset by peer".into(),
            });
        }
        self.inner.put_opts(location, payload, opts).await
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

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn failed_writes_of_the_run_folder_are_retried_not_fatal() {
    let store = Arc::new(Flaky::default());
    let run = Location::new(store.clone(), "run");
    let job = JobConfig::preset("tiny").unwrap();
    let spec = JobSpec {
        job_id: "job-flaky".into(),
        job_toml: job.to_toml(),
        job,
        data: "memory://nowhere/data".into(),
        run: "flaky://run".into(),
        max_steps: Some(3),
        deadline_unix_s: None,
        cluster_overrides: ClusterOverrides::default(),
    };
    let coord = Coordinator::open_at(spec, run.clone(), false)
        .await
        .unwrap();
    // Every write of the monitor fails for a while: the first five puts.
    store.fail_puts.store(5, Ordering::SeqCst);
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
    let (stop, stopped) = tokio::sync::oneshot::channel::<()>();
    let serving = tokio::spawn(coord.serve(
        listener,
        Token::generate(),
        None,
        Duration::from_secs(1),
        async move {
            let _ = stopped.await;
        },
    ));
    let job_json = run.path("job.json");
    let t = Instant::now();
    while store.inner.head(&job_json).await.is_err() {
        assert!(
            !serving.is_finished(),
            "the coordinator exited on a failed put"
        );
        assert!(
            t.elapsed() < Duration::from_secs(30),
            "job.json never written"
        );
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    assert_eq!(store.failed.load(Ordering::SeqCst), 5);
    let bytes = store
        .inner
        .get(&job_json)
        .await
        .unwrap()
        .bytes()
        .await
        .unwrap();
    let p: serde_json::Value = serde_json::from_slice(&bytes).unwrap();
    assert_eq!(p["state"], "waiting", "{p}");
    stop.send(()).unwrap();
    serving.await.unwrap().unwrap();
}
