//! The run's metrics records as written by the coordinator's log: appended to one local
//! file, or as parts on an object store; cut where a new generation starts; never more
//! than one part in memory; a failed write loses and repeats nothing.

use object_store::ObjectStoreExt;
use object_store::memory::InMemory;
use osrt_run::METRICS_FILE;
use osrt_run::metrics_log::{self, MetricsLog, PART_LINES, part_name};
use osrt_store::Location;
use osrt_store::chaos::ChaosStore;
use std::sync::Arc;

fn line(step: u64) -> String {
    format!("{{\"loss\":0.5,\"step\":{step}}}")
}

fn lines(steps: impl IntoIterator<Item = u64>) -> Vec<(u64, String)> {
    steps.into_iter().map(|s| (s, line(s))).collect()
}

/// The steps the run folder holds, in order, as a reader sees them.
async fn steps(run: &Location) -> Vec<u64> {
    let text = metrics_log::read_all(run)
        .await
        .unwrap()
        .unwrap_or_default();
    text.lines()
        .map(|l| osrt_run::MetricsRecord::parse(l).unwrap().step())
        .collect()
}

fn memory_run() -> (Arc<InMemory>, Location) {
    let inner = Arc::new(InMemory::new());
    (inner.clone(), Location::new(inner, "run"))
}

async fn exists(store: &InMemory, run: &Location, name: &str) -> bool {
    store.head(&run.path(name)).await.is_ok()
}

#[tokio::test]
async fn an_object_store_gets_parts_and_only_the_open_one_is_written_again() {
    let (store, run) = memory_run();
    let mut log = MetricsLog::open(&run).await.unwrap();
    assert!(!log.appends_in_place());
    let n = 2 * PART_LINES as u64 + 10;
    // Pushed and flushed in small batches, as the coordinator does: memory never holds
    // more than the open part.
    for chunk in (0..n).collect::<Vec<_>>().chunks(100) {
        log.push(lines(chunk.iter().copied()));
        log.flush().await.unwrap();
        assert!(log.held() <= PART_LINES, "{} lines held", log.held());
    }
    assert_eq!(steps(&run).await, (0..n).collect::<Vec<_>>());
    for i in 0..3 {
        assert!(exists(&store, &run, &part_name(i)).await, "part {i}");
    }
    assert!(!exists(&store, &run, METRICS_FILE).await);
    assert_eq!(log.held(), 10);

    // A cut inside the first part: the later parts go, the first is open again; the
    // newest step left is known (retention protects the checkpoint it bounds).
    let keep = PART_LINES as u64 / 2;
    log.cut_after(Some(keep));
    log.flush().await.unwrap();
    assert_eq!(log.last_step(), Some(keep));
    log.push(lines([keep + 1]));
    log.flush().await.unwrap();
    assert_eq!(steps(&run).await, (0..=keep + 1).collect::<Vec<_>>());
    assert!(!exists(&store, &run, &part_name(1)).await);
    assert!(!exists(&store, &run, &part_name(2)).await);

    // Opened again (a restarted coordinator), it continues where the folder ends.
    let mut log = MetricsLog::open(&run).await.unwrap();
    assert_eq!(log.last_step(), Some(keep + 1));
    log.push(lines(keep + 2..keep + 2 + PART_LINES as u64));
    log.flush().await.unwrap();
    let all = keep + 2 + PART_LINES as u64;
    assert_eq!(steps(&run).await, (0..all).collect::<Vec<_>>());
    // A cut of everything (no checkpoint) leaves no record.
    log.cut_after(None);
    log.flush().await.unwrap();
    assert_eq!(steps(&run).await, Vec::<u64>::new());
}

#[tokio::test]
async fn a_local_file_is_appended_and_cut_in_place() {
    let dir = tempfile::tempdir().unwrap();
    let run = Location::parse(dir.path().to_str().unwrap()).unwrap();
    let mut log = MetricsLog::open(&run).await.unwrap();
    assert!(log.appends_in_place());
    log.push(lines(0..6));
    log.flush().await.unwrap();
    log.push(lines(6..8));
    log.flush().await.unwrap();
    assert_eq!(log.held(), 0);
    assert_eq!(steps(&run).await, (0..8).collect::<Vec<_>>());
    log.cut_after(Some(4));
    log.push(lines(5..7));
    log.flush().await.unwrap();
    assert_eq!(steps(&run).await, (0..7).collect::<Vec<_>>());

    // A crash in the middle of an append leaves half a line: the restarted job's cut
    // drops it, and what follows starts on a line of its own.
    let file = dir.path().join(METRICS_FILE);
    let mut text = std::fs::read_to_string(&file).unwrap();
    text.push_str("{\"loss\":0.5,\"st");
    std::fs::write(&file, &text).unwrap();
    let mut log = MetricsLog::open(&run).await.unwrap();
    log.cut_after(Some(6));
    log.flush().await.unwrap();
    assert_eq!(
        log.last_step(),
        Some(6),
        "the newest step left after the cut"
    );
    log.push(lines([7]));
    log.flush().await.unwrap();
    assert_eq!(steps(&run).await, (0..8).collect::<Vec<_>>());
}

#[tokio::test]
async fn an_older_single_file_on_an_object_store_is_moved_into_parts() {
    let (store, run) = memory_run();
    let text: String = (0..PART_LINES as u64 + 3).map(|s| line(s) + "\n").collect();
    store
        .put(&run.path(METRICS_FILE), text.into())
        .await
        .unwrap();
    let mut log = MetricsLog::open(&run).await.unwrap();
    assert_eq!(log.last_step(), Some(PART_LINES as u64 + 2));
    // Nothing moves before the first flush (a refused job leaves the folder as it was).
    assert!(exists(&store, &run, METRICS_FILE).await);
    log.push(lines([PART_LINES as u64 + 3]));
    log.flush().await.unwrap();
    assert!(!exists(&store, &run, METRICS_FILE).await);
    assert!(exists(&store, &run, &part_name(1)).await);
    assert_eq!(
        steps(&run).await,
        (0..PART_LINES as u64 + 4).collect::<Vec<_>>()
    );
}

#[tokio::test]
async fn a_failed_flush_is_made_again_without_loss_or_repeat() {
    let inner = Arc::new(InMemory::new());
    let chaos = Arc::new(ChaosStore::new(inner));
    let run = Location::new(chaos.clone(), "run");
    let mut log = MetricsLog::open(&run).await.unwrap();
    log.push(lines(0..PART_LINES as u64 + 5));
    chaos.faults(|f| f.fail_puts = 2);
    assert!(log.flush().await.is_err());
    assert!(log.is_dirty());
    log.push(lines([PART_LINES as u64 + 5]));
    assert!(log.flush().await.is_err());
    log.flush().await.unwrap();
    assert!(!log.is_dirty());
    assert_eq!(
        steps(&run).await,
        (0..PART_LINES as u64 + 6).collect::<Vec<_>>()
    );
}
