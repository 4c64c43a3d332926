//! A worker's membership of the job: registration with the coordinator, the loop that asks
//! for plans and runs each generation, the heartbeats that tell the coordinator this
//! worker is alive (and tell the worker when its generation ended), and which errors end
//! the worker or only the generation.

use crate::error::{Result, WorkerError};
use crate::generation::{Ended, run_generation};
use crate::link::{Client, CoordinatorLink, with_retry};
use crate::shell::WorkerOptions;
use osrt_collective::Mailbox;
use osrt_proto::convert::{Directive, PlanState, WorkerPlan};
use osrt_proto::{PROTOCOL_VERSION, v1};
use osrt_trainer::TrainError;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

/// This worker process's instance: random, never 0 (0 says "none").
fn instance() -> u64 {
    static INSTANCE: std::sync::OnceLock<u64> = std::sync::OnceLock::new();
    *INSTANCE.get_or_init(|| rand::random::<u64>() | 1)
}

/// Registers with the coordinator, retrying while it is unreachable or the call is cut
/// off; a repeat whose first reply was lost gets the first one's id (same instance).
async fn register(
    opts: &WorkerOptions,
    client: &mut Client,
    collective_addr: &str,
) -> Result<(String, u64)> {
    let req = v1::RegisterRequest {
        protocol_version: PROTOCOL_VERSION,
        name: opts.name.clone(),
        collective_addr: collective_addr.to_string(),
        threads: opts.threads as u32,
        instance: instance(),
    };
    let reply = with_retry(opts.coordinator_timeout, "register", || {
        let mut c = client.clone();
        let r = req.clone();
        async move { c.register(r).await.map(|r| r.into_inner()) }
    })
    .await?;
    tracing::info!(job = %reply.job, worker_id = reply.worker_id, addr = collective_addr, "registered");
    Ok((reply.job, reply.worker_id))
}

/// Who this worker is to the coordinator, and in which generation.
#[derive(Debug, Clone)]
pub(crate) struct Membership {
    pub(crate) job: String,
    pub(crate) worker_id: u64,
    pub(crate) generation: u64,
}

pub(crate) async fn worker_loop(
    opts: &WorkerOptions,
    client: &mut Client,
    mailbox: &Arc<Mailbox>,
    collective_addr: &str,
    member: &Mutex<Option<Membership>>,
) -> Result<()> {
    let note = |job: &str, worker_id: u64, generation: u64| {
        *member.lock().expect("membership") = Some(Membership {
            job: job.to_string(),
            worker_id,
            generation,
        });
    };
    let (mut job, mut worker_id) = register(opts, client, collective_addr).await?;
    note(&job, worker_id, 0);
    mailbox.set_job(&job);
    let mut last_generation = 0;
    loop {
        let req = v1::PlanRequest {
            job: job.clone(),
            worker_id,
            after_generation: last_generation,
        };
        let plan = with_retry(opts.coordinator_timeout, "get plan", || {
            let mut c = client.clone();
            let r = req.clone();
            async move { c.get_plan(r).await.map(|r| r.into_inner()) }
        })
        .await;
        let plan = match plan {
            Ok(p) => p,
            Err(WorkerError::Coordinator {
                code: tonic::Code::NotFound,
                ..
            }) => {
                (job, worker_id) = register(opts, client, collective_addr).await?;
                note(&job, worker_id, 0);
                mailbox.set_job(&job);
                continue;
            }
            Err(e) => return Err(e),
        };
        let plan = PlanState::try_from(plan)
            .map_err(|e| WorkerError::Cluster(format!("bad plan from the coordinator: {e}")))?;
        let plan = match plan {
            PlanState::Waiting => continue,
            PlanState::Done => {
                tracing::info!("job done");
                return Ok(());
            }
            PlanState::Failed(msg) => {
                return Err(WorkerError::Cluster(format!("the job failed: {msg}")));
            }
            PlanState::Running(p) => p,
        };
        last_generation = plan.generation;
        tracing::info!(
            generation = plan.generation,
            rank = plan.rank,
            world = plan.world(),
            resume_step = ?plan.resume_step,
            "starting generation"
        );
        note(&job, worker_id, plan.generation);
        let ended = run_generation(opts, client, mailbox, worker_id, &plan).await;
        match ended {
            Ok(Ended::Finished) => {}
            Ok(Ended::Forgotten) => {
                (job, worker_id) = register(opts, client, collective_addr).await?;
                note(&job, worker_id, 0);
                mailbox.set_job(&job);
                last_generation = 0;
            }
            Ok(Ended::Aborted { reason, report }) => {
                tracing::warn!(generation = plan.generation, %reason, "generation aborted");
                if report {
                    CoordinatorLink::new(client.clone(), &plan, worker_id)
                        .fault(&reason, false, false)
                        .await;
                }
            }
            Err(e) => {
                let reason = e.to_string();
                tracing::error!(generation = plan.generation, %reason, "generation failed");
                // A device this worker cannot use: it leaves, and the job re-forms without it.
                let leaving = matches!(e, WorkerError::Train(TrainError::Device(_)));
                CoordinatorLink::new(client.clone(), &plan, worker_id)
                    .fault(&reason, is_fatal(&e), leaving)
                    .await;
                if is_fatal(&e) || leaving {
                    return Err(e);
                }
            }
        }
    }
}

