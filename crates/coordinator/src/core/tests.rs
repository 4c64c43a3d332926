//! The state machine's unit tests: membership, generations, plans, records, hashes.

use super::*;
use osrt_proto::convert::{Directive, PlanState};
use osrt_proto::{MAX_RECORDS_PER_REPORT, PROTOCOL_VERSION};
use std::time::Duration;

pub(super) fn spec(min: usize, max: usize, restarts: u32) -> JobSpec {
    // The `tiny` preset's cluster table: short timeouts, frequent hashes and checkpoints.
    let cluster = ClusterConfig {
        min_workers: min,
        max_workers: max,
        max_restarts: restarts,
        join_grace_s: 0.0,
        hash_every: 1,
        checkpoint_every: 5,
        heartbeat_timeout_s: 3.0,
        rpc_timeout_s: 5.0,
        ..Default::default()
    };
    JobSpec {
        job_id: "j".into(),
        job_toml: "[cluster]\n".into(),
        cluster,
        data: "data".into(),
        run: "run".into(),
        max_steps: Some(10),
        deadline_unix_s: None,
        cluster_overrides: ClusterOverrides::default(),
    }
}

fn prog(
    id: u64,
    generation: u64,
    rank: usize,
    step: u64,
    hash: Option<&str>,
    records: Vec<String>,
) -> Progress {
    Progress {
        worker_id: id,
        generation,
        rank,
        step,
        param_hash: hash.map(str::to_string),
        records,
    }
}

fn registration(protocol_version: u32, name: &str, addr: &str) -> Registration {
    Registration {
        protocol_version,
        name: name.into(),
        addr: addr.into(),
        threads: 1,
        instance: 0,
    }
}

/// A tick, and the service's discard of an abandoned timeline done at once.
pub(super) fn tick(c: &mut Core, now: Instant) {
    c.tick(now);
    if c.discard_pending {
        c.discarded();
    }
}

pub(super) fn reg(c: &mut Core, now: Instant) -> u64 {
    c.register(registration(PROTOCOL_VERSION, "w", "http://x:1"), now)
        .unwrap()
}

#[test]
fn a_generation_forms_at_min_workers_and_ranks_follow_registration() {
    let t = Instant::now();
    let mut c = Core::new(spec(2, 2, 3), t);
    let a = reg(&mut c, t);
    tick(&mut c, t);
    assert!(matches!(c.phase, Phase::Waiting { .. }));
    assert_eq!(c.plan(a, 0, t).unwrap(), PlanState::Waiting);
    let b = reg(&mut c, t);
    c.tick(t);
    assert_eq!(c.phase, Phase::Running);
    // No plan before the abandoned timeline's checkpoints are gone.
    assert!(c.discard_pending);
    assert_eq!(c.plan(b, 0, t).unwrap(), PlanState::Waiting);
    c.discarded();
    let PlanState::Running(p) = c.plan(b, 0, t).unwrap() else {
        panic!()
    };
    assert_eq!(
        (p.rank, p.world(), p.generation, p.resume_step),
        (1, 2, 1, None)
    );
    // Already running this generation: wait for a newer one.
    assert_eq!(c.plan(b, 1, t).unwrap(), PlanState::Waiting);
}

