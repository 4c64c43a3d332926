//! Protocol messages ↔ domain types, in one place. proto3 makes every field optional on
//! the wire; these conversions turn "absent", "unspecified" and "out of range" into typed
//! errors instead of silent defaults.

use crate::v1;
use thiserror::Error;

#[derive(Debug, Error, PartialEq)]
pub enum ConvertError {
    #[error("{message}: missing field `{field}`")]
    Missing {
        message: &'static str,
        field: &'static str,
    },
    #[error("{message}: field `{field}`: {reason}")]
    Invalid {
        message: &'static str,
        field: &'static str,
        reason: String,
    },
}

fn missing(message: &'static str, field: &'static str) -> ConvertError {
    ConvertError::Missing { message, field }
}

fn invalid(message: &'static str, field: &'static str, reason: String) -> ConvertError {
    ConvertError::Invalid {
        message,
        field,
        reason,
    }
}

/// What one member runs in one generation.
#[derive(Debug, Clone, PartialEq)]
pub struct WorkerPlan {
    pub job: String,
    pub generation: u64,
    pub rank: usize,
    /// Collective addresses in ring order.
    pub peers: Vec<String>,
    pub job_config_toml: String,
    pub data: String,
    pub run: String,
    pub resume_step: Option<u64>,
    pub max_steps: Option<u64>,
    pub deadline_unix_s: Option<f64>,
    /// Generations formed again before this one.
    pub restarts: u32,
}

impl WorkerPlan {
    pub fn world(&self) -> usize {
        self.peers.len()
    }
}

/// The answer to a plan request.
#[derive(Debug, Clone, PartialEq)]
pub enum PlanState {
    /// Not enough members yet (or no newer generation): ask again.
    Waiting,
    Running(WorkerPlan),
    Done,
    Failed(String),
}

impl TryFrom<v1::Plan> for PlanState {
    type Error = ConvertError;

    fn try_from(p: v1::Plan) -> Result<Self, ConvertError> {
        const M: &str = "Plan";
        let state = v1::JobState::try_from(p.state)
            .map_err(|_| invalid(M, "state", format!("unknown job state {}", p.state)))?;
        match state {
            v1::JobState::Unspecified => Err(missing(M, "state")),
            v1::JobState::Waiting => Ok(Self::Waiting),
            v1::JobState::Done => Ok(Self::Done),
            v1::JobState::Failed => Ok(Self::Failed(p.message)),
            v1::JobState::Running => {
                if p.job.is_empty() {
                    return Err(missing(M, "job"));
                }
                if p.generation == 0 {
                    return Err(missing(M, "generation"));
                }
                if p.peers.is_empty() {
                    return Err(missing(M, "peers"));
                }
                if p.rank as usize >= p.peers.len() {
                    return Err(invalid(
                        M,
                        "rank",
                        format!("rank {} outside a ring of {}", p.rank, p.peers.len()),
                    ));
                }
                for (field, v) in [
                    ("job_config_toml", &p.job_config_toml),
                    ("data", &p.data),
                    ("run", &p.run),
                ] {
                    if v.is_empty() {
                        return Err(missing(M, field));
                    }
                }
                if let Some(d) = p.deadline_unix_s
                    && !d.is_finite()
                {
                    return Err(invalid(M, "deadline_unix_s", format!("{d} is not finite")));
                }
                Ok(Self::Running(WorkerPlan {
                    job: p.job,
                    generation: p.generation,
                    rank: p.rank as usize,
                    peers: p.peers,
                    job_config_toml: p.job_config_toml,
                    data: p.data,
                    run: p.run,
                    resume_step: p.resume_step,
                    max_steps: p.max_steps,
                    deadline_unix_s: p.deadline_unix_s,
                    restarts: p.restarts,
                }))
            }
        }
    }
}

impl PlanState {
    pub fn into_proto(self, job: &str) -> v1::Plan {
        let base = v1::Plan {
            job: job.to_string(),
            ..Default::default()
        };
        match self {
            Self::Waiting => v1::Plan {
                state: v1::JobState::Waiting as i32,
                ..base
            },
            Self::Done => v1::Plan {
                state: v1::JobState::Done as i32,
                ..base
            },
            Self::Failed(message) => v1::Plan {
                state: v1::JobState::Failed as i32,
                message,
                ..base
            },
            Self::Running(w) => v1::Plan {
                job: w.job,
                state: v1::JobState::Running as i32,
                generation: w.generation,
                rank: w.rank as u32,
                peers: w.peers,
                job_config_toml: w.job_config_toml,
                data: w.data,
                run: w.run,
                resume_step: w.resume_step,
                max_steps: w.max_steps,
                deadline_unix_s: w.deadline_unix_s,
                message: String::new(),
                restarts: w.restarts,
            },
        }
    }
}

/// What the coordinator tells a worker after a heartbeat or report.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Directive {
    Continue,
    Restart,
    Stop,
}

impl TryFrom<i32> for Directive {
    type Error = ConvertError;

    fn try_from(a: i32) -> Result<Self, ConvertError> {
        match v1::Action::try_from(a) {
            Ok(v1::Action::Continue) => Ok(Self::Continue),
            Ok(v1::Action::Restart) => Ok(Self::Restart),
            Ok(v1::Action::Stop) => Ok(Self::Stop),
            Ok(v1::Action::Unspecified) => Err(missing("Ack", "action")),
            Err(_) => Err(invalid("Ack", "action", format!("unknown action {a}"))),
        }
    }
}

impl From<Directive> for v1::Action {
    fn from(d: Directive) -> Self {
        match d {
            Directive::Continue => Self::Continue,
            Directive::Restart => Self::Restart,
            Directive::Stop => Self::Stop,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn running() -> WorkerPlan {
        WorkerPlan {
            job: "j".into(),
            generation: 3,
            rank: 1,
            peers: vec!["http://a:1".into(), "http://b:2".into()],
            job_config_toml: "x = 1".into(),
            data: "data".into(),
            run: "runs/r".into(),
            resume_step: Some(10),
            max_steps: None,
            deadline_unix_s: Some(1.0e9),
            restarts: 2,
        }
    }

    #[test]
    fn plans_round_trip() {
        for s in [
            PlanState::Waiting,
            PlanState::Done,
            PlanState::Failed("why".into()),
            PlanState::Running(running()),
        ] {
            assert_eq!(PlanState::try_from(s.clone().into_proto("j")).unwrap(), s);
        }
    }

    #[test]
    fn missing_and_invalid_fields_are_typed_errors() {
        let mut p = PlanState::Running(running()).into_proto("j");
        p.peers.clear();
        assert_eq!(
            PlanState::try_from(p).unwrap_err(),
            ConvertError::Missing {
                message: "Plan",
                field: "peers"
            }
        );
        let mut p = PlanState::Running(running()).into_proto("j");
        p.rank = 2;
        let e = PlanState::try_from(p).unwrap_err().to_string();
        assert!(e.contains("rank 2 outside a ring of 2"), "{e}");
        let p = v1::Plan::default();
        assert!(matches!(
            PlanState::try_from(p),
            Err(ConvertError::Missing { field: "state", .. })
        ));
        assert!(Directive::try_from(0).is_err());
        assert!(Directive::try_from(99).is_err());
        assert_eq!(Directive::try_from(2).unwrap(), Directive::Restart);
    }
}
