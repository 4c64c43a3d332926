//! Checkpoints through an object store (the in-memory one): exact round trip, torn and
//! corrupt checkpoints skipped, retention of the newest K plus the best.

use candle_core::Device;
use object_store::ObjectStoreExt;
use osrt_run::checkpoint::{self, CheckpointState, apply_retention, latest_verified, list_steps};
use osrt_store::Location;
use osrt_trainer::checkpoint::{Snapshot, load};
use osrt_trainer::{JobConfig, Trainer};

fn state(step: u64, fg_ari: Option<f64>) -> CheckpointState {
    CheckpointState {
        step,
        epoch: 0,
        epoch_start_step: 0,
        world_size: 1,
        rng: String::new(),
        adam_t: step,
        skipped_total: 0,
        wall_s: step as f64,
        train_s: step as f64,
        config_hash: "h".into(),
        val_fg_ari: fg_ari,
        val_psnr: Some(20.0),
        horizon: None,
    }
}

fn trainer() -> Trainer {
    Trainer::new(JobConfig::preset("tiny").unwrap(), Device::Cpu).unwrap()
}

/// Commits `t`'s weights as a checkpoint with `state` to `run`.
async fn commit(t: &Trainer, run: &Location, state: CheckpointState) {
    Snapshot::take(t, state)
        .unwrap()
        .commit(run, None)
        .await
        .unwrap();
}

/// The error of committing `t`'s weights with `state` to `run`.
async fn commit_error(t: &Trainer, run: &Location, state: CheckpointState) -> String {
    let e = Snapshot::take(t, state).unwrap().commit(run, None).await;
    e.unwrap_err().to_string()
}

/// The tiny preset's model initialised from another seed: other weights.
fn trainer_with_seed(seed: u64) -> Trainer {
    let mut job = JobConfig::preset("tiny").unwrap();
    job.train.seed = seed;
    Trainer::new(job, Device::Cpu).unwrap()
}

#[tokio::test]
async fn a_checkpoint_round_trips_exactly() {
    let run = Location::parse("memory://ckpt-roundtrip/run").unwrap();
    let mut t = trainer();
    // Non-trivial optimiser state.
    let n = t.num_parameters();
    let m: Vec<f32> = (0..n).map(|i| i as f32 * 1e-3).collect();
    let v: Vec<f32> = (0..n).map(|i| i as f32 * 1e-6).collect();
    t.opt.restore(m.clone(), v.clone(), 7).unwrap();
    let snap = Snapshot::take(&t, state(7, Some(0.5))).unwrap();
    snap.commit(&run, None).await.unwrap();
    let mut u = trainer_with_seed(99);
    assert_ne!(u.params.flatten().unwrap(), t.params.flatten().unwrap());
    let st = load(&run, 7, &mut u).await.unwrap();
    assert_eq!(st, state(7, Some(0.5)));
    assert_eq!(u.params.flatten().unwrap(), t.params.flatten().unwrap());
    assert_eq!((u.opt.moments().unwrap(), u.opt.t()), ((m, v), 7));
    assert_eq!(u.step, 7);
}

#[tokio::test]
async fn torn_and_corrupt_checkpoints_are_skipped() {
    let run = Location::parse("memory://ckpt-torn/run").unwrap();
    let t = trainer();
    for s in [1, 2, 3] {
        commit(&t, &run, state(s, None)).await;
    }
    assert_eq!(latest_verified(&run, None).await.unwrap(), Some(3));
    // Corrupt step 3's optimiser file; tear step 2 (manifest gone).
    let p = run.path(
        &checkpoint::object_of(&run, 3, checkpoint::OPTIMIZER)
            .await
            .unwrap(),
    );
    let mut bytes = run
        .store
        .get(&p)
        .await
        .unwrap()
        .bytes()
        .await
        .unwrap()
        .to_vec();
    bytes[100] ^= 1;
    run.store.put(&p, bytes.into()).await.unwrap();
    run.store
        .delete(&run.path("checkpoints/step-000000002/MANIFEST.json"))
        .await
        .unwrap();
    let e = checkpoint::verify(&run, 3).await.unwrap_err().to_string();
    assert!(
        e.contains("SHA-256") && e.contains("step-000000003/optimizer"),
        "{e}"
    );
    let e = checkpoint::verify(&run, 2).await.unwrap_err().to_string();
    assert!(e.contains("torn"), "{e}");
    assert_eq!(latest_verified(&run, None).await.unwrap(), Some(1));
    let mut u = trainer();
    assert!(load(&run, 3, &mut u).await.is_err(), "never loaded");
    // Re-committing a step whose manifest exists but fails is refused, not overwritten.
    let e = commit_error(&t, &run, state(3, None)).await;
    assert!(e.contains("does not verify"), "{e}");
}