#[test]
fn a_lost_member_restarts_survivors_from_the_last_checkpoint() {
    let t = Instant::now();
    let mut c = Core::new(spec(1, 2, 3), t);
    let a = reg(&mut c, t);
    let b = reg(&mut c, t);
    tick(&mut c, t);
    c.checkpoint(a, 1, 5, false, t).unwrap();
    for s in [0, 5, 6] {
        let line = format!("{{\"loss\":0.5,\"step\":{s}}}");
        c.progress(prog(a, 1, 0, s, None, vec![line]), t).unwrap();
    }
    let later = t + Duration::from_secs(4);
    assert_eq!(c.heartbeat(a, 1, 6, later).unwrap().0, Directive::Continue);
    tick(&mut c, later);
    assert!(!c.members.contains_key(&b), "b timed out");
    assert_eq!(c.restarts, 1);
    assert_eq!(c.heartbeat(a, 1, 6, later).unwrap().0, Directive::Restart);
    tick(&mut c, later);
    let PlanState::Running(p) = c.plan(a, 1, later).unwrap() else {
        panic!()
    };
    assert_eq!((p.generation, p.world(), p.resume_step), (2, 1, Some(5)));
    let steps: Vec<u64> = c.records.iter().map(|(s, _)| *s).collect();
    assert_eq!(steps, vec![0, 5], "records past the checkpoint are dropped");
    // A resent report (its answer was lost) does not repeat records.
    let resent = vec![
        "{\"loss\":0.5,\"step\":5}".to_string(),
        "{\"loss\":0.5,\"step\":7}".to_string(),
    ];
    c.progress(prog(a, 2, 0, 7, None, resent), later).unwrap();
    let steps: Vec<u64> = c.records.iter().map(|(s, _)| *s).collect();
    assert_eq!(steps, vec![0, 5, 7]);
    // The unknown (timed-out) worker is told to register again.
    assert_eq!(
        c.heartbeat(b, 1, 6, later).unwrap_err().code(),
        tonic::Code::NotFound
    );
}

#[test]
fn a_failed_round_does_not_re_admit_a_silent_peer() {
    let t = Instant::now();
    let mut c = Core::new(spec(1, 2, 3), t);
    let a = reg(&mut c, t);
    let b = reg(&mut c, t);
    tick(&mut c, t);
    c.checkpoint(a, 1, 5, false, t).unwrap();
    // b died; a's round fails and a reports it at once, long before b times out.
    let t1 = t + Duration::from_millis(500);
    c.fault(a, 1, "sending to rank 1 failed", false, false, t1)
        .unwrap();
    let t2 = t1 + Duration::from_millis(1100);
    c.plan(a, 1, t2).unwrap();
    tick(&mut c, t2);
    let PlanState::Running(p) = c.plan(a, 1, t2).unwrap() else {
        panic!("{:?}", c.phase)
    };
    assert_eq!((p.world(), p.generation, p.resume_step), (1, 2, Some(5)));
    assert_eq!(c.restarts, 1);
    // A late report of generation 1's next checkpoint does not move generation 2's
    // starting point.
    c.checkpoint(a, 1, 10, false, t2).unwrap();
    assert_eq!(c.last_checkpoint, Some(5));
    let _ = b;
}

/// A coordinator restarted while a worker was paused issues new ids: the paused
/// worker's old id is unknown to it (so that worker registers again) even after
/// another worker registered with the new coordinator.
#[test]
fn a_restarted_coordinator_never_reissues_an_earlier_incarnations_ids() {
    let t = Instant::now();
    let mut first = Core::with_incarnation(spec(2, 2, 3), 7, t);
    let paused = reg(&mut first, t);
    let other = reg(&mut first, t);
    let mut second = Core::with_incarnation(spec(2, 2, 3), 8, t);
    let again = reg(&mut second, t);
    assert_ne!(again, paused);
    assert_ne!(again, other);
    for id in [paused, other] {
        let e = second.heartbeat(id, 1, 3, t).unwrap_err();
        assert_eq!(e.code(), tonic::Code::NotFound);
        let e = second.plan(id, 1, t).unwrap_err();
        assert_eq!(e.code(), tonic::Code::NotFound);
    }
    // Two coordinators started independently draw different incarnations.
    let ids: std::collections::BTreeSet<u64> = (0..2)
        .map(|_| reg(&mut Core::new(spec(1, 9, 0), t), t))
        .collect();
    assert_eq!(ids.len(), 2, "random incarnations: {ids:?}");
}

