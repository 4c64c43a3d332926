//! The Coordinator gRPC handlers: each checks the job and hands the request to the
//! shared [`Core`](crate::core::Core).

use super::{Shared, status_of};
use crate::core::{Progress, Registration};
use osrt_proto::convert::Directive;
use osrt_proto::v1;
use osrt_proto::v1::coordinator_server;
use std::sync::Arc;
use std::time::{Duration, Instant};
use tonic::{Request, Response, Status};

/// How long a plan request waits for a change before answering `Waiting`.
const PLAN_POLL: Duration = Duration::from_secs(2);

pub(super) struct Service {
    pub(super) shared: Arc<Shared>,
}

impl Service {
    fn check_job(&self, job: &str) -> Result<(), Status> {
        let c = self.shared.core.lock().expect("state");
        if job != c.spec.job_id {
            return Err(Status::permission_denied(format!(
                "message for job `{job}`, this coordinator runs job `{}`",
                c.spec.job_id
            )));
        }
        Ok(())
    }
}

fn ack(d: Directive) -> Response<v1::Ack> {
    Response::new(v1::Ack {
        action: v1::Action::from(d) as i32,
    })
}

#[tonic::async_trait]
impl coordinator_server::Coordinator for Service {
    async fn register(
        &self,
        request: Request<v1::RegisterRequest>,
    ) -> Result<Response<v1::RegisterReply>, Status> {
        let r = request.into_inner();
        let registration = Registration {
            protocol_version: r.protocol_version,
            name: r.name,
            addr: r.collective_addr,
            threads: r.threads,
            instance: r.instance,
        };
        let (id, job) = self.shared.with(|c, now| {
            c.register(registration, now)
                .map(|id| (id, c.spec.job_id.clone()))
        })?;
        Ok(Response::new(v1::RegisterReply { job, worker_id: id }))
    }

    async fn get_plan(
        &self,
        request: Request<v1::PlanRequest>,
    ) -> Result<Response<v1::Plan>, Status> {
        let r = request.into_inner();
        self.check_job(&r.job)?;
        let deadline = tokio::time::Instant::now() + PLAN_POLL;
        loop {
            let notified = self.shared.changed.notified();
            tokio::pin!(notified);
            notified.as_mut().enable();
            let (plan, job) = {
                let mut c = self.shared.core.lock().expect("state");
                let plan = c.plan(r.worker_id, r.after_generation, Instant::now())?;
                (plan, c.spec.job_id.clone())
            };
            let waiting = plan == osrt_proto::convert::PlanState::Waiting;
            if !waiting || tokio::time::timeout_at(deadline, notified).await.is_err() {
                return Ok(Response::new(plan.into_proto(&job)));
            }
        }
    }

    async fn heartbeat(
        &self,
        request: Request<v1::HeartbeatRequest>,
    ) -> Result<Response<v1::HeartbeatReply>, Status> {
        let r = request.into_inner();
        self.check_job(&r.job)?;
        let (d, generation) = self
            .shared
            .with(|c, now| c.heartbeat(r.worker_id, r.generation, r.step, now))?;
        Ok(Response::new(v1::HeartbeatReply {
            action: v1::Action::from(d) as i32,
            generation,
        }))
    }

    async fn report_progress(
        &self,
        request: Request<v1::ProgressReport>,
    ) -> Result<Response<v1::Ack>, Status> {
        let r = request.into_inner();
        self.check_job(&r.job)?;
        let d = self.shared.with(|c, now| {
            c.progress(
                Progress {
                    worker_id: r.worker_id,
                    generation: r.generation,
                    rank: r.rank as usize,
                    step: r.step,
                    param_hash: r.param_hash,
                    records: r.records,
                },
                now,
            )
        })?;
        Ok(ack(d))
    }

    async fn report_checkpoint(
        &self,
        request: Request<v1::CheckpointReport>,
    ) -> Result<Response<v1::Ack>, Status> {
        let r = request.into_inner();
        self.check_job(&r.job)?;
        let d = self
            .shared
            .with(|c, now| c.checkpoint(r.worker_id, r.generation, r.step, r.r#final, now))?;
        Ok(ack(d))
    }

    async fn report_fault(
        &self,
        request: Request<v1::FaultReport>,
    ) -> Result<Response<v1::Ack>, Status> {
        let r = request.into_inner();
        self.check_job(&r.job)?;
        tracing::warn!(worker_id = r.worker_id, generation = r.generation, fatal = r.fatal, reason = %r.reason, "fault reported");
        let d = self.shared.with(|c, now| {
            c.fault(
                r.worker_id,
                r.generation,
                &r.reason,
                r.fatal,
                r.leaving,
                now,
            )
        })?;
        Ok(ack(d))
    }

    async fn get_status(
        &self,
        _request: Request<v1::StatusRequest>,
    ) -> Result<Response<v1::JobStatus>, Status> {
        let c = self.shared.core.lock().expect("state");
        Ok(Response::new(status_of(&c, Instant::now())))
    }
}