/// Errors that a restart cannot fix.
pub(crate) fn is_fatal(e: &WorkerError) -> bool {
    matches!(
        e,
        WorkerError::Train(
            TrainError::Config { .. }
                | TrainError::Dataset(_)
                | TrainError::TooManySkips { .. }
                | TrainError::OutOfMemory(_)
        )
    )
}

/// Shared between the training loop and the heartbeat task.
pub(crate) struct Liveness {
    pub(crate) step: AtomicU64,
    pub(crate) abort: Mutex<Option<Ended>>,
}

impl Liveness {
    pub(crate) fn take_abort(&self) -> Option<Ended> {
        self.abort.lock().expect("liveness").take()
    }
}

pub(crate) fn spawn_heartbeat(
    (client, worker_id, every, coordinator_timeout): (Client, u64, Duration, Duration),
    plan: &WorkerPlan,
    live: &Arc<Liveness>,
    mailbox: &Arc<Mailbox>,
) -> tokio::task::JoinHandle<()> {
    let (job, generation) = (plan.job.clone(), plan.generation);
    let (live, mailbox) = (live.clone(), mailbox.clone());
    tokio::spawn(async move {
        let mut last_ok = Instant::now();
        loop {
            tokio::time::sleep(every).await;
            let mut c = client.clone();
            let reply = c
                .heartbeat(v1::HeartbeatRequest {
                    job: job.clone(),
                    worker_id,
                    generation,
                    step: live.step.load(Ordering::Relaxed),
                })
                .await;
            let abort = |why: Ended, msg: &str| {
                *live.abort.lock().expect("liveness") = Some(why);
                mailbox.abort(msg);
            };
            match reply {
                Ok(r) => {
                    last_ok = Instant::now();
                    let r = r.into_inner();
                    match Directive::try_from(r.action) {
                        Ok(Directive::Continue) if r.generation == generation => {}
                        Ok(Directive::Stop) => {
                            abort(
                                Ended::Aborted {
                                    reason: "the coordinator stopped the job".into(),
                                    report: false,
                                },
                                "job stopped",
                            );
                            return;
                        }
                        _ => {
                            let reason = format!(
                                "the coordinator ended generation {generation} (now at {})",
                                r.generation
                            );
                            abort(
                                Ended::Aborted {
                                    reason: reason.clone(),
                                    report: false,
                                },
                                &reason,
                            );
                            return;
                        }
                    }
                }
                Err(s) if s.code() == tonic::Code::NotFound => {
                    abort(
                        Ended::Forgotten,
                        "the coordinator does not know this worker",
                    );
                    return;
                }
                Err(s) => {
                    tracing::warn!(status = %s, "heartbeat failed");
                    if last_ok.elapsed() > coordinator_timeout {
                        abort(
                            Ended::Aborted {
                                reason: format!(
                                    "coordinator unreachable for {coordinator_timeout:?}"
                                ),
                                report: false,
                            },
                            "coordinator unreachable",
                        );
                        return;
                    }
                }
            }
        }
    })
}

/// How a generation ends after `e`: a failed round is an abort to report (or no fault of
/// this rank's, if the coordinator moved on meanwhile); any other error fails it.
pub(crate) fn aborted(live: &Liveness, e: WorkerError) -> Result<Ended> {
    if let Some(a) = live.take_abort() {
        return Ok(a);
    }
    match e {
        WorkerError::Collective(err) => Ok(Ended::Aborted {
            reason: err.to_string(),
            report: true,
        }),
        other => Err(other),
    }
}