/// Too few workers: the waiting phase ends in a clear failure, not a wait forever.
#[test]
fn waiting_for_too_few_workers_fails_after_the_wait_timeout() {
    let t = Instant::now();
    let mut c = Core::new(spec(2, 2, 3), t);
    let limit = c.spec.cluster.wait_timeout_s;
    let a = reg(&mut c, t);
    let before = t + Duration::from_secs_f64(limit * 0.9);
    c.heartbeat(a, 0, 0, before).unwrap();
    tick(&mut c, before);
    assert!(matches!(c.phase, Phase::Waiting { .. }));
    let after = t + Duration::from_secs_f64(limit + 1.0);
    c.heartbeat(a, 0, 0, after).unwrap();
    tick(&mut c, after);
    let Phase::Failed(m) = &c.phase else {
        panic!("{:?}", c.phase)
    };
    assert!(
        m.contains("cluster.wait_timeout_s") && m.contains("1 took part"),
        "{m}"
    );
    assert_eq!(c.heartbeat(a, 0, 0, after).unwrap().0, Directive::Stop);
    // With nobody at all (a finished job resumed with no workers) as well.
    let mut c = Core::new(spec(1, 2, 3), t);
    tick(&mut c, after);
    assert!(matches!(c.phase, Phase::Failed(_)), "{:?}", c.phase);
}

/// `--resume` is a new invocation: the restarts of earlier ones do not count against
/// its budget; a coordinator restarted after a crash keeps counting.
#[test]
fn a_resumed_job_gets_a_fresh_restart_budget() {
    let t = Instant::now();
    for (resume, fails) in [(true, false), (false, true)] {
        let mut c = Core::new(spec(1, 1, 1), t);
        let mut p = c.persisted();
        p.restarts = 1;
        c.restore(&p, None, Some(5), resume, t);
        let a = reg(&mut c, t);
        tick(&mut c, t);
        c.fault(a, c.generation, "boom", false, false, t).unwrap();
        assert_eq!(c.restarts, 2);
        assert_eq!(
            matches!(c.phase, Phase::Failed(_)),
            fails,
            "resume {resume}"
        );
    }
}

/// Records are handed to `metrics.jsonl` as appends and forgotten once the event log has
/// them too (memory stays bounded); a new generation from an older checkpoint cuts what
/// either holds past it.
#[test]
fn records_are_handed_over_once_and_cut_where_they_went() {
    let t = Instant::now();
    let mut c = Core::new(spec(1, 2, 3), t);
    let a = reg(&mut c, t);
    tick(&mut c, t);
    let line = |s: u64| format!("{{\"loss\":0.5,\"step\":{s}}}");
    let lines = |steps: &[u64]| steps.iter().map(|&s| (s, line(s))).collect::<Vec<_>>();
    let report = |c: &mut Core, g: u64, steps: std::ops::RangeInclusive<u64>| {
        let lines = steps.clone().map(line).collect();
        c.progress(prog(a, g, 0, *steps.end(), None, lines), t)
            .unwrap();
    };
    report(&mut c, 1, 1..=2);
    let w = c.metrics_write();
    assert_eq!((w.cut_after, w.lines), (None, lines(&[1, 2])));
    assert_eq!(c.records.len(), 2, "the event log has not taken them yet");
    report(&mut c, 1, 3..=3);
    assert_eq!(c.metrics_write().lines, lines(&[3]));
    assert_eq!(c.events_work().records.len(), 3);
    assert!(c.records.is_empty(), "delivered to both: forgotten");
    report(&mut c, 1, 4..=4);
    assert_eq!(c.metrics_write().lines, lines(&[4]));
    // A resent report repeats nothing, though its records are forgotten.
    report(&mut c, 1, 3..=4);
    assert!(!c.dirty_metrics && c.records.len() == 1);
    // A new generation from checkpoint 2 drops 3 and 4 from both logs.
    c.checkpoint(a, 1, 2, false, t).unwrap();
    c.fault(a, 1, "boom", false, false, t).unwrap();
    tick(&mut c, t);
    assert!(c.records.is_empty(), "{:?}", c.records);
    let w = c.metrics_write();
    assert_eq!((w.cut_after, w.lines), (Some(Some(2)), vec![]));
    let e = c.events_work();
    assert_eq!((e.cut_after, e.records.len()), (Some(Some(2)), 0));
    // The replayed steps are taken again.
    report(&mut c, 2, 3..=3);
    assert_eq!(c.metrics_write().lines, lines(&[3]));
}

