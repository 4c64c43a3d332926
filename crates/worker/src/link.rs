//! A worker's reports to the coordinator within one generation: progress (the step, the
//! parameter hash, rank 0's records), checkpoints and faults, each naming the job, the
//! worker and the generation the link was made for; the client they go through, and
//! how a call is retried while the coordinator is unreachable.

use crate::error::{Result, WorkerError};
use osrt_proto::auth::AttachToken;
use osrt_proto::convert::{Directive, WorkerPlan};
use osrt_proto::credentials::Credentials;
use osrt_proto::v1::coordinator_client::CoordinatorClient;
use osrt_proto::{MAX_RECORDS_PER_REPORT, v1};
use osrt_retry::RetryPolicy;
use osrt_run::MetricsRecord;
use std::time::Duration;
use tonic::service::interceptor::InterceptedService;
use tonic::transport::Channel;

pub type Client = CoordinatorClient<InterceptedService<Channel, AttachToken>>;

/// Connects to the coordinator with the job's token on every call.
pub fn coordinator_client(addr: &str, credentials: &Credentials) -> Result<Client> {
    let endpoint = credentials
        .endpoint(addr)
        .map_err(|e| WorkerError::Cluster(format!("coordinator address {addr}: {e}")))?;
    let endpoint = endpoint
        .connect_timeout(Duration::from_secs(5))
        .timeout(Duration::from_secs(30))
        .http2_keep_alive_interval(osrt_proto::KEEP_ALIVE_INTERVAL)
        .keep_alive_timeout(osrt_proto::KEEP_ALIVE_TIMEOUT)
        .keep_alive_while_idle(true)
        .tcp_nodelay(true);
    Ok(CoordinatorClient::with_interceptor(
        endpoint.connect_lazy(),
        credentials.attach(),
    ))
}

/// Whether a failed call may succeed if made again: the coordinator unreachable or busy,
/// or the connection lost during the call (tonic then answers `Unknown`, or `Cancelled`
/// when hyper saw the connection close, with the transport error as the source; a
/// `Cancelled` the coordinator itself sent has no such source).
fn is_transient(s: &tonic::Status) -> bool {
    use std::error::Error;
    match s.code() {
        tonic::Code::Unavailable
        | tonic::Code::DeadlineExceeded
        | tonic::Code::ResourceExhausted => true,
        tonic::Code::Unknown | tonic::Code::Cancelled => s
            .source()
            .is_some_and(|e| e.downcast_ref::<tonic::transport::Error>().is_some()),
        _ => false,
    }
}

/// Retries `f` while the coordinator is unreachable, up to `limit`.
pub async fn with_retry<T, F, Fut>(limit: Duration, what: &str, f: F) -> Result<T>
where
    F: FnMut() -> Fut,
    Fut: std::future::Future<Output = std::result::Result<T, tonic::Status>>,
{
    // Unreachable, cut off mid-call, or full until a lost member times out: all pass.
    // (Every call retried here is idempotent on the coordinator.) Tried every 250 ms: a
    // restarted coordinator is found at once.
    RetryPolicy::every(Duration::from_millis(250), limit)
        .run(what, is_transient, f)
        .await
        .map_err(|s| WorkerError::Coordinator {
            what: what.to_string(),
            code: s.code(),
            message: s.message().to_string(),
        })
}

/// How long a checkpoint report is retried while the coordinator is unreachable: a
/// dropped connection passes within it; a coordinator gone for longer fails the
/// generation (a restarted one does not know this worker anyway).
pub const CHECKPOINT_REPORT_RETRY: Duration = Duration::from_secs(10);

/// The coordinator as one member of one generation speaks to it.
#[derive(Clone)]
pub struct CoordinatorLink {
    client: Client,
    plan: WorkerPlan,
    worker_id: u64,
}

impl CoordinatorLink {
    pub fn new(client: Client, plan: &WorkerPlan, worker_id: u64) -> Self {
        Self {
            client,
            plan: plan.clone(),
            worker_id,
        }
    }

    /// Reports a fault of this generation (`fatal`: the job cannot go on; `leaving`: this
    /// worker leaves it); a report that fails is logged, not retried.
    pub async fn fault(&mut self, reason: &str, fatal: bool, leaving: bool) {
        let r = self
            .client
            .report_fault(v1::FaultReport {
                job: self.plan.job.clone(),
                worker_id: self.worker_id,
                generation: self.plan.generation,
                reason: reason.to_string(),
                fatal,
                leaving,
            })
            .await;
        if let Err(s) = r {
            tracing::warn!(status = %s, "could not report the fault");
        }
    }

    /// Reports a step's parameter hash and the records not yet delivered (`unsent`,
    /// emptied once delivered; beyond [`MAX_RECORDS_PER_REPORT`] the oldest are dropped);
    /// returns the coordinator's answer (`None`: not delivered).
    pub async fn step(
        &mut self,
        step: u64,
        hash: Option<String>,
        unsent: &mut Vec<MetricsRecord>,
    ) -> Option<Directive> {
        if unsent.len() > MAX_RECORDS_PER_REPORT {
            let dropped = unsent.len() - MAX_RECORDS_PER_REPORT;
            tracing::warn!(
                dropped,
                "the coordinator took no records for long: oldest dropped"
            );
            unsent.drain(..dropped);
        }
        let r = self
            .client
            .report_progress(self.progress(step, hash, unsent))
            .await;
        let directive = match r {
            Ok(a) => Directive::try_from(a.into_inner().action).ok(),
            Err(s) => {
                tracing::warn!(status = %s, "progress report failed");
                None
            }
        };
        if directive.is_some() {
            unsent.clear();
        }
        directive
    }

    /// Delivers records up to checkpoint `step` that earlier reports could not, retrying
    /// within [`CHECKPOINT_REPORT_RETRY`]; an error unless the coordinator takes them and
    /// the generation goes on.
    pub async fn held_records(&self, step: u64, records: &[MetricsRecord]) -> Result<()> {
        let sent = with_retry(CHECKPOINT_REPORT_RETRY, "sending held records", || {
            let mut c = self.client.clone();
            let r = self.progress(step, None, records);
            async move { c.report_progress(r).await }
        })
        .await?;
        if Directive::try_from(sent.into_inner().action) != Ok(Directive::Continue) {
            return Err(WorkerError::Cluster(format!(
                "the coordinator took no records before checkpoint {step}: generation over"
            )));
        }
        Ok(())
    }

    /// Tells the coordinator that checkpoint `step` is committed (`last`: the job's
    /// final one), retrying within [`CHECKPOINT_REPORT_RETRY`].
    pub async fn checkpoint(&self, step: u64, last: bool) -> Result<()> {
        let report = v1::CheckpointReport {
            job: self.plan.job.clone(),
            worker_id: self.worker_id,
            generation: self.plan.generation,
            step,
            r#final: last,
        };
        let what = format!("reporting checkpoint {step}");
        with_retry(CHECKPOINT_REPORT_RETRY, &what, || {
            let mut c = self.client.clone();
            let r = report.clone();
            async move { c.report_checkpoint(r).await.map(|_| ()) }
        })
        .await
    }

    fn progress(
        &self,
        step: u64,
        param_hash: Option<String>,
        records: &[MetricsRecord],
    ) -> v1::ProgressReport {
        v1::ProgressReport {
            job: self.plan.job.clone(),
            worker_id: self.worker_id,
            generation: self.plan.generation,
            rank: self.plan.rank as u32,
            step,
            param_hash,
            records: records.iter().map(MetricsRecord::to_line).collect(),
        }
    }
}
