//! Checkpoints on a store that misbehaves. One that cannot be read never costs a
//! checkpoint: a resume tells "missing or provably corrupt" (skipped) from "could not be
//! read" (retried, then an error naming the checkpoint), and nothing is deleted on the
//! way. A commit whose puts were answered `AlreadyExists` after they went through keeps
//! its checkpoint.

use bytes::Bytes;
use object_store::ObjectStoreExt;
use object_store::memory::InMemory;
use osrt_retry::RetryPolicy;
use osrt_run::RunError;
use osrt_run::checkpoint::{self, CheckpointState, MODEL, OPTIMIZER, STATE};
use osrt_store::Location;
use osrt_store::chaos::{ChaosStore, ReadFault};
use std::sync::Arc;
use std::time::Duration;

fn state(step: u64) -> CheckpointState {
    CheckpointState {
        step,
        epoch: 0,
        epoch_start_step: 0,
        world_size: 1,
        rng: String::new(),
        adam_t: step,
        skipped_total: 0,
        wall_s: 0.0,
        train_s: 0.0,
        config_hash: "c".into(),
        val_fg_ari: None,
        val_psnr: None,
        horizon: None,
    }
}

/// The files of a checkpoint of `st`, their bytes drawn from `fill`.
fn files_of(st: &CheckpointState, fill: u8) -> Vec<(&'static str, Bytes)> {
    vec![
        (MODEL, Bytes::from(vec![fill; 64])),
        (OPTIMIZER, Bytes::from(vec![fill; 128])),
        (STATE, Bytes::from(serde_json::to_vec(st).unwrap())),
    ]
}

async fn run_with_checkpoints(steps: &[u64]) -> (Arc<ChaosStore>, Location) {
    let chaos = Arc::new(ChaosStore::new(Arc::new(InMemory::new())));
    let run = Location::new(chaos.clone(), "run");
    for &s in steps {
        let st = state(s);
        checkpoint::commit(&run, &st, files_of(&st, s as u8), None)
            .await
            .unwrap();
    }
    (chaos, run)
}

fn quick() -> RetryPolicy {
    RetryPolicy::every(Duration::from_millis(5), Duration::from_millis(300))
}

/// Every optimizer file refused (the reproduction: `chmod 000 optimizer.*`): the resume
/// stops at once with an error naming the newest checkpoint, and every checkpoint stays.
#[tokio::test]
async fn a_refused_read_stops_the_resume_and_keeps_every_checkpoint() {
    let (chaos, run) = run_with_checkpoints(&[5, 10, 12]).await;
    chaos.faults(|f| f.reads = vec![("optimizer.".into(), ReadFault::Denied, usize::MAX)]);
    let e = checkpoint::latest_verified_with(&run, None, quick())
        .await
        .unwrap_err();
    assert!(
        matches!(
            e,
            RunError::Unreadable {
                transient: false,
                ..
            }
        ),
        "{e:?}"
    );
    let msg = e.to_string();
    assert!(
        msg.contains("step-000000012") && msg.contains("nothing was discarded"),
        "{msg}"
    );
    assert_eq!(chaos.served(), 1, "a refusal is not retried");
    assert_eq!(checkpoint::list_steps(&run).await.unwrap(), vec![12, 10, 5]);
}

/// Reads that time out are retried; ones that pass within the budget verify the newest
/// checkpoint, ones that do not stop the resume with the error (no older checkpoint is
/// taken instead).
#[tokio::test]
async fn a_read_that_times_out_is_retried_then_stops_the_resume() {
    let (chaos, run) = run_with_checkpoints(&[5, 10]).await;
    chaos.faults(|f| f.reads = vec![("optimizer.".into(), ReadFault::Transient, 3)]);
    let got = checkpoint::latest_verified_with(&run, None, quick()).await;
    assert_eq!(got.unwrap(), Some(10));
    assert_eq!(chaos.served(), 3);
    chaos.faults(|f| f.reads = vec![("step-000000010".into(), ReadFault::Transient, usize::MAX)]);
    let e = checkpoint::latest_verified_with(&run, None, quick())
        .await
        .unwrap_err();
    assert!(
        matches!(
            e,
            RunError::Unreadable {
                transient: true,
                ..
            }
        ),
        "{e:?}"
    );
    assert!(e.to_string().contains("step-000000010"), "{e}");
    assert_eq!(checkpoint::list_steps(&run).await.unwrap(), vec![10, 5]);
}