/// A worker that leaves is dropped at once: the next generation forms without it,
/// not with a dead member that fails its first round.
#[test]
fn a_leaving_worker_is_dropped_at_once() {
    let t = Instant::now();
    let mut c = Core::new(spec(2, 3, 5), t);
    let a = reg(&mut c, t);
    let b = reg(&mut c, t);
    tick(&mut c, t);
    assert_eq!(c.phase, Phase::Running);
    c.fault(b, 1, "stopped by a signal", false, true, t)
        .unwrap();
    assert!(!c.members.contains_key(&b));
    assert_eq!(c.restarts, 1);
    let d = reg(&mut c, t);
    tick(&mut c, t);
    let PlanState::Running(p) = c.plan(a, 1, t).unwrap() else {
        panic!("{:?}", c.phase)
    };
    assert_eq!((p.generation, p.world()), (2, 2));
    assert!(c.ring.contains(&d) && !c.ring.contains(&b));
}

#[test]
fn a_report_may_carry_a_bounded_number_of_records() {
    let t = Instant::now();
    let mut c = Core::new(spec(1, 1, 1), t);
    let a = reg(&mut c, t);
    tick(&mut c, t);
    let many = vec!["{\"loss\":0.5,\"step\":1}".to_string(); MAX_RECORDS_PER_REPORT + 1];
    let e = c.progress(prog(a, 1, 0, 1, None, many), t).unwrap_err();
    assert_eq!(e.code(), tonic::Code::InvalidArgument);
    assert!(c.records.is_empty());
}

#[test]
fn cluster_overrides_apply_and_keep_max_at_least_min() {
    let mut c = ClusterConfig {
        max_workers: 2,
        ..Default::default()
    };
    let o = ClusterOverrides {
        min_workers: Some(3),
        max_workers: None,
        max_restarts: Some(9),
    };
    o.apply(&mut c);
    assert_eq!((c.min_workers, c.max_workers, c.max_restarts), (3, 3, 9));
    ClusterOverrides {
        max_workers: Some(5),
        ..Default::default()
    }
    .apply(&mut c);
    assert_eq!((c.min_workers, c.max_workers, c.max_restarts), (3, 5, 9));
}

/// Diverged replicas restart from the last checkpoint (a restart); once the budget
/// is spent, the job fails and says why.
#[test]
fn diverged_hashes_restart_from_the_checkpoint_and_equal_ones_count() {
    let t = Instant::now();
    let mut c = Core::new(spec(2, 2, 1), t);
    let a = reg(&mut c, t);
    let b = reg(&mut c, t);
    tick(&mut c, t);
    c.checkpoint(a, 1, 1, false, t).unwrap();
    c.progress(prog(a, 1, 0, 1, Some("aa"), vec![]), t).unwrap();
    c.progress(prog(b, 1, 1, 1, Some("aa"), vec![]), t).unwrap();
    assert_eq!(c.hash_checks, 1);
    c.progress(prog(a, 1, 0, 2, Some("aa"), vec![]), t).unwrap();
    let d = c.progress(prog(b, 1, 1, 2, Some("bb"), vec![]), t).unwrap();
    assert_eq!(d, Directive::Restart);
    assert_eq!(c.restarts, 1);
    tick(&mut c, t);
    let PlanState::Running(p) = c.plan(a, 1, t).unwrap() else {
        panic!("{:?}", c.phase)
    };
    assert_eq!((p.generation, p.resume_step), (2, Some(1)));
    c.progress(prog(a, 2, 0, 2, Some("aa"), vec![]), t).unwrap();
    let d = c.progress(prog(b, 2, 1, 2, Some("cc"), vec![]), t).unwrap();
    assert_eq!(d, Directive::Stop);
    let Phase::Failed(m) = &c.phase else { panic!() };
    assert!(m.contains("replicas diverged at step 2"), "{m}");
    assert!(m.contains("gave up after 1 restarts"), "{m}");
}

