//! The coordinator against a store whose writes fail for a while: it keeps serving,
//! writes `job.json` once the store answers again, and never exits on one failed put.

use object_store::ObjectStoreExt;
use object_store::memory::InMemory;
use osrt_coordinator::{Coordinator, JobSpec};
use osrt_proto::auth::Token;
use osrt_proto::credentials::Credentials;
use osrt_run::cluster_config::ClusterConfig;
use osrt_run::cluster_config::ClusterOverrides;
use osrt_store::Location;
use osrt_store::chaos::ChaosStore;
use std::sync::Arc;
use std::time::{Duration, Instant};

/// A three-step job of `cluster` on data it never reads.
fn spec(job_id: &str, cluster: ClusterConfig) -> JobSpec {
    JobSpec {
        job_id: job_id.into(),
        job_toml: "[cluster]\n".into(),
        cluster,
        data: "memory://nowhere/data".into(),
        run: "memory://run".into(),
        max_steps: Some(3),
        deadline_unix_s: None,
        cluster_overrides: ClusterOverrides::default(),
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn failed_writes_of_the_run_folder_are_retried_not_fatal() {
    let inner = Arc::new(InMemory::new());
    let store = Arc::new(ChaosStore::new(inner.clone()));
    let run = Location::new(store.clone(), "run");
    let spec = spec("job-flaky", ClusterConfig::default());
    let coord = Coordinator::open_at(spec, run.clone(), false)
        .await
        .unwrap();
    // Every write of the monitor fails for a while: the first five puts.
    store.faults(|f| f.fail_puts = 5);
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
    let (stop, stopped) = tokio::sync::oneshot::channel::<()>();
    let serving = tokio::spawn(coord.serve(
        listener,
        Credentials::new(Token::generate(), None),
        Duration::from_secs(1),
        async move {
            let _ = stopped.await;
        },
    ));
    let job_json = run.path("job.json");
    let t = Instant::now();
    while inner.head(&job_json).await.is_err() {
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
    assert_eq!(store.served(), 5);
    let bytes = inner.get(&job_json).await.unwrap().bytes().await.unwrap();
    let p: serde_json::Value = serde_json::from_slice(&bytes).unwrap();
    assert_eq!(p["state"], "waiting", "{p}");
    stop.send(()).unwrap();
    serving.await.unwrap().unwrap();
}

/// A slow store delays what is written, not the job's clock: while every write of
/// `job.json` takes 20 s, a worker is still let in, formed into a generation, and dropped
/// once silent past its heartbeat timeout.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_slow_upload_does_not_hold_up_lost_worker_detection() {
    use osrt_proto::auth::AttachToken;
    use osrt_proto::v1;
    let inner = Arc::new(InMemory::new());
    let store = Arc::new(ChaosStore::new(inner.clone()));
    let run = Location::new(store.clone(), "run");
    let cluster = ClusterConfig {
        min_workers: 1,
        join_grace_s: 0.1,
        heartbeat_timeout_s: 1.5,
        ..ClusterConfig::default()
    };
    let spec = spec("job-slow", cluster);
    let coord = Coordinator::open_at(spec, run.clone(), false)
        .await
        .unwrap();
    store.faults(|f| {
        f.slow_puts = Some("job.json".into());
        f.put_delay = Duration::from_secs(20);
    });
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
    let addr = listener.local_addr().unwrap();
    let token = Token::generate();
    let serving = tokio::spawn(coord.clone().serve(
        listener,
        Credentials::new(token.clone(), None),
        Duration::from_secs(1),
        std::future::pending(),
    ));
    let channel = tonic::transport::Endpoint::from_shared(format!("http://{addr}"))
        .unwrap()
        .connect_lazy();
    let mut client =
        v1::coordinator_client::CoordinatorClient::with_interceptor(channel, AttachToken(token));
    let t = Instant::now();
    client
        .register(v1::RegisterRequest {
            protocol_version: osrt_proto::PROTOCOL_VERSION,
            name: "silent".into(),
            collective_addr: "http://127.0.0.1:1".into(),
            threads: 1,
            instance: 7,
        })
        .await
        .unwrap();
    // Formed (generation 1), then silent: dropped well before a job.json write returns.
    loop {
        let s = coord.status();
        if s.generation >= 1 && s.members.is_empty() {
            break;
        }
        assert!(
            t.elapsed() < Duration::from_secs(8),
            "after {:?}: generation {}, {} members",
            t.elapsed(),
            s.generation,
            s.members.len()
        );
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    assert!(!serving.is_finished());
    serving.abort();
}