/// A replayed step adopts the committed checkpoint only if it holds the same weights
/// under the same config and world size; another job's checkpoint at that step is an
/// error, and its files are left as they were.
#[tokio::test]
async fn a_committed_checkpoint_is_adopted_only_if_it_is_this_jobs() {
    let run = Location::parse("memory://ckpt-adopt/run").unwrap();
    let t = trainer();
    commit(&t, &run, state(5, None)).await;
    let model = run.path(
        &checkpoint::object_of(&run, 5, checkpoint::MODEL)
            .await
            .unwrap(),
    );
    let before = run.store.get(&model).await.unwrap().bytes().await.unwrap();
    // The same step replayed: adopted.
    let mut again = state(5, None);
    again.wall_s = 99.0;
    commit(&t, &run, again).await;
    // Other weights, another config, another world size: refused.
    let other = trainer_with_seed(99);
    let e = commit_error(&other, &run, state(5, None)).await;
    assert!(
        e.contains("another checkpoint is committed at step 5"),
        "{e}"
    );
    assert!(e.contains("model.safetensors"), "{e}");
    let mut hashed = state(5, None);
    hashed.config_hash = "other".into();
    hashed.world_size = 2;
    let e = commit_error(&t, &run, hashed).await;
    assert!(
        e.contains("job config") && e.contains("world size (1 there, 2 here)"),
        "{e}"
    );
    let after = run.store.get(&model).await.unwrap().bytes().await.unwrap();
    assert_eq!(before, after, "the committed files were not touched");
}

/// A generation that starts from step 10 discards what an abandoned timeline left past
/// it, committed or torn.
#[tokio::test]
async fn checkpoints_past_the_starting_point_are_discarded() {
    let run = Location::parse("memory://ckpt-discard/run").unwrap();
    let t = trainer();
    for s in [10, 20, 30] {
        commit(&t, &run, state(s, None)).await;
    }
    let m = run.path("checkpoints/step-000000030/MANIFEST.json");
    run.store.delete(&m).await.unwrap();
    assert_eq!(
        checkpoint::discard_after(&run, Some(10)).await.unwrap(),
        vec![30, 20]
    );
    assert_eq!(list_steps(&run).await.unwrap(), vec![10]);
    assert_eq!(
        checkpoint::discard_after(&run, None).await.unwrap(),
        vec![10]
    );
    assert!(list_steps(&run).await.unwrap().is_empty());
}

/// A transient error while checking whether a checkpoint is already committed fails the
/// commit: it never leads to writing over a committed checkpoint's files.
#[tokio::test]
async fn a_transient_error_before_a_commit_never_overwrites() {
    use osrt_store::chaos::{ChaosStore, ReadFault};
    let inner = std::sync::Arc::new(object_store::memory::InMemory::new());
    let store = std::sync::Arc::new(ChaosStore::new(inner));
    let run = Location::new(store.clone(), "run");
    let t = trainer();
    commit(&t, &run, state(5, None)).await;
    let model = run.path(
        &checkpoint::object_of(&run, 5, checkpoint::MODEL)
            .await
            .unwrap(),
    );
    let before = run.store.get(&model).await.unwrap().bytes().await.unwrap();
    store.faults(|f| f.reads = vec![("step-000000005/MANIFEST".into(), ReadFault::Transient, 1)]);
    let other = trainer_with_seed(7);
    let e = commit_error(&other, &run, state(5, None)).await;
    assert!(e.contains("timed out (injected)"), "{e}");
    assert_eq!(store.served(), 1);
    let after = run.store.get(&model).await.unwrap().bytes().await.unwrap();
    assert_eq!(before, after);
    checkpoint::verify(&run, 5).await.unwrap();
}

/// Torn folders (no manifest) do not count towards `keep_last`, so they can never push
/// the newest committed checkpoint out; `keep_last = 0` keeps one.
#[tokio::test]
async fn retention_never_counts_torn_folders() {
    let run = Location::parse("memory://ckpt-retention-torn/run").unwrap();
    let t = trainer();
    for s in [10, 20, 30, 40, 50] {
        commit(&t, &run, state(s, None)).await;
    }
    for s in [40, 50] {
        let m = run.path(&format!("checkpoints/step-{s:09}/MANIFEST.json"));
        run.store.delete(&m).await.unwrap();
    }
    assert_eq!(apply_retention(&run, 2, u64::MAX).await.unwrap(), vec![10]);
    assert_eq!(latest_verified(&run, None).await.unwrap(), Some(30));
    assert_eq!(apply_retention(&run, 0, u64::MAX).await.unwrap(), vec![20]);
    assert_eq!(latest_verified(&run, None).await.unwrap(), Some(30));
    assert_eq!(
        list_steps(&run).await.unwrap(),
        vec![50, 40, 30],
        "torn left alone"
    );
}