#[test]
fn restarts_are_bounded_and_bad_registrations_refused() {
    let t = Instant::now();
    let mut c = Core::new(spec(1, 1, 1), t);
    let e = c
        .register(registration(99, "w", "http://x:1"), t)
        .unwrap_err();
    assert_eq!(e.code(), tonic::Code::FailedPrecondition);
    let a = reg(&mut c, t);
    let e = c
        .register(registration(PROTOCOL_VERSION, "w", "http://y:1"), t)
        .unwrap_err();
    assert_eq!(e.code(), tonic::Code::ResourceExhausted);
    tick(&mut c, t);
    c.fault(a, 1, "boom", false, false, t).unwrap();
    assert_eq!(c.restarts, 1);
    tick(&mut c, t);
    c.fault(a, 2, "boom again", false, false, t).unwrap();
    let Phase::Failed(m) = &c.phase else { panic!() };
    assert!(m.contains("gave up after 1 restarts"), "{m}");
    assert_eq!(c.heartbeat(a, 2, 0, t).unwrap().0, Directive::Stop);
    // A final checkpoint of the current generation finishes a job.
    let mut c = Core::new(spec(1, 1, 1), t);
    let a = reg(&mut c, t);
    tick(&mut c, t);
    c.checkpoint(a, 1, 10, true, t).unwrap();
    assert_eq!(c.phase, Phase::Done);
    assert_eq!(c.plan(a, 1, t).unwrap(), PlanState::Done);
}

/// A ring never outgrows the global batch: with a batch of 2 scenes the ring forms at 2
/// workers without waiting for more, and a third registration is refused, saying why.
#[test]
fn the_ring_is_capped_at_the_global_batch() {
    let t = Instant::now();
    let mut s = spec(1, 64, 3);
    s.cluster.join_grace_s = 3600.0;
    s.job_toml = "[train]\nbatch_size = 2\n\n[cluster]\n".into();
    let mut c = Core::new(s, t);
    assert_eq!(c.batch, Some(2));
    reg(&mut c, t);
    tick(&mut c, t);
    assert!(
        matches!(c.phase, Phase::Waiting { .. }),
        "one worker waits for the grace"
    );
    reg(&mut c, t);
    tick(&mut c, t);
    assert_eq!(
        c.phase,
        Phase::Running,
        "two workers are all the batch can feed"
    );
    assert_eq!(c.ring.len(), 2);
    let e = c
        .register(registration(PROTOCOL_VERSION, "w3", "http://x:1"), t)
        .unwrap_err();
    assert_eq!(e.code(), tonic::Code::ResourceExhausted);
    assert!(e.message().contains("train.batch_size"), "{}", e.message());
}

#[test]
fn an_address_that_names_no_host_is_refused() {
    let t = Instant::now();
    let mut c = Core::new(spec(1, 4, 3), t);
    for addr in ["http://0.0.0.0:7071", "https://[::]:7071"] {
        let e = c
            .register(registration(PROTOCOL_VERSION, "w", addr), t)
            .unwrap_err();
        assert_eq!(e.code(), tonic::Code::InvalidArgument);
        assert!(e.message().contains("--advertise"), "{}", e.message());
    }
    assert!(
        c.register(
            registration(PROTOCOL_VERSION, "w", "http://10.0.0.7:7071"),
            t
        )
        .is_ok()
    );
}

