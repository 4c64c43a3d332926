//! A coordinator continuing a job whose checkpoints its store will not hand over stops
//! with an error naming the checkpoint: it neither starts the job over nor rewrites
//! `metrics.jsonl`, and every checkpoint is still there (before, it took the refusal for
//! a corrupt checkpoint, started from step 0 and rank 0 deleted every checkpoint).

use bytes::Bytes;
use object_store::ObjectStoreExt;
use object_store::memory::InMemory;
use osrt_coordinator::{Coordinator, JobSpec, Persisted};
use osrt_run::checkpoint::{self, CheckpointState, MODEL, OPTIMIZER, STATE};
use osrt_run::cluster_config::ClusterConfig;
use osrt_run::cluster_config::ClusterOverrides;
use osrt_store::Location;
use osrt_store::chaos::{ChaosStore, ReadFault};
use std::sync::Arc;

const TOML: &str = "[cluster]\n";

fn spec() -> JobSpec {
    JobSpec {
        job_id: "job-unreadable".into(),
        job_toml: TOML.into(),
        cluster: ClusterConfig::default(),
        data: "memory://nowhere/data".into(),
        run: "chaos://run".into(),
        max_steps: Some(100),
        deadline_unix_s: None,
        cluster_overrides: ClusterOverrides::default(),
    }
}

async fn put(run: &Location, name: &str, bytes: Vec<u8>) {
    run.store.put(&run.path(name), bytes.into()).await.unwrap();
}

/// A job trained to step 12 with checkpoints at 5, 10 and 12, as its coordinator left it.
async fn trained_run() -> (Arc<ChaosStore>, Location, Vec<u8>) {
    let chaos = Arc::new(ChaosStore::new(Arc::new(InMemory::new())));
    let run = Location::new(chaos.clone(), "run");
    for step in [5, 10, 12] {
        let st = CheckpointState {
            step,
            epoch: 0,
            epoch_start_step: 0,
            world_size: 1,
            rng: String::new(),
            adam_t: step,
            skipped_total: 0,
            wall_s: 1.0,
            train_s: 1.0,
            config_hash: checkpoint::config_hash(TOML),
            val_fg_ari: None,
            val_psnr: None,
            horizon: None,
        };
        let files = vec![
            (MODEL, Bytes::from(vec![step as u8; 64])),
            (OPTIMIZER, Bytes::from(vec![step as u8; 128])),
            (STATE, Bytes::from(serde_json::to_vec(&st).unwrap())),
        ];
        checkpoint::commit(&run, &st, files, None).await.unwrap();
    }
    let p = Persisted {
        job_id: "job-unreadable".into(),
        data: "memory://nowhere/data".into(),
        max_steps: Some(100),
        deadline_unix_s: None,
        generation: 1,
        restarts: 0,
        last_checkpoint: Some(12),
        hash_checks: 0,
        state: "running".into(),
        message: String::new(),
    };
    put(&run, "job.json", serde_json::to_vec(&p).unwrap()).await;
    put(&run, "config.toml", TOML.as_bytes().to_vec()).await;
    let metrics: String = (0..=12)
        .map(|s| format!("{{\"step\":{s},\"loss\":0.5}}\n"))
        .collect();
    put(&run, "metrics.jsonl", metrics.clone().into_bytes()).await;
    (chaos, run, metrics.into_bytes())
}

async fn read(run: &Location, name: &str) -> Vec<u8> {
    let r = run.store.get(&run.path(name)).await.unwrap();
    r.bytes().await.unwrap().to_vec()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn an_unreadable_resume_stops_and_loses_nothing() {
    let (chaos, run, metrics) = trained_run().await;
    chaos.faults(|f| f.reads = vec![("optimizer.".into(), ReadFault::Denied, usize::MAX)]);
    let e = match Coordinator::open_at(spec(), run.clone(), true).await {
        Ok(_) => panic!("the resume went on without its checkpoints"),
        Err(e) => e.to_string(),
    };
    assert!(
        e.contains("step-000000012") && e.contains("could not be read"),
        "{e}"
    );
    assert_eq!(checkpoint::list_steps(&run).await.unwrap(), vec![12, 10, 5]);
    assert_eq!(
        read(&run, "metrics.jsonl").await,
        metrics,
        "records rewritten"
    );
    assert!(
        run.store.head(&run.path("lease.json")).await.is_err(),
        "the refusal leaves the folder free"
    );
    // Once the store answers again, the job continues from step 12.
    chaos.faults(|f| f.reads.clear());
    let coord = Coordinator::open_at(spec(), run.clone(), true)
        .await
        .unwrap();
    assert_eq!(coord.status().last_checkpoint, Some(12));
}