#[tokio::test]
async fn retention_keeps_the_newest_and_the_best() {
    let run = Location::parse("memory://ckpt-retention/run").unwrap();
    let t = trainer();
    let scores = [(10, 0.2), (20, 0.9), (30, 0.4), (40, 0.5), (50, 0.1)];
    for (s, f) in scores {
        commit(&t, &run, state(s, Some(f))).await;
    }
    let deleted = apply_retention(&run, 2, u64::MAX).await.unwrap();
    assert_eq!(deleted, vec![30, 10]);
    assert_eq!(list_steps(&run).await.unwrap(), vec![50, 40, 20]);
    for s in [50, 40, 20] {
        checkpoint::verify(&run, s).await.unwrap();
    }
}

/// Retention never deletes the checkpoint a restarted coordinator would continue from
/// (the newest at or before the resume bound) nor a newer one, whatever `keep_last`.
#[tokio::test]
async fn retention_keeps_the_checkpoint_a_restart_continues_from() {
    let run = Location::parse("memory://ckpt-retention-bound/run").unwrap();
    let t = trainer();
    for s in [10, 20, 30, 40, 50] {
        commit(&t, &run, state(s, None)).await;
    }
    // Records reached step 27: a restart continues from 20.
    assert_eq!(apply_retention(&run, 1, 27).await.unwrap(), vec![10]);
    assert_eq!(list_steps(&run).await.unwrap(), vec![50, 40, 30, 20]);
    assert_eq!(latest_verified(&run, Some(27)).await.unwrap(), Some(20));
    // Nothing at or before the bound: a restart starts over, nothing to keep for it.
    assert_eq!(apply_retention(&run, 1, 5).await.unwrap(), vec![40, 30, 20]);
    assert_eq!(list_steps(&run).await.unwrap(), vec![50]);
}

/// Two writers commit one step at once (a second job on the folder): each writes its own
/// create-only files, the first manifest wins, the loser is told and leaves nothing
/// behind, and the winner's checkpoint verifies with the winner's bytes. Two writers of
/// the same bytes both succeed.
#[tokio::test]
async fn two_writers_at_one_step_never_overwrite_each_other() {
    let dir = tempfile::tempdir().unwrap();
    let run = Location::parse(dir.path().join("run").to_str().unwrap()).unwrap();
    for round in 0..8u64 {
        let (a, b) = (trainer(), trainer_with_seed(99 + round));
        let step = 10 + round;
        let (ra, rb) = tokio::join!(
            Snapshot::take(&a, state(step, None))
                .unwrap()
                .commit(&run, None),
            Snapshot::take(&b, state(step, None))
                .unwrap()
                .commit(&run, None),
        );
        assert!(ra.is_ok() != rb.is_ok(), "round {round}: {ra:?} / {rb:?}");
        let loser = ra.as_ref().err().or(rb.as_ref().err()).unwrap().to_string();
        assert!(loser.contains("another checkpoint is committed"), "{loser}");
        let winner = if ra.is_ok() { &a } else { &b };
        let mut loaded = trainer_with_seed(7);
        load(&run, step, &mut loaded).await.unwrap();
        let (got, want) = (
            loaded.params.flatten().unwrap(),
            winner.params.flatten().unwrap(),
        );
        assert!(got == want, "round {round}: the winner's weights");
        let folder = dir.path().join(format!("run/checkpoints/step-{step:09}"));
        let objects = std::fs::read_dir(&folder).unwrap().count();
        assert_eq!(
            objects, 4,
            "round {round}: the manifest and the winner's 3 files"
        );
    }
    let t = trainer();
    let (ra, rb) = tokio::join!(
        Snapshot::take(&t, state(40, None))
            .unwrap()
            .commit(&run, None),
        Snapshot::take(&t, state(40, None))
            .unwrap()
            .commit(&run, None),
    );
    assert_eq!((ra.unwrap(), rb.unwrap()), (40, 40));
    checkpoint::verify(&run, 40).await.unwrap();
}