/// A step whose hash one rank never reports (its report was lost) is dropped once a later
/// step completes: the per-step map does not grow with the job.
#[test]
fn hashes_of_steps_that_can_no_longer_complete_are_dropped() {
    let t = Instant::now();
    let mut c = Core::new(spec(2, 2, 1), t);
    let a = reg(&mut c, t);
    let b = reg(&mut c, t);
    tick(&mut c, t);
    for step in 1..=100 {
        c.progress(prog(a, 1, 0, step, Some("h"), vec![]), t)
            .unwrap();
        if step % 10 == 0 {
            c.progress(prog(b, 1, 1, step, Some("h"), vec![]), t)
                .unwrap();
        }
    }
    assert_eq!(c.hash_checks, 10);
    assert!(
        c.hashes.is_empty(),
        "{:?}",
        c.hashes.keys().collect::<Vec<_>>()
    );
}

/// A rank that never reports its hashes (every report lost) leaves every step short:
/// the coordinator holds at most `MAX_PENDING_HASH_STEPS` of them, the newest.
#[test]
fn hashes_a_rank_never_reports_stay_bounded() {
    let t = Instant::now();
    let mut c = Core::new(spec(2, 2, 1), t);
    let a = reg(&mut c, t);
    let _b = reg(&mut c, t);
    tick(&mut c, t);
    for step in 1..=1000 {
        c.progress(prog(a, 1, 0, step, Some("h"), vec![]), t)
            .unwrap();
    }
    assert_eq!(c.hashes.len(), MAX_PENDING_HASH_STEPS);
    assert_eq!(
        c.hashes.keys().next(),
        Some(&(1001 - MAX_PENDING_HASH_STEPS as u64))
    );
}

/// A worker that registers again because the reply was lost (same instance) is the same
/// member: no second id, no ghost in the ring; another instance is a new member.
#[test]
fn a_repeated_registration_of_one_instance_is_one_member() {
    let t = Instant::now();
    let mut c = Core::new(spec(1, 4, 3), t);
    let r = Registration {
        instance: 7,
        ..registration(PROTOCOL_VERSION, "w", "http://x:1")
    };
    let a = c.register(r.clone(), t).unwrap();
    assert_eq!(c.register(r.clone(), t).unwrap(), a);
    assert_eq!(c.members.len(), 1);
    tick(&mut c, t + Duration::from_secs(2));
    assert_eq!(c.phase, Phase::Running);
    assert_eq!(c.ring, vec![a]);
    let generation = c.generation;
    assert_eq!(c.register(r.clone(), t).unwrap(), a);
    assert_eq!(c.generation, generation, "no new generation for a repeat");
    let b = c.register(Registration { instance: 8, ..r }, t).unwrap();
    assert_ne!(a, b);
    assert_eq!(c.members.len(), 2);
}

/// A generation that ends while rank 0 commits a checkpoint: rank 0's late report (its
/// answer says restart) still delivers the records before that checkpoint, which the
/// coordinator then accepts, so the next generation, resuming from it, leaves no gap.
#[test]
fn the_ended_generations_last_records_count_with_its_last_checkpoint() {
    let t = Instant::now();
    let mut c = Core::new(spec(2, 3, 5), t);
    let a = reg(&mut c, t);
    let b = reg(&mut c, t);
    tick(&mut c, t);
    let line = |s: u64| format!("{{\"loss\":0.5,\"step\":{s}}}");
    c.progress(prog(a, 1, 0, 9, None, vec![line(9)]), t)
        .unwrap();
    c.fault(b, 1, "stopped by a signal", false, true, t)
        .unwrap();
    // Rank 0's report of step 10, answered after the generation ended.
    let d = c.progress(prog(a, 1, 0, 10, None, vec![line(10), line(11)]), t);
    assert_eq!(d.unwrap(), Directive::Restart);
    c.checkpoint(a, 1, 10, false, t).unwrap();
    // Any other member's late records do not count.
    let d = c.progress(prog(b, 1, 0, 12, None, vec![line(12)]), t);
    assert!(d.is_err() || d.unwrap() == Directive::Restart);
    let _d = reg(&mut c, t);
    tick(&mut c, t);
    assert_eq!(c.resume_step, Some(10));
    let steps: Vec<u64> = c.metrics_write().lines.iter().map(|(s, _)| *s).collect();
    assert_eq!(steps, [9, 10], "11 is past the checkpoint");
}
