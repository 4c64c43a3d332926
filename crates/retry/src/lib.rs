//! The one retry policy of the project: after a failure that may pass, wait (starting at
//! `first`, doubling up to `max`) and try again, until `budget` has been spent failing;
//! then the error stands. Store reads, coordinator calls and the coordinator's writes of
//! the run folder each pick their figures; the mechanism is this.

use std::future::Future;
use std::time::{Duration, Instant};

/// When to try again after failures.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RetryPolicy {
    /// The wait after the first failure.
    pub first: Duration,
    /// The longest wait (each failure doubles the last one up to this).
    pub max: Duration,
    /// How long calls may keep failing before the error stands.
    pub budget: Duration,
}

impl RetryPolicy {
    /// 0.2 s doubling to 5 s within `budget`: for stores, whose outages last seconds.
    pub fn backoff(budget: Duration) -> Self {
        Self {
            first: Duration::from_millis(200),
            max: Duration::from_secs(5),
            budget,
        }
    }

    /// Every `wait` within `budget`: for a peer that comes back any moment and must be
    /// found soon when it does (a restarted coordinator).
    pub fn every(wait: Duration, budget: Duration) -> Self {
        Self {
            first: wait,
            max: wait,
            budget,
        }
    }

    /// Runs `call` until it succeeds, fails with an error `transient` calls permanent,
    /// or the budget is spent; each retried failure is logged as `what`.
    pub async fn run<T, E, F, Fut>(
        &self,
        what: &str,
        transient: impl Fn(&E) -> bool,
        mut call: F,
    ) -> Result<T, E>
    where
        E: std::fmt::Display,
        F: FnMut() -> Fut,
        Fut: Future<Output = Result<T, E>>,
    {
        let mut state = Failing::default();
        loop {
            match call().await {
                Ok(v) => {
                    if state.failures > 0 {
                        tracing::info!(what, failures = state.failures, "succeeded after retries");
                    }
                    return Ok(v);
                }
                Err(e) if transient(&e) => match state.failed(self) {
                    Some(wait) => {
                        // Retries a second or less apart (a peer polled) would flood the
                        // log at warning level.
                        if self.max <= Duration::from_secs(1) {
                            tracing::debug!(what, error = %e, retry_in = ?wait, "failed; retrying");
                        } else {
                            tracing::warn!(what, error = %e, retry_in = ?wait, "failed; retrying");
                        }
                        tokio::time::sleep(wait).await;
                    }
                    None => return Err(e),
                },
                Err(e) => return Err(e),
            }
        }
    }
}

/// Failures so far under a [`RetryPolicy`], for callers that retry on their own clock
/// (the coordinator's loop): when the next try is due, and whether to give up.
#[derive(Debug, Default)]
pub struct Failing {
    since: Option<Instant>,
    wait: Duration,
    next_try: Option<Instant>,
    failures: u32,
}

impl Failing {
    /// Whether a try is due (no failure pending, or its wait has passed).
    pub fn due(&self) -> bool {
        self.next_try.is_none_or(|t| Instant::now() >= t)
    }

    /// Counts a failure: the wait before the next try, or `None` once `policy`'s budget
    /// is spent (the error then stands).
    pub fn failed(&mut self, policy: &RetryPolicy) -> Option<Duration> {
        let since = *self.since.get_or_insert_with(Instant::now);
        self.wait = if self.failures == 0 {
            policy.first
        } else {
            (self.wait * 2).min(policy.max)
        };
        self.failures += 1;
        if since.elapsed() + self.wait >= policy.budget {
            return None;
        }
        self.next_try = Some(Instant::now() + self.wait);
        Some(self.wait)
    }

    /// A success: the next failure starts over. Returns how long the calls had been
    /// failing, if they had.
    pub fn succeeded(&mut self) -> Option<Duration> {
        let was = self.since.take().map(|s| s.elapsed());
        *self = Self::default();
        was
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::cell::Cell;

    #[test]
    fn waits_double_up_to_the_most_and_the_budget_ends_them() {
        let p = RetryPolicy {
            first: Duration::from_millis(10),
            max: Duration::from_millis(35),
            budget: Duration::from_secs(3600),
        };
        let mut f = Failing::default();
        let waits: Vec<u128> = (0..4).map(|_| f.failed(&p).unwrap().as_millis()).collect();
        assert_eq!(waits, [10, 20, 35, 35]);
        assert!(!f.due(), "a wait is pending");
        assert!(f.succeeded().is_some());
        assert!(f.due());
        assert_eq!(f.failed(&p), Some(Duration::from_millis(10)), "starts over");
        let spent = RetryPolicy {
            budget: Duration::ZERO,
            ..p
        };
        assert_eq!(Failing::default().failed(&spent), None);
    }

    #[tokio::test]
    async fn transient_errors_are_retried_permanent_ones_are_not() {
        let p = RetryPolicy::every(Duration::from_millis(1), Duration::from_secs(10));
        let calls = Cell::new(0);
        let transient = |e: &String| e == "transient";
        let got = p
            .run("call", transient, || {
                calls.set(calls.get() + 1);
                let n = calls.get();
                async move {
                    if n < 3 {
                        Err("transient".to_string())
                    } else {
                        Ok(n)
                    }
                }
            })
            .await;
        assert_eq!(got, Ok(3));
        calls.set(0);
        let got: Result<(), String> = p
            .run("call", transient, || {
                calls.set(calls.get() + 1);
                async { Err("permanent".to_string()) }
            })
            .await;
        assert_eq!((got, calls.get()), (Err("permanent".into()), 1));
        let short = RetryPolicy::every(Duration::from_millis(20), Duration::from_millis(50));
        calls.set(0);
        let got: Result<(), String> = short
            .run("call", transient, || {
                calls.set(calls.get() + 1);
                async { Err("transient".to_string()) }
            })
            .await;
        assert!(got.is_err() && calls.get() >= 2, "{}", calls.get());
    }
}