/// Missing or corrupt is another matter: a torn checkpoint (no manifest) and one whose
/// file fails its hash are skipped for the newest older one that verifies.
#[tokio::test]
async fn a_provably_corrupt_checkpoint_is_skipped() {
    let (_chaos, run) = run_with_checkpoints(&[5, 10, 15]).await;
    let manifest = format!("{}/{}", checkpoint::step_dir(15), checkpoint::MANIFEST);
    run.store.delete(&run.path(&manifest)).await.unwrap();
    let model = checkpoint::object_of(&run, 10, MODEL).await.unwrap();
    run.store
        .put(&run.path(&model), Bytes::from(vec![0u8; 64]).into())
        .await
        .unwrap();
    let got = checkpoint::latest_verified_with(&run, None, quick()).await;
    assert_eq!(got.unwrap(), Some(5));
}

/// Retention stops when a checkpoint's state cannot be read: it might be the best's.
#[tokio::test]
async fn retention_deletes_nothing_it_cannot_read() {
    let (chaos, run) = run_with_checkpoints(&[5, 10, 15, 20]).await;
    chaos.faults(|f| {
        f.reads = vec![(
            "step-000000005/state.".into(),
            ReadFault::Transient,
            usize::MAX,
        )]
    });
    let e = checkpoint::apply_retention(&run, 1, u64::MAX)
        .await
        .unwrap_err();
    assert!(e.to_string().contains("step-000000005"), "{e}");
    assert_eq!(
        checkpoint::list_steps(&run).await.unwrap(),
        vec![20, 15, 10, 5]
    );
}

/// Every create of a commit goes through but is answered `AlreadyExists` (a retry of a
/// request the store had taken): the commit succeeds and its files stay (they were once
/// deleted as a losing writer's, leaving a manifest without files).
#[tokio::test]
async fn a_create_answered_already_exists_after_it_went_through_is_kept() {
    let (chaos, run) = run_with_checkpoints(&[]).await;
    chaos.faults(|f| f.exists_after_create = 4);
    let st = state(7);
    let files = files_of(&st, 7);
    assert_eq!(checkpoint::commit(&run, &st, files, None).await.unwrap(), 7);
    assert_eq!(chaos.served(), 4);
    checkpoint::check(&run, 7).await.unwrap();
}

/// A commit fenced by a generation the run folder's lease no longer names is refused
/// before its manifest, and leaves no file behind.
#[tokio::test]
async fn a_commit_of_an_abandoned_generation_is_refused() {
    use osrt_run::lease::{Holder, Keeper, Lease, LeaseTiming};
    let (_chaos, run) = run_with_checkpoints(&[]).await;
    let lease = Lease::acquire(
        &run,
        Holder::this_process("j"),
        LeaseTiming::default(),
        false,
    )
    .await
    .unwrap();
    let keeper = Keeper::start(lease);
    while !keeper.fence(3) {
        tokio::time::sleep(Duration::from_millis(5)).await;
    }
    let st = state(9);
    let files = || files_of(&st, 9);
    let e = checkpoint::commit(&run, &st, files(), Some(2))
        .await
        .unwrap_err();
    assert!(matches!(e, RunError::Fenced { .. }), "{e:?}");
    let left = run
        .store
        .list_with_delimiter(Some(&run.path(&checkpoint::step_dir(9))))
        .await
        .unwrap();
    assert!(left.objects.is_empty(), "{:?}", left.objects);
    assert_eq!(
        checkpoint::commit(&run, &st, files(), Some(3))
            .await
            .unwrap(),
        9
    );
    keeper.release().await.unwrap();
}

/// A coordinator continuing a job fences off the persisted generation's ranks from its
/// first write of the lease: a rank of a previous holder cannot commit while the new one
/// is still starting.
#[tokio::test]
async fn a_new_holder_fences_off_the_previous_holders_ranks_at_once() {
    use osrt_run::lease::{Holder, Lease, LeaseTiming};
    let (_chaos, run) = run_with_checkpoints(&[]).await;
    let lease = Lease::acquire_fencing(
        &run,
        Holder::this_process("j"),
        LeaseTiming::default(),
        false,
        5,
    )
    .await
    .unwrap();
    let st = state(11);
    let files = || files_of(&st, 1);
    let e = checkpoint::commit(&run, &st, files(), Some(4))
        .await
        .unwrap_err();
    assert!(e.to_string().contains("generation 5"), "{e}");
    assert_eq!(
        checkpoint::commit(&run, &st, files(), Some(5))
            .await
            .unwrap(),
        11
    );
    lease.release().await.unwrap();
}
